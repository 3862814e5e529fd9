"""Vendor cine files: Elekta Unity `.bin` (MS-NRBF) and DICOM frames read with the right plane, pixels and geometry.

The real frames (three Unity frames, each as `.bin` and as its DICOM export) live in ../shared/data/unity_cine; the
tests that need them skip with the reason when it is absent. The rest build `.bin` streams here with a small writer
that follows the [MS-NRBF] specification record by record (independent of the reader under test).
"""

import json
import os
import shutil
import struct

import numpy as np
import pytest

from conftest import DATA
from warpmpm.cine import plane_name, read_cine, read_frame
from warpmpm.errors import InputError
from warpmpm.nrbf import read_nrbf

UNITY = os.path.join(DATA, "unity_cine")
PLANES = ("sagittal", "coronal", "transversal")
# the README's ImageOrientationPatient of each real frame
IOP = {"sagittal": (0, 1, 0, 0, 0, -1), "coronal": (1, 0, 0, 0, 0, -1), "transversal": (1, 0, 0, 0, 1, 0)}


def unity(name):
    path = os.path.join(UNITY, name)
    if not os.path.exists(path):
        pytest.skip(f"real Unity cine frames are absent ({UNITY}; they live in ../shared/data beside the checkout)")
    return path


# ------------------------------------------------------------------------------------------------
# a minimal MS-NRBF writer (record layouts from the specification, sections 2.1-2.7)
# ------------------------------------------------------------------------------------------------

def lps(s: str) -> bytes:
    b = s.encode("utf-8")
    n, out = len(b), bytearray()
    while True:
        byte = n & 0x7F
        n >>= 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out) + b


class Writer:
    """Class records with typed members (ClassWithMembersAndTypes, record 5); primitives inline, classes nested."""

    def __init__(self):
        self.next_id = 1
        self.out = bytearray()

    def header(self):
        self.out += bytes([0]) + struct.pack("<iiii", 1, -1, 1, 0)
        self.out += bytes([12]) + struct.pack("<i", 2) + lps("Common.Data.DTO, Version=4.4.14.16")

    def obj(self, name, members):
        """members: list of (member name, kind, value); kind: 'i32', 'i64', 'u64', 'f64', 'bool', 'class', 'bytes', 'str', 'null'."""
        oid = self.next_id
        self.next_id += 1
        rec = bytearray([5]) + struct.pack("<i", oid) + lps(name) + struct.pack("<i", len(members))
        for m, _, _ in members:
            rec += lps(m)
        prim = {"i32": 8, "i64": 9, "u64": 16, "f64": 6, "bool": 1}
        types, extra = bytearray(), bytearray()
        for _, kind, value in members:
            if kind in prim:
                types.append(0)
                extra.append(prim[kind])
            elif kind == "bytes":
                types.append(7)
                extra.append(2)
            elif kind == "str":
                types.append(1)
            elif kind == "null":
                types.append(2)
            else:
                types.append(4)
                extra += lps(value[0]) + struct.pack("<i", 2)
        rec += types + extra + struct.pack("<i", 2)
        self.out += rec
        fmt = {"i32": "<i", "i64": "<q", "u64": "<Q", "f64": "<d", "bool": "<?"}
        for _, kind, value in members:
            if kind in fmt:
                self.out += struct.pack(fmt[kind], value)
            elif kind == "bytes":
                aid = self.next_id
                self.next_id += 1
                self.out += bytes([15]) + struct.pack("<ii", aid, len(value)) + bytes([2]) + bytes(value)
            elif kind == "str":
                sid = self.next_id
                self.next_id += 1
                self.out += bytes([6]) + struct.pack("<i", sid) + lps(value)
            elif kind == "null":
                self.out += bytes([10])
            else:
                self.obj(value[0], value[1])
        return oid

    def end(self):
        return bytes(self.out) + bytes([11])


def point(x, y, z):
    return ("Common.Data.DTO.Point", [("<X>k__BackingField", "f64", x), ("<Y>k__BackingField", "f64", y),
                                      ("<Z>k__BackingField", "f64", z)])


def unity_bin(pixels, origin, row, col, spacing, thickness, ticks):
    rows, cols = pixels.shape
    volume = [
        ("<Dimension>k__BackingField", "class", ("Common.Data.DTO.Dimension", [
            ("<Rows>k__BackingField", "i32", rows), ("<Columns>k__BackingField", "i32", cols),
            ("<Slices>k__BackingField", "i32", 1)])),
        ("<VoxelSize>k__BackingField", "class", ("Common.Data.DTO.VoxelSize", [
            ("<XInmm>k__BackingField", "f64", spacing[0]), ("<YInmm>k__BackingField", "f64", spacing[1]),
            ("<ZInmm>k__BackingField", "f64", thickness)])),
        ("<Orientation>k__BackingField", "class", ("Common.Data.DTO.SliceOrientation", [
            ("<RowDirectionCosines>k__BackingField", "class", point(*row)),
            ("<ColumnDirectionCosines>k__BackingField", "class", point(*col))])),
        ("<BitsPerVoxel>k__BackingField", "i32", 12), ("<BytesPerVoxel>k__BackingField", "i32", 2),
        ("<NoOfComponents>k__BackingField", "i32", 1),
        ("<Origin>k__BackingField", "class", point(*origin)),
        ("<Unsigned>k__BackingField", "bool", True),
        ("<Data>k__BackingField", "bytes", pixels.astype("<u2").tobytes()),
        ("<Elapsed100NanosecondInterval>k__BackingField", "i64", ticks),
    ]
    w = Writer()
    w.header()
    w.obj("Common.Data.DTO.MotionManagementResultData", [
        ("<TwoDSlicedata>k__BackingField", "class", ("Common.Data.DTO.VolumeData", volume)),
        ("<BeamGatingData>k__BackingField", "null", None),
        ("<Note>k__BackingField", "str", "written by the test"),
    ])
    return w.end()


# ------------------------------------------------------------------------------------------------
# the real frames
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("plane", PLANES)
def test_real_unity_bin_and_dicom_give_the_same_frame(plane):
    """The vendor's .bin and its DICOM export: the same pixels, the same placement in the scanner, the right plane."""
    b = read_frame(unity(f"{plane}.bin"))
    d = read_frame(unity(f"{plane}.dcm"))
    assert plane_name(b.normal) == plane_name(d.normal) == plane
    import SimpleITK as sitk

    assert np.array_equal(sitk.GetArrayFromImage(b.image), sitk.GetArrayFromImage(d.image))
    assert np.allclose(b.image.GetOrigin(), d.image.GetOrigin(), atol=1e-4)
    assert np.allclose(b.image.GetDirection(), d.image.GetDirection(), atol=1e-9)
    assert np.allclose(b.image.GetSpacing()[:2], d.image.GetSpacing()[:2], atol=1e-6)
    assert b.thickness_mm == d.thickness_mm == 5.0
    assert np.allclose(b.centre_mm, d.centre_mm, atol=1e-4)
    # the README's ImageOrientationPatient: row direction then column direction
    assert np.allclose(np.concatenate([b.e_u, b.e_v]), IOP[plane])


@pytest.mark.parametrize("plane", PLANES)
def test_real_frame_pixel_positions_agree_with_an_independent_dicom_reader(plane):
    """pydicom's reading of the DICOM (position of pixel (r, c) = IPP + c dc * row + r dr * col) against ours of the .bin."""
    import pydicom

    ds = pydicom.dcmread(unity(f"{plane}.dcm"))
    f = read_frame(unity(f"{plane}.bin"))
    ipp = np.array([float(x) for x in ds.ImagePositionPatient])
    iop = np.array([float(x) for x in ds.ImageOrientationPatient])
    dr, dc = (float(x) for x in ds.PixelSpacing)  # between rows, between columns
    rows, cols = int(ds.Rows), int(ds.Columns)
    assert np.array_equal(ds.pixel_array, np.squeeze(__import__("SimpleITK").GetArrayFromImage(f.image)).astype(ds.pixel_array.dtype))
    for r, c in [(0, 0), (rows - 1, 0), (0, cols - 1), (rows - 1, cols - 1), (17, 301)]:
        expected = ipp + c * dc * iop[:3] + r * dr * iop[3:]
        got = np.array(f.image.TransformIndexToPhysicalPoint((c, r, 0)))
        assert np.allclose(got, expected, atol=1e-3), (r, c)
    assert float(ds.SliceThickness) == f.thickness_mm


def test_real_unity_series_orders_planes_by_the_acquisition_clock(tmp_path):
    for p in PLANES:
        shutil.copy(unity(f"{p}.bin"), tmp_path / f"{p}.bin")
    frames = read_cine(str(tmp_path))
    # the files' 100 ns acquisition counters: sagittal 07:03:45.805, transversal 07:04:30.547, coronal 07:05:00.443 UTC
    assert [plane_name(f.normal) for f in frames] == ["sagittal", "transversal", "coronal"]
    assert np.allclose([f.time_s for f in frames], [0.0, 44.742003, 74.638066], atol=1e-4)
    assert len({f.plane for f in frames}) == 3


def test_unity_export_file_name_time_is_read(tmp_path):
    """An anonymised DICOM export holds no acquisition time; Unity's file name does (``..._698.4829_(ms).dcm``)."""
    p = tmp_path / "Frame_ID_0a503b9b_698.4829_(ms).dcm"
    shutil.copy(unity("sagittal.dcm"), p)
    f = read_frame(str(p))
    assert f.time_s == pytest.approx(0.6984829) and f.time_from == "the file name"


def test_mixed_bin_and_dicom_folder_is_refused(tmp_path):
    shutil.copy(unity("sagittal.bin"), tmp_path / "a.bin")
    shutil.copy(unity("sagittal.dcm"), tmp_path / "a.dcm")
    with pytest.raises(InputError, match="mixes kinds of cine file"):
        read_cine(str(tmp_path))


def test_cine_info_json_on_the_real_frames(capsys):
    from warpmpm.cli import main

    unity("sagittal.bin")
    assert main(["cine-info", UNITY, "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert len(info) == 6
    for item in info:
        for key in ("plane", "size", "spacing_mm", "thickness_mm", "origin_mm", "row_direction", "column_direction", "time_s"):
            assert key in item
        assert item["size"] == [336, 336] and item["spacing_mm"] == pytest.approx([1.298, 1.298], abs=1e-6)
        assert item["plane"] == os.path.basename(item["file"]).split(".")[0]
    sag = next(i for i in info if i["file"].endswith("sagittal.bin"))
    assert sag["origin_mm"] == pytest.approx([57.2, -166.215, 208.015], abs=1e-3)
    assert sag["time_s"] == pytest.approx(25425.80509, abs=1e-4)  # 07:03:45.805 UTC


# ------------------------------------------------------------------------------------------------
# streams written here
# ------------------------------------------------------------------------------------------------

def test_written_oblique_bin_is_placed_where_it_says(tmp_path):
    """An oblique frame with a known pattern: every pixel lands at origin + c * sx * row + r * sy * col."""
    a = np.radians(20.0)
    row = (np.cos(a), np.sin(a), 0.0)
    col = (0.0, 0.0, -1.0)
    pixels = (np.arange(12 * 7).reshape(12, 7) * 13 % 4096).astype(np.uint16)
    p = tmp_path / "oblique.bin"
    p.write_bytes(unity_bin(pixels, (10.0, -20.0, 30.0), row, col, (1.5, 2.5), 7.0, 39405566258050919))
    f = read_frame(str(p))
    assert plane_name(f.normal) == "oblique" and f.thickness_mm == 7.0
    img = np.squeeze(__import__("SimpleITK").GetArrayFromImage(f.image))
    assert np.array_equal(img, pixels)
    got = np.array(f.image.TransformIndexToPhysicalPoint((6, 11, 0)))
    assert np.allclose(got, np.array([10.0, -20.0, 30.0]) + 6 * 1.5 * np.array(row) + 11 * 2.5 * np.array(col))
    assert f.time_s == pytest.approx(25425.8050919)


def test_nrbf_reader_resolves_references_and_nulls():
    """A hand-written stream: a string referenced twice (record 9), ObjectNullMultiple256 (13), a class reused by id (1)."""
    out = bytearray([0]) + struct.pack("<iiii", 1, -1, 1, 0)
    out += bytes([12]) + struct.pack("<i", 2) + lps("Lib")
    # class 1: Pair {a: string, b: object, c: object, d: object, e: int32}
    out += bytes([5]) + struct.pack("<i", 1) + lps("Pair") + struct.pack("<i", 5)
    for m in "abcde":
        out += lps(m)
    out += bytes([1, 2, 2, 2, 0, 8]) + struct.pack("<i", 2)
    out += bytes([6]) + struct.pack("<i", 3) + lps("shared")  # a
    out += bytes([9]) + struct.pack("<i", 3)  # b -> the same string
    out += bytes([13, 1])  # c: one null
    out += bytes([9]) + struct.pack("<i", 4)  # d -> object 4, defined later
    out += struct.pack("<i", -7)  # e
    out += bytes([1]) + struct.pack("<ii", 4, 1)  # object 4: another Pair, metadata of object 1
    out += bytes([6]) + struct.pack("<i", 5) + lps("inner") + bytes([10]) + bytes([14]) + struct.pack("<i", 2)
    out += struct.pack("<i", 42) + bytes([11])
    root = read_nrbf(bytes(out))
    assert root["a"] == root["b"] == "shared" and root["c"] is None and root["e"] == -7
    inner = root["d"]
    assert inner.class_name == "Pair" and inner["a"] == "inner" and inner["b"] is None and inner["d"] is None and inner["e"] == 42


@pytest.mark.parametrize("damage", ["truncated", "garbage", "wrong root", "short pixels"])
def test_damaged_bin_gives_one_clear_error(tmp_path, damage):
    pixels = np.ones((4, 5), np.uint16)
    data = unity_bin(pixels, (0, 0, 0), (1, 0, 0), (0, 1, 0), (1.0, 1.0), 5.0, 1)
    if damage == "truncated":
        data = data[: len(data) // 2]
    elif damage == "garbage":
        data = b"\x89PNG\r\n" + bytes(200)
    elif damage == "wrong root":
        w = Writer()
        w.header()
        w.obj("Some.Other.Thing", [("x", "i32", 1)])
        data = w.end()
    else:
        data = unity_bin(pixels, (0, 0, 0), (1, 0, 0), (0, 1, 0), (1.0, 1.0), 5.0, 1).replace(
            struct.pack("<ii", 4, 5), struct.pack("<ii", 40, 5), 1)
    p = tmp_path / "frame.bin"
    p.write_bytes(data)
    with pytest.raises(InputError, match="frame.bin"):
        read_frame(str(p))


# ------------------------------------------------------------------------------------------------
# the TrackRAD challenge's layout
# ------------------------------------------------------------------------------------------------

def trackrad_case(folder, stack_rows_cols_time, spacing=(1.0, 1.5, 2.0), rate=8.0):
    """A TrackRAD case folder: images/<id>_frames.mha (numpy (rows, columns, time)) and frame-rate.json."""
    import SimpleITK as sitk

    os.makedirs(os.path.join(folder, "images"), exist_ok=True)
    img = sitk.GetImageFromArray(np.asarray(stack_rows_cols_time, dtype=np.float32))
    img.SetSpacing(spacing)
    sitk.WriteImage(img, os.path.join(folder, "images", f"{os.path.basename(folder)}_frames.mha"))
    with open(os.path.join(folder, "frame-rate.json"), "w") as f:
        json.dump(rate, f)
    return folder


def test_trackrad_frames_are_timed_by_the_frame_rate_and_placed_where_the_user_says(tmp_path):
    from warpmpm.cine import read_trackrad

    stack = np.arange(40 * 30 * 5, dtype=np.float32).reshape(40, 30, 5)
    case = trackrad_case(str(tmp_path / "A_001"), stack, rate=8.0)
    with pytest.raises(InputError, match="keep no patient position.*--trackrad-centre"):
        read_trackrad(case)
    frames = read_trackrad(case, (12.0, -3.0, 40.0))
    assert len(frames) == 5 and np.allclose([f.time_s for f in frames], np.arange(5) / 8.0)
    f = frames[3]
    assert plane_name(f.normal) == "sagittal" and np.allclose(f.centre_mm, (12.0, -3.0, 40.0))
    import SimpleITK as sitk

    assert np.array_equal(np.squeeze(sitk.GetArrayFromImage(f.image)), stack[:, :, 3])
    # pixel (row 0, column 0) lies anterior (-y) and superior (+z) of the centre: columns run posterior, rows inferior
    p = np.array(f.image.TransformIndexToPhysicalPoint((0, 0, 0)))
    assert np.allclose(p, (12.0, -3.0 - 14.5 * 1.5, 40.0 + 19.5 * 2.0))


def test_track_on_a_trackrad_case_through_the_phantom(tmp_path, tiny_case, capsys):
    """The phantom's planning image sampled on a sagittal plane through the pancreas, as a TrackRAD stack of still
    frames: tracked end to end (the still frames give a still estimate), and refused without a placement."""
    import SimpleITK as sitk

    from warpmpm.cli import main

    g = tiny_case.geometry
    plan = tmp_path / "plan"
    plan.mkdir()
    sitk.WriteImage(tiny_case.intensity_image(), str(plan / "image.nii.gz"))
    sitk.WriteImage(tiny_case.labels_image(), str(plan / "labels.nii.gz"))
    ijk = np.argwhere(tiny_case.labels == tiny_case.label_map["pancreas"])[:, ::-1].astype(float)
    centre = g.index_to_world(ijk).mean(0)
    rows, cols, sp = 48, 60, 2.0
    r, c = np.mgrid[0:rows, 0:cols]
    world = (centre + ((c - (cols - 1) / 2) * sp)[..., None] * np.array([0, 1.0, 0])
             + ((r - (rows - 1) / 2) * sp)[..., None] * np.array([0, 0, -1.0]))
    from scipy import ndimage

    q = g.world_to_index(world.reshape(-1, 3))
    plane = ndimage.map_coordinates(tiny_case.image, q[:, ::-1].T, order=1).reshape(rows, cols)
    case = trackrad_case(str(tmp_path / "Z_001"), np.repeat(plane[..., None], 3, axis=2), spacing=(1.0, sp, sp), rate=4.0)
    args = ["track", "--image", str(plan / "image.nii.gz"), "--labels", str(plan / "labels.nii.gz"), "--cine", case,
            "--out", str(tmp_path / "out"), "--device", "cpu", "--max-steps", "600", "--estimator", "slice-driven"]
    assert main(args) == 2 and "--trackrad-centre" in capsys.readouterr().err
    assert main(args + ["--trackrad-centre=" + ",".join(f"{v:.3f}" for v in centre)]) == 0
    import csv

    rows_out = list(csv.DictReader(open(tmp_path / "out" / "track.csv")))
    assert [float(r["time_s"]) for r in rows_out] == pytest.approx([0.0, 0.25, 0.5])
    assert all(float(r["pancreas_shift_mm"]) < 1.0 for r in rows_out)
