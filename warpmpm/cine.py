"""Cine MR frames: reading a series of 2D frames, their planes in the scanner's space, grouping by plane.

A frame is a 2D image placed in 3D, in any of these forms:

- an Elekta Unity cine file (``.bin``: the vendor's .NET binary serialisation, read by :mod:`warpmpm.nrbf`).
  Its ``VolumeData`` holds the pixels (unsigned 16-bit, rows x columns), the world position of the first pixel
  (``Origin``, mm), the row and column direction cosines, the pixel size and the slice thickness, and the
  acquisition clock (``Elapsed100NanosecondInterval``: 100 ns ticks since 1900-01-01 UTC); the same fields as
  the DICOM export of the same frame (ImagePositionPatient, ImageOrientationPatient, PixelSpacing,
  SliceThickness), checked on real Unity frames;
- a 2D DICOM MR file (Unity's or MRIdian's export; ImagePositionPatient / ImageOrientationPatient place it);
  its time is AcquisitionDateTime, AcquisitionTime or ContentTime, else the time Unity writes into its export
  file names (``..._698.4829_(ms).dcm``), else its instance number;
- a NIfTI / MHA / NRRD image one voxel thick (its geometry places the plane; frames are ordered by file name).

- a TrackRAD challenge case folder (``images/<id>_frames.mha``, ``frame-rate.json``): a 2D+t stack of sagittal
  frames, time along the first ITK axis (numpy ``(rows, columns, time)``), timed by the frame rate. TrackRAD keeps
  no patient position, so its frames are placed where the user says: on the sagittal plane through ``centre_mm``,
  rows running inferior (-z) and columns posterior (+y), the layout of Unity's sagittal frames.

Frames are ordered by acquisition time. Any plane orientation, oblique included. Frames of the same plane (same normal and position, to 0.5 mm) form one plane's stream:
one plane on MRIdian (sagittal), interleaved sagittal / coronal on Unity.

In-plane coordinates of a frame are the offsets ``(u, v) = ((x - c) . e_u, (x - c) . e_v)`` in mm from its
centre ``c``, along its two in-plane image axes: the convention of :mod:`warpmpm.slices`.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from .errors import InputError
from .images import check_file_integrity

__all__ = ["IMAGE_SUFFIXES", "CineFrame", "read_cine", "read_frame", "cine_info", "plane_name", "is_trackrad", "read_trackrad"]

IMAGE_SUFFIXES = (".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".dcm", ".bin")

#: a time in an export's file name, as Unity writes it: ``Frame_ID_<uuid>_698.4829_(ms).dcm``
_NAME_TIME = re.compile(r"_(\d+(?:\.\d+)?)_\(ms\)", re.IGNORECASE)


@dataclass
class CineFrame:
    """One cine frame.

    Attributes:
        path: the file. image: the frame as a 3D SimpleITK image one voxel thick. time_s: acquisition time
        (s, from the first frame). plane: the index of its plane in the series. thin_axis: the image axis of
        size 1. normal, e_u, e_v: unit world vectors (the slice normal and the in-plane image axes).
        centre_mm: the world centre of the frame. thickness_mm: the slice thickness. source: where it came
        from ("unity-bin", "dicom" or "image"). time_from: what its acquisition time was read from.
    """

    path: str
    image: sitk.Image
    time_s: float
    thin_axis: int
    normal: np.ndarray
    e_u: np.ndarray
    e_v: np.ndarray
    centre_mm: np.ndarray
    thickness_mm: float
    plane: int = 0
    source: str = "image"
    time_from: str = "file order"
    instance: int = 0
    frame_of_reference: str = ""
    patient: str = ""

    def slice_2d(self, volume_image: sitk.Image | None = None, interpolator=sitk.sitkLinear) -> sitk.Image:
        """The frame (or ``volume_image`` resampled on the frame's plane) as a 2D image in centred in-plane mm."""
        img = self.image if volume_image is None else sitk.Resample(volume_image, self.image, sitk.Transform(), interpolator, 0.0)
        arr = np.squeeze(sitk.GetArrayFromImage(img), axis=2 - self.thin_axis).astype(np.float32)
        out = sitk.GetImageFromArray(arr)
        axes = [a for a in range(3) if a != self.thin_axis]
        x0 = np.asarray(self.image.GetOrigin()) - self.centre_mm
        out.SetOrigin((float(x0 @ self.e_u), float(x0 @ self.e_v)))
        out.SetSpacing(tuple(float(self.image.GetSpacing()[a]) for a in axes))
        return out

    def in_plane(self, positions_mm: np.ndarray) -> np.ndarray:
        """(N, 2) in-plane coordinates (mm) of world positions."""
        d = np.asarray(positions_mm, dtype=np.float64) - self.centre_mm
        return np.stack([d @ self.e_u, d @ self.e_v], axis=1)

    def distance_mm(self, positions_mm: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of world positions from the frame's plane."""
        return (np.asarray(positions_mm, dtype=np.float64) - self.centre_mm) @ self.normal

    @property
    def projector(self) -> np.ndarray:
        return np.outer(self.e_u, self.e_u) + np.outer(self.e_v, self.e_v)


def _frame(path: str, image: sitk.Image, time_s: float, thickness_mm: float | None = None, source: str = "image",
           time_from: str = "file order") -> CineFrame:
    if image.GetDimension() == 2:
        image = sitk.JoinSeries(image)
    if image.GetDimension() != 3:
        raise InputError(f"cine frame {path} is {image.GetDimension()}D; a 2D frame (or a 3D image one voxel thick) is required")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"cine frame {path} is not a scalar image")
    size = image.GetSize()
    thin = [a for a in range(3) if size[a] == 1]
    if len(thin) != 1:
        raise InputError(f"cine frame {path} is {size[0]} x {size[1]} x {size[2]} voxels; a frame must be one voxel thick "
                         "(a multi-frame file: export the cine as one file per frame)")
    a = thin[0]
    d = np.asarray(image.GetDirection()).reshape(3, 3)
    u, v = [b for b in range(3) if b != a]
    arr = sitk.GetArrayViewFromImage(image)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"cine frame {path} holds non-finite (NaN or Inf) pixels")
    thickness = float(image.GetSpacing()[a]) if thickness_mm is None else float(thickness_mm)
    if not (np.isfinite(thickness) and thickness > 0):
        raise InputError(f"cine frame {path} has a slice thickness of {thickness} mm; a positive thickness is required")
    centre_idx = (np.asarray(size, dtype=np.float64) - 1.0) / 2.0
    centre = np.asarray(image.TransformContinuousIndexToPhysicalPoint(centre_idx.tolist()))
    return CineFrame(path, image, time_s, a, d[:, a] / np.linalg.norm(d[:, a]), d[:, u], d[:, v], centre,
                     thickness, source=source, time_from=time_from)


def _placed_image(pixels: np.ndarray, first_pixel_mm, row_direction, column_direction, spacing_mm) -> sitk.Image:
    """A (rows, columns) pixel array placed as DICOM places it, as a 3D image one voxel thick.

    ``row_direction``: the world direction along a row (column index increasing), ``column_direction``: down a column
    (row index increasing); ``spacing_mm``: (along a row, along a column).
    """
    r = np.asarray(row_direction, dtype=np.float64)
    c = np.asarray(column_direction, dtype=np.float64)
    n = np.cross(r, c)
    image = sitk.GetImageFromArray(np.ascontiguousarray(pixels[None]).astype(np.float32))
    image.SetOrigin(tuple(float(x) for x in first_pixel_mm))
    image.SetSpacing((float(spacing_mm[0]), float(spacing_mm[1]), 1.0))
    image.SetDirection(tuple(np.stack([r, c, n], axis=1).ravel().tolist()))
    return image


def _unity_frame(path: str) -> CineFrame:
    from .nrbf import NrbfObject, read_nrbf

    with open(path, "rb") as fh:
        root = read_nrbf(fh.read(), f"cine frame {path}")
    try:
        v = root.field("TwoDSlicedata") if isinstance(root, NrbfObject) and root.class_name.endswith("MotionManagementResultData") else root
        if not isinstance(v, NrbfObject) or not v.class_name.endswith("VolumeData"):
            raise KeyError(f"its root is {getattr(root, 'class_name', type(root).__name__)}, not a Unity cine frame")
        dim, vox, ori = v.field("Dimension"), v.field("VoxelSize"), v.field("Orientation")
        rows, cols, slices = (int(dim.field(k)) for k in ("Rows", "Columns", "Slices"))

        def point(p):
            return np.array([float(p.field(k)) for k in ("X", "Y", "Z")])

        origin = point(v.field("Origin"))
        row_dir, col_dir = point(ori.field("RowDirectionCosines")), point(ori.field("ColumnDirectionCosines"))
        spacing = (float(vox.field("XInmm")), float(vox.field("YInmm")))
        thickness = float(vox.field("ZInmm"))
        nbytes, ncomp = int(v.field("BytesPerVoxel")), int(v.field("NoOfComponents"))
        unsigned = bool(v.field("Unsigned"))
        data = v.field("Data")
        ticks = v.get("<Elapsed100NanosecondInterval>k__BackingField")
    except KeyError as exc:
        raise InputError(f"cine frame {path}: not an Elekta Unity cine frame ({exc.args[0]})") from None
    if slices != 1 or ncomp != 1 or nbytes not in (1, 2, 4):
        raise InputError(f"cine frame {path}: {rows} x {cols} x {slices} voxels of {ncomp} component(s), {nbytes} bytes each; "
                         "a single-slice scalar frame is required")
    dtype = np.dtype(f"<{'u' if unsigned else 'i'}{nbytes}")
    if not isinstance(data, np.ndarray) or data.nbytes != rows * cols * nbytes:
        got = data.nbytes if isinstance(data, np.ndarray) else 0
        raise InputError(f"cine frame {path}: its pixel data holds {got} bytes, {rows} x {cols} pixels of {nbytes} bytes need "
                         f"{rows * cols * nbytes}")
    for name, d in (("row", row_dir), ("column", col_dir)):
        if not (np.all(np.isfinite(d)) and abs(np.linalg.norm(d) - 1) < 1e-3):
            raise InputError(f"cine frame {path}: its {name} direction {d.tolist()} is not a unit vector")
    if abs(row_dir @ col_dir) > 1e-3:
        raise InputError(f"cine frame {path}: its row and column directions are not perpendicular")
    if not (np.all(np.isfinite(origin)) and all(np.isfinite(s) and s > 0 for s in spacing)):
        raise InputError(f"cine frame {path}: its origin {origin.tolist()} or pixel size {spacing} is not usable")
    pixels = data.view(dtype).reshape(rows, cols)
    image = _placed_image(pixels, origin, row_dir, col_dir, spacing)
    if isinstance(ticks, int) and ticks > 0:
        time_s, time_from = _seconds_of_day(ticks * 1e-7), "the file's acquisition clock"
    else:
        time_s, time_from = _name_time(path)
    return _frame(path, image, time_s, thickness, source="unity-bin", time_from=time_from)


def _seconds_of_day(seconds: float) -> float:
    return float(seconds % 86400.0)


def _name_time(path: str) -> tuple[float, str]:
    m = _NAME_TIME.search(os.path.basename(path))
    if m:
        return float(m.group(1)) * 1e-3, "the file name"
    return float("nan"), "file order"


def _dicom_numbers(reader, tag: str) -> list[float] | None:
    """A multi-valued numeric tag ("a\\b\\c") as floats; None when absent or empty; [nan] when unreadable."""
    if not reader.HasMetaDataKey(tag):
        return None
    text = str(reader.GetMetaData(tag)).strip()
    if not text:
        return None
    try:
        return [float(x) for x in text.split("\\")]
    except ValueError:
        return [float("nan")]


def _check_dicom_geometry(reader, path: str) -> None:
    """A cine frame placed by its own tags or refused: PixelSpacing (two positive numbers), ImagePositionPatient (three
    finite numbers), ImageOrientationPatient (two perpendicular unit vectors). ITK otherwise reads 1 mm pixels at the
    origin, or takes a negative spacing's absolute value, without a word."""
    checks = (("0028|0030", "PixelSpacing", 2, lambda v: all(x > 0 for x in v), "two positive numbers (mm)"),
              ("0020|0032", "ImagePositionPatient", 3, lambda v: True, "three finite numbers (mm)"),
              ("0020|0037", "ImageOrientationPatient", 6,
               lambda v: abs(np.linalg.norm(v[:3]) - 1) < 1e-3 and abs(np.linalg.norm(v[3:]) - 1) < 1e-3
               and abs(np.dot(v[:3], v[3:])) < 1e-3, "two perpendicular unit vectors"))
    for tag, name, n, ok, want in checks:
        v = _dicom_numbers(reader, tag)
        if v is None:
            raise InputError(f"cine frame {path} has no {name}: it cannot be placed in the patient (a frame without it would "
                             f"be read at 1 mm pixels at the scanner's origin); export the cine with its geometry tags")
        if len(v) != n or not all(np.isfinite(v)) or not ok(np.asarray(v)):
            raise InputError(f"cine frame {path} has an unusable {name} {reader.GetMetaData(tag).strip()!r}: {want} are "
                             "required; export the cine again from the scanner")


def _dicom_frame(path: str) -> CineFrame:
    try:
        reader = sitk.ImageFileReader()
        reader.SetFileName(path)
        reader.LoadPrivateTagsOff()
        reader.ReadImageInformation()
        _check_dicom_geometry(reader, path)
        image = reader.Execute()
    except RuntimeError as exc:
        raise InputError(f"cannot read cine frame {path}: {str(exc).strip().splitlines()[-1]}") from None
    thickness = None
    if reader.HasMetaDataKey("0018|0050"):
        try:
            thickness = float(str(reader.GetMetaData("0018|0050")).strip())
        except ValueError:
            raise InputError(f"cine frame {path} has an unreadable slice thickness "
                             f"{reader.GetMetaData('0018|0050')!r}") from None
    time_s, time_from = _dicom_time_s(reader, path)
    if not np.isfinite(time_s):
        time_s, time_from = _name_time(path)
    frame = _frame(path, image, time_s, thickness, source="dicom", time_from=time_from)
    frame.instance = _dicom_int(reader, "0020|0013")
    for tag, attr in (("0020|0052", "frame_of_reference"), ("0010|0020", "patient")):
        if reader.HasMetaDataKey(tag):
            setattr(frame, attr, str(reader.GetMetaData(tag)).strip())
    return frame


def read_frame(path: str) -> CineFrame:
    """One cine frame from a file, of any form in the module docstring (the vendor's ``.bin``, DICOM, NIfTI/MHA/NRRD).

    Its ``time_s`` is the file's own time in s (seconds of the day for a Unity ``.bin`` or a DICOM time; the export's
    file-name time; NaN when the file holds none). Raises :class:`InputError` naming the file when it cannot be read.
    """
    from .errors import check_input_file

    check_input_file(path, "cine frame")
    low = path.lower()
    if low.endswith(".bin"):
        return _unity_frame(path)
    if low.endswith(".dcm"):
        return _dicom_frame(path)
    check_file_integrity(path)
    try:
        image = sitk.ReadImage(path)
    except RuntimeError as exc:
        raise InputError(f"cannot read cine frame {path}: {str(exc).strip().splitlines()[-1]}") from None
    return _frame(path, image, float("nan"))


def plane_name(normal) -> str:
    """"sagittal", "coronal" or "transversal" for a plane within 10 degrees of one, else "oblique"."""
    n = np.abs(np.asarray(normal, dtype=np.float64))
    k = int(np.argmax(n))
    if n[k] < np.cos(np.radians(10.0)):
        return "oblique"
    return ("sagittal", "coronal", "transversal")[k]


def cine_info(paths) -> list[dict]:
    """What was read of each frame (JSON-ready): plane, size, spacing_mm, thickness_mm, origin_mm (the world position of
    the first pixel), row_direction, column_direction (unit world LPS vectors), time_s, and where each came from."""
    out = []
    for p in paths:
        f = read_frame(p)
        img = f.image
        size, sp = img.GetSize(), img.GetSpacing()
        u, v = [a for a in range(3) if a != f.thin_axis]
        out.append({
            "file": p, "format": f.source, "plane": plane_name(f.normal),
            "size": [int(size[u]), int(size[v])],
            "spacing_mm": [float(sp[u]), float(sp[v])],
            "thickness_mm": f.thickness_mm,
            "origin_mm": [float(x) for x in img.GetOrigin()],
            "row_direction": [float(x) for x in f.e_u], "column_direction": [float(x) for x in f.e_v],
            "normal": [float(x) for x in f.normal],
            "time_s": None if not np.isfinite(f.time_s) else float(f.time_s), "time_from": f.time_from,
        })
    return out


def read_cine(folder: str) -> list[CineFrame]:
    """Every frame of a cine folder, in acquisition order, with its plane index (see module docstring).

    Raises :class:`InputError` naming the file for an unreadable frame, a frame that is not one voxel
    thick, mixed sizes within one plane, or a folder that mixes kinds of file.
    """
    if not os.path.isdir(folder):
        raise InputError(f"cine folder {folder} " + ("is a file; give the folder that holds the frames" if os.path.exists(folder)
                                                     else "not found"))
    paths = sorted(os.path.join(folder, f) for f in os.listdir(folder) if f.lower().endswith(IMAGE_SUFFIXES))
    if not paths:
        raise InputError(f"no cine frames (Unity .bin, DICOM, NIfTI, MHA or NRRD files) in {folder}")
    kinds = {".bin" if p.lower().endswith(".bin") else ".dcm" if p.lower().endswith(".dcm") else "image" for p in paths}
    if len(kinds) > 1:
        raise InputError(f"{folder} mixes kinds of cine file ({', '.join(sorted(kinds))}); keep one kind per series (the "
                         "Unity .bin and its DICOM export of a frame are the same frame)")
    frames = [read_frame(p) for p in paths]
    for attr, what in (("frame_of_reference", "frame of reference (scanner coordinates)"), ("patient", "patient ID")):
        values = {getattr(f, attr) for f in frames if getattr(f, attr)}
        if len(values) > 1:
            a = next(f for f in frames if getattr(f, attr))
            b = next(f for f in frames if getattr(f, attr) and getattr(f, attr) != getattr(a, attr))
            raise InputError(f"cine frames of two series in {folder}: {os.path.basename(a.path)} and {os.path.basename(b.path)} "
                             f"have another {what} ({getattr(a, attr)} vs {getattr(b, attr)}); keep one session's cine per folder")
    sources = {f.time_from for f in frames}
    if len(sources) > 1:  # one frame's time from another clock (or none) would misplace it among the others
        counts = {src: sum(f.time_from == src for f in frames) for src in sources}
        rare = min(counts, key=counts.get)
        odd = [os.path.basename(f.path) for f in frames if f.time_from == rare]
        raise InputError(f"cine frames in {folder} take their times from different clocks: {', '.join(odd[:5])}"
                         f"{' ...' if len(odd) > 5 else ''} from {rare}, the others from "
                         f"{', '.join(sorted(sources - {rare}))}; a frame's place in the series would be wrong. Export the "
                         "cine again with every frame's AcquisitionTime, or remove those frames")
    timed = all(np.isfinite(f.time_s) for f in frames)
    if not timed:  # no time in some file: the order of the instance numbers, then of the file names; one s apart
        order = sorted(range(len(frames)), key=lambda n: (frames[n].instance, n))
        for rank, n in enumerate(order):
            frames[n].time_s, frames[n].time_from = float(rank), "file order"
    else:
        for f in frames:
            f.time_s += 1e-6 * f.instance
    times = sorted(f.time_s for f in frames)
    if timed and len(times) > 1 and times[-1] - times[0] > 43200:  # crossed midnight: unwrap seconds of the day
        for f in frames:
            if f.time_s < 43200:
                f.time_s += 86400.0
    frames.sort(key=lambda f: f.time_s)
    frames = _without_duplicates(frames)
    t0 = frames[0].time_s
    for f in frames:
        f.time_s -= t0
    # group by plane: same normal (up to sign) and the same offset along it
    planes: list[tuple[np.ndarray, float, tuple]] = []
    for f in frames:
        n = f.normal * np.sign(f.normal[np.argmax(np.abs(f.normal))])
        off = float(f.centre_mm @ n)
        for i, (pn, po, size) in enumerate(planes):
            if abs(abs(pn @ n) - 1) < 1e-4 and abs(po - off) < 0.5:
                if f.image.GetSize() != size:
                    raise InputError(f"cine frame {f.path} is {f.image.GetSize()} voxels, other frames of its plane "
                                     f"{size}: one plane's frames must share a size")
                f.plane = i
                break
        else:
            planes.append((n, off, f.image.GetSize()))
            f.plane = len(planes) - 1
    return frames


def _without_duplicates(frames: list[CineFrame]) -> list[CineFrame]:
    """Frames in time order less exact copies (the same time, plane and pixels: a file copied twice), with a warning;
    two different frames at the same time on the same plane are refused (which one was acquired?)."""
    import warnings

    from .errors import InputWarning

    out = [frames[0]]
    for f in frames[1:]:
        last = out[-1]
        same_plane = abs(abs(float(f.normal @ last.normal)) - 1) < 1e-4 and abs(float((f.centre_mm - last.centre_mm) @ f.normal)) < 0.5
        if same_plane and abs(f.time_s - last.time_s) < 1e-4 and f.time_from != "file order":
            if (f.image.GetSize() == last.image.GetSize()
                    and np.array_equal(sitk.GetArrayViewFromImage(f.image), sitk.GetArrayViewFromImage(last.image))):
                warnings.warn(f"cine frame {f.path} is a copy of {last.path} (the same time, plane and pixels): read once",
                              InputWarning, stacklevel=3)
                continue
            raise InputError(f"cine frames {last.path} and {f.path} are two different frames of one plane at the same time "
                             f"({f.time_s:.4f} s); remove the one that does not belong to the series")
        out.append(f)
    return out


def _dicom_int(reader, tag: str) -> int:
    try:
        return int(str(reader.GetMetaData(tag)).strip())
    except (RuntimeError, ValueError):
        return 0


def _dicom_clock(v: str) -> float:
    """Seconds of the day of a DICOM TM value: HH, HHMM, HHMMSS or HHMMSS.FFFFFF (and the old HH:MM:SS); ValueError else."""
    v = v.replace(":", "")
    whole, _, frac = v.partition(".")
    if len(whole) not in (2, 4, 6) or not whole.isdigit() or (frac and not frac.isdigit()):
        raise ValueError(v)
    hh, mm, ss = int(whole[0:2]), int(whole[2:4] or 0), int(whole[4:6] or 0)
    if hh > 23 or mm > 59 or ss > 60 or (frac and len(whole) != 6):
        raise ValueError(v)
    return hh * 3600 + mm * 60 + ss + (float("0." + frac) if frac else 0.0)


def _dicom_time_s(reader, path: str) -> tuple[float, str]:
    """Seconds of the day from AcquisitionDateTime, AcquisitionTime or ContentTime (NaN when none)."""
    for tag, name in (("0008|002a", "AcquisitionDateTime"), ("0008|0032", "AcquisitionTime"), ("0008|0033", "ContentTime")):
        if reader.HasMetaDataKey(tag):
            v = str(reader.GetMetaData(tag)).strip()
            if tag == "0008|002a":
                v = v[8:].split("+")[0].split("-")[0]  # YYYYMMDDHHMMSS.frac&ZZXX -> HHMMSS.frac
            if not v:
                continue
            try:
                return _dicom_clock(v), name
            except ValueError:
                raise InputError(f"cine frame {path} has an unreadable {name} {v!r} (HHMMSS.FFFFFF expected); mend the "
                                 "tag or export the cine again") from None
    return float("nan"), "file order"


def is_trackrad(folder: str) -> bool:
    """Whether ``folder`` is laid out as a TrackRAD case (``images/*_frames.mha`` beside ``frame-rate.json``)."""
    images = os.path.join(folder, "images")
    return (os.path.isfile(os.path.join(folder, "frame-rate.json")) and os.path.isdir(images)
            and any(f.endswith("_frames.mha") for f in os.listdir(images)))


def read_trackrad(folder: str, centre_mm=None, thickness_mm: float = 5.0) -> list[CineFrame]:
    """The frames of a TrackRAD case folder, placed on the sagittal plane through ``centre_mm`` (module docstring).

    ``thickness_mm``: the slice thickness (TrackRAD does not keep it; 5 mm is Unity's and MRIdian's usual cine).
    Raises :class:`InputError` when the layout is incomplete, the frame rate unreadable, or no placement is given.
    """
    import json

    if not is_trackrad(folder):
        raise InputError(f"{folder} is not a TrackRAD case folder (images/<id>_frames.mha and frame-rate.json)")
    stacks = sorted(f for f in os.listdir(os.path.join(folder, "images")) if f.endswith("_frames.mha"))
    if len(stacks) > 1:
        raise InputError(f"{folder}/images holds {len(stacks)} primary cine stacks ({', '.join(stacks)}); keep one per folder")
    try:
        with open(os.path.join(folder, "frame-rate.json")) as fh:
            rate = json.load(fh)
        rate = float(rate["frame_rate"] if isinstance(rate, dict) else rate)
    except (ValueError, KeyError, TypeError, json.JSONDecodeError):
        raise InputError(f"{folder}/frame-rate.json: a frame rate (a number of frames per second) is required") from None
    if not (np.isfinite(rate) and 0 < rate <= 100):
        raise InputError(f"{folder}/frame-rate.json: frame rate {rate} fps; an MR-Linac cine runs at 1-100 fps")
    if centre_mm is None:
        raise InputError(f"{folder} is a TrackRAD case: its frames keep no patient position; say where the sagittal plane lies in "
                         "the planning scan with --trackrad-centre X,Y,Z (mm, LPS: a point on the plane at the frames' centre)")
    centre = np.asarray(centre_mm, dtype=np.float64)
    if centre.shape != (3,) or not np.all(np.isfinite(centre)):
        raise InputError(f"--trackrad-centre must be three finite numbers (mm), got {centre_mm!r}")
    from .images import read_volume

    path = os.path.join(folder, "images", stacks[0])
    stack = read_volume(path)  # checked: integrity, 3D, scalar
    arr = sitk.GetArrayFromImage(stack)  # (rows, columns, time)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{path} holds non-finite pixels")
    spacing = stack.GetSpacing()
    rows, cols, n = arr.shape
    row_dir, col_dir = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, -1.0])
    sp = (float(spacing[1]), float(spacing[2]))  # along a row (columns), along a column (rows)
    first = centre - (cols - 1) / 2.0 * sp[0] * row_dir - (rows - 1) / 2.0 * sp[1] * col_dir
    frames = []
    for t in range(n):
        image = _placed_image(arr[:, :, t], first, row_dir, col_dir, sp)
        f = _frame(f"{path}#frame{t}", image, t / rate, thickness_mm, source="trackrad", time_from="the frame rate")
        frames.append(f)
    for f in frames:
        f.plane = 0
    return frames
