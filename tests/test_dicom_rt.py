"""DICOM for the planning system, checked by independent readers: dicom3tools' dciodvfy (every object valid, no
error), plastimatch (the structure set rasterised by it gives the masks back; its own encoding of the same field as a
Deformable Spatial Registration is ours), and the bad structure sets a clinic meets refused by name.

dciodvfy and plastimatch come from Debian (`bash scripts/setup.sh` installs them); where they are absent the tests
that need them skip saying so, except under CI, where their absence fails.
"""

import csv
import os
import shutil
import subprocess

import numpy as np
import pytest
import SimpleITK as sitk

from warpmpm.cli import main
from warpmpm.dicom_rt import (find_structures, read_registration, read_rtstruct, write_registration, write_rtdose, write_rtstruct,
                              write_series)
from warpmpm.errors import InputError
from warpmpm.experiment.cine_series import same_session
from warpmpm.images import load_case

ORGAN_ROIS = {"pancreas": "Pancreas", "stomach": "Stomach", "duodenum": "Duodenum", "left_kidney": "Kidney_L"}


def need(tool):
    if shutil.which(tool) is None:
        if os.environ.get("CI"):
            pytest.fail(f"{tool} is not installed: scripts/setup.sh installs it (Debian's dicom3tools / plastimatch)")
        pytest.skip(f"{tool} is absent (bash scripts/setup.sh installs it on Debian/Ubuntu)")
    return tool


def dciodvfy_errors(path):
    out = subprocess.run([need("dciodvfy"), path], capture_output=True, text=True)
    return [line for line in (out.stdout + out.stderr).splitlines() if line.startswith("Error")]


def dice(a, b):
    return 2.0 * np.sum(a & b) / max(np.sum(a) + np.sum(b), 1)


@pytest.fixture(scope="module")
def planning(tmp_path_factory, tiny_case):
    """The phantom's planning image as a DICOM MR series and its organs as a structure set, as a clinic has them."""
    root = tmp_path_factory.mktemp("planning")
    ref = write_series(tiny_case.intensity_image(), str(root / "series"), "MR")
    masks = {o: tiny_case.labels == v for o, v in tiny_case.label_map.items()}
    write_rtstruct(str(root / "RS.dcm"), ref, masks, ORGAN_ROIS, label="plan")
    return root, ref, masks


def test_series_structure_set_and_registration_pass_dciodvfy(planning, tmp_path):
    root, ref, _ = planning
    field = np.random.default_rng(0).normal(size=tuple(ref.geometry.size[::-1]) + (3,)).astype(np.float32)
    write_registration(str(tmp_path / "REG.dcm"), ref, field)
    first = sorted(os.listdir(root / "series"))[0]
    for path in (root / "series" / first, root / "RS.dcm", tmp_path / "REG.dcm"):
        assert dciodvfy_errors(str(path)) == [], path


def test_structure_set_rasterised_by_plastimatch_gives_the_masks(planning, tmp_path):
    """Our contours, read by a second program on the series' grid: each organ within Dice 0.95 (and ours exactly)."""
    root, ref, masks = planning
    subprocess.run([need("plastimatch"), "convert", "--input", str(root / "RS.dcm"), "--referenced-ct", str(root / "series"),
                    "--output-prefix", str(tmp_path / "pl"), "--prefix-format", "nrrd"], check=True, capture_output=True)
    ours = read_rtstruct(str(root / "RS.dcm"), ref.geometry, ref.frame_of_reference_uid)
    for organ, mask in masks.items():
        img = sitk.ReadImage(str(tmp_path / "pl" / f"{ORGAN_ROIS[organ]}.nrrd"))
        assert np.allclose(img.GetOrigin(), ref.geometry.origin_mm, atol=1e-3) and img.GetSize() == ref.geometry.size
        theirs = sitk.GetArrayFromImage(img) > 0
        assert dice(theirs, mask) >= 0.95, organ
        assert np.array_equal(ours[ORGAN_ROIS[organ]], mask), organ


def test_registration_is_encoded_as_plastimatch_encodes_the_same_field(planning, tmp_path):
    """The same ITK displacement field as a DICOM REG by plastimatch and by us: the same grid and vectors to 0.01 mm
    (so a planning system reads our planning-to-frame vectors with the sign and axes it reads plastimatch's)."""
    import pydicom

    root, ref, _ = planning
    g = ref.geometry
    k, j, i = np.meshgrid(*[np.arange(n) for n in g.size[::-1]], indexing="ij")
    field = np.stack([0.1 * i + 1.0, -0.05 * j - 2.0, 0.3 * k + 0.5], -1).astype(np.float32)
    sitk.WriteImage(g.apply_to(sitk.GetImageFromArray(field, isVector=True)), str(tmp_path / "vf.nrrd"))
    subprocess.run([need("plastimatch"), "xf-convert", "--input", str(tmp_path / "vf.nrrd"), "--output-dicom",
                    str(tmp_path / "pm"), "--fixed-rcs", str(root / "series"), "--moving-rcs", str(root / "series")],
                   check=True, capture_output=True)
    write_registration(str(tmp_path / "REG.dcm"), ref, field)
    theirs = pydicom.dcmread(str(next((tmp_path / "pm").glob("*.dcm"))))
    grid_t = theirs.DeformableRegistrationSequence[0].DeformableRegistrationGridSequence[0]
    ours, geometry = read_registration(str(tmp_path / "REG.dcm"))
    assert list(grid_t.GridDimensions) == list(geometry.size)
    assert np.allclose([float(x) for x in grid_t.GridResolution], geometry.spacing_mm, atol=1e-4)
    assert np.allclose([float(x) for x in grid_t.ImagePositionPatient], geometry.origin_mm, atol=1e-3)
    assert np.allclose([float(x) for x in grid_t.ImageOrientationPatient], np.asarray(geometry.direction).reshape(3, 3)[:, :2].T.ravel())
    vt = np.frombuffer(grid_t.VectorGridData, dtype="<f4").reshape(ours.shape)
    assert np.abs(vt - ours).max() <= 0.01 and np.abs(ours - field).max() <= 0.01


def test_organs_found_by_name_and_bowel_is_not_the_duodenum():
    rois = ["BODY", "Bowel_Small", "GTV_Panc", "Stomach", "DUODENUM", "Kidney L", "Kidney_R"]
    found = find_structures(rois, {"pancreas": "GTV_Panc"})
    assert found == {"pancreas": "GTV_Panc", "stomach": "Stomach", "duodenum": "DUODENUM", "left_kidney": "Kidney L"}
    assert "duodenum" not in find_structures(["Bowel_Small", "Pancreas"])
    with pytest.raises(InputError, match="'Panc_PRV' .* not in the structure set"):
        find_structures(rois, {"pancreas": "Panc_PRV"})
    with pytest.raises(InputError, match="could each be the left_kidney; name one with --structure"):
        find_structures(["Kidney_L", "L Kidney", "Pancreas"])


def _edited(src, dst, edit):
    import pydicom

    ds = pydicom.dcmread(src)
    edit(ds)
    ds.save_as(dst)
    return dst


@pytest.mark.parametrize("damage, message", [
    ("frame", "on frame of reference .* another scan"),
    ("empty", "a contour with 2 points"),
    ("crossed", "crosses itself"),
    ("between", "does not lie on a slice"),
])
def test_bad_structure_sets_are_refused_by_name(planning, tmp_path, damage, message):
    root, ref, _ = planning

    def edit(ds):
        roi = next(r for r in ds.StructureSetROISequence if r.ROIName == "Pancreas")
        rc = next(c for c in ds.ROIContourSequence if c.ReferencedROINumber == roi.ROINumber)
        c = rc.ContourSequence[0]
        pts = np.array([float(v) for v in c.ContourData]).reshape(-1, 3)
        if damage == "frame":
            roi.ReferencedFrameOfReferenceUID = "1.2.3.4"
        elif damage == "empty":
            pts = pts[:2]
        elif damage == "crossed":  # a bow tie: swap two corners of the outline
            box = np.array([[0, 0], [20, 20], [20, 0], [0, 20]], dtype=float)
            pts = np.column_stack([pts[0, 0] + box[:, 0], pts[0, 1] + box[:, 1], np.full(4, pts[0, 2])])
        else:
            pts[:, 2] += 0.45 * ref.geometry.spacing_mm[2]
        c.ContourData = [f"{v:.4f}" for v in pts.ravel()]
        c.NumberOfContourPoints = len(pts)

    bad = _edited(str(root / "RS.dcm"), str(tmp_path / "RS.dcm"), edit)
    with pytest.raises(InputError, match=f"'Pancreas'.*{message}"):
        read_rtstruct(bad, ref.geometry, ref.frame_of_reference_uid)


@pytest.fixture(scope="module")
def tracked(tmp_path_factory, planning):
    """A synthetic cine tracked from the DICOM planning series and its structure set, with --dicom (as a clinic would)."""
    root, ref, masks = planning
    series = str(tmp_path_factory.mktemp("series"))
    assert main(["make-cine", "--phantom-resolution", "3", "--frames", "2", "--plane", "sagittal,coronal", "--out", series]) == 0
    case = load_case(os.path.join(series, "planning", "labels.nii.gz"), os.path.join(series, "planning", "image.nii.gz"))
    plan = tmp_path_factory.mktemp("clinic")
    pref = write_series(case.intensity_image(), str(plan / "series"), "MR")
    same_session(os.path.join(series, "cine"), pref)
    write_rtstruct(str(plan / "RS.dcm"), pref, {o: case.labels == v for o, v in case.label_map.items()}, ORGAN_ROIS)
    write_rtdose(str(plan / "RD.dcm"), pref, plan_dose(case))
    with open(plan / "beam.csv", "w") as f:
        f.write("frame,beam_on_s\n0,0.25\n1,0.25\n")
    out = str(tmp_path_factory.mktemp("track") / "out")
    code = main(["track", "--image", str(plan / "series"), "--rtstruct", str(plan / "RS.dcm"), "--cine",
                 os.path.join(series, "cine"), "--out", out, "--device", "cpu", "--max-steps", "1500", "--estimator", "slice-driven", "--dicom", "--displacement",
                 "--dose", str(plan / "RD.dcm"), "--beam-on", str(plan / "beam.csv")])
    assert code == 0
    return plan, pref, out, case


def plan_dose(case):
    """50 Gy around the pancreas falling off over about 8 mm (a logistic edge), 0 far away."""
    g = case.geometry
    k, j, i = np.meshgrid(*[np.arange(n) for n in g.size[::-1]], indexing="ij")
    w = g.index_to_world(np.stack([i.ravel(), j.ravel(), k.ravel()], 1).astype(float)).reshape(k.shape + (3,))
    c = w[case.labels == case.label_map["pancreas"]].mean(0)
    r = np.linalg.norm(w - c, axis=-1)
    return 50.0 / (1.0 + np.exp((r - 25.0) / 4.0))


def test_track_from_a_structure_set_writes_contours_and_registrations_a_planning_system_reads(tracked, tmp_path):
    plan, pref, out, _ = tracked
    values = {"pancreas": 10, "stomach": 7, "duodenum": 13, "left_kidney": 3}  # the AMOS labels of a structure-set case
    for n in range(2):
        folder = os.path.join(out, "dicom", f"frame_{n:04d}")
        labels = sitk.GetArrayFromImage(sitk.ReadImage(os.path.join(out, "labels", f"frame_{n:04d}.nii.gz")))
        for name in ("RS.dcm", "REG.dcm"):
            assert dciodvfy_errors(os.path.join(folder, name)) == [], (n, name)
        pl = tmp_path / f"pl{n}"
        subprocess.run([need("plastimatch"), "convert", "--input", os.path.join(folder, "RS.dcm"), "--referenced-ct",
                        str(plan / "series"), "--output-prefix", str(pl), "--prefix-format", "nrrd"], check=True, capture_output=True)
        for organ, roi in ORGAN_ROIS.items():  # named as in the planning structure set
            theirs = sitk.GetArrayFromImage(sitk.ReadImage(str(pl / f"{roi}.nrrd"))) > 0
            assert dice(theirs, labels == values[organ]) >= 0.95, (n, organ)
        field, geometry = read_registration(os.path.join(folder, "REG.dcm"))
        nifti = sitk.GetArrayFromImage(sitk.ReadImage(os.path.join(out, "displacement", f"frame_{n:04d}.nii.gz")))
        assert np.abs(field - nifti).max() <= 0.01
        import pydicom

        reg = pydicom.dcmread(os.path.join(folder, "REG.dcm"))
        assert reg.FrameOfReferenceUID == pref.frame_of_reference_uid
        assert reg.ReferencedSeriesSequence[0].SeriesInstanceUID == pref.series_uid
    rows = list(csv.DictReader(open(os.path.join(out, "track.csv"))))
    for r in rows:  # each field's quality: the smallest Jacobian determinant inside the organs and the folded voxels
        assert 0.0 < float(r["field_jacobian_min"]) <= 1.5 and int(r["field_folded_voxels"]) == 0
    assert not os.path.exists(os.path.join(out, "dicom", "planning"))  # the user's own series is referred to, not copied


def test_structure_set_without_the_pancreas_is_refused(planning, tmp_path, capsys):
    root, ref, masks = planning
    write_rtstruct(str(tmp_path / "RS.dcm"), ref, {o: m for o, m in masks.items() if o != "pancreas"}, ORGAN_ROIS)
    code = main(["track", "--image", str(root / "series"), "--rtstruct", str(tmp_path / "RS.dcm"), "--cine", str(tmp_path),
                 "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and not os.path.exists(tmp_path / "out")
    assert "has no structure for pancreas (it holds: Kidney_L, Stomach, Duodenum); name it with --structure pancreas=NAME" in err


def test_field_quality_counts_folds():
    """A field that turns a slab inside out (u = -2 x along x) folds every voxel of it: det(I + grad u) = -1."""
    from warpmpm.fields import jacobian_determinant
    from warpmpm.images import Geometry

    g = Geometry((8, 6, 5), (2.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    x = np.arange(8) * 2.0
    field = np.zeros((5, 6, 8, 3))
    field[..., 0] = -2.0 * x
    assert np.allclose(jacobian_determinant(field, g), -1.0)


def test_track_with_a_plan_dose_writes_planned_and_accumulated_dvhs(tracked):
    """The planned figures are the plan's dose on the planning organs (computed here apart); the accumulated ones move
    with the estimate; the accumulated RT Dose passes dciodvfy; the plot is there."""
    from warpmpm.dose import dose_metrics

    plan, pref, out, case = tracked
    rows = {(r["organ"], r["metric"]): r for r in csv.DictReader(open(os.path.join(out, "dose", "dose_metrics.csv")))}
    dose = plan_dose(case)
    cc = float(np.prod(case.geometry.spacing_mm)) / 1000.0
    for organ, metrics in {"pancreas": ("D95_Gy", "D98_Gy"), "duodenum": ("D0.5cc_Gy", "D1cc_Gy", "Dmax_Gy"),
                           "stomach": ("D0.5cc_Gy", "D1cc_Gy", "Dmax_Gy")}.items():
        direct = dose_metrics(dose[case.labels == case.label_map[organ]], cc)
        for m in metrics:
            assert float(rows[(organ, m)]["planned"]) == pytest.approx(direct[m], abs=0.02 + 0.002 * direct[m]), (organ, m)
            assert np.isfinite(float(rows[(organ, m)]["accumulated"]))
    dvh = list(csv.DictReader(open(os.path.join(out, "dose", "dvh.csv"))))
    assert float(dvh[0]["pancreas_planned_pct"]) == pytest.approx(100.0) and float(dvh[-1]["pancreas_accumulated_pct"]) == 0.0
    assert os.path.getsize(os.path.join(out, "dose", "dvh.png")) > 10_000
    assert dciodvfy_errors(os.path.join(out, "dicom", "RD_accumulated.dcm")) == []


def test_a_structure_set_written_by_plastimatch_on_the_real_ct_is_read_back(tmp_path):
    """The real CT sample (flipped x and y axes) written as a DICOM CT series and its organs as an RT Structure Set by
    plastimatch, another program's files: our reading gives the label map back, Dice 1.0 for every organ (the test
    demands 0.95), the organs found by their names."""
    import glob

    from conftest import data_case
    from warpmpm.dicom_rt import case_from_rtstruct

    labels_path, image_path = data_case("totalseg_ct")
    pm = need("plastimatch")
    lab = sitk.ReadImage(labels_path)
    (tmp_path / "masks").mkdir()
    values = {"Pancreas": 7, "Stomach": 6, "Duodenum": 19, "Kidney_L": 3}  # TotalSegmentator's `total` labels
    for name, v in values.items():
        sitk.WriteImage(sitk.Cast(lab == v, sitk.sitkUInt8), str(tmp_path / "masks" / f"{name}.nrrd"))
    subprocess.run([pm, "convert", "--input", image_path, "--output-dicom", str(tmp_path / "ct")], check=True, capture_output=True)
    subprocess.run([pm, "convert", "--input-prefix", str(tmp_path / "masks"), "--referenced-ct", str(tmp_path / "ct"),
                    "--output-dicom", str(tmp_path / "rs")], check=True, capture_output=True)
    case = case_from_rtstruct(str(tmp_path / "ct"), glob.glob(str(tmp_path / "rs" / "*.dcm"))[0])
    assert case.meta["roi_names"] == {"pancreas": "Pancreas", "stomach": "Stomach", "duodenum": "Duodenum", "left_kidney": "Kidney_L"}
    grid = case.geometry.apply_to(sitk.GetImageFromArray(case.labels.astype(np.uint8)))
    truth = sitk.GetArrayFromImage(sitk.Resample(lab, grid, sitk.Transform(), sitk.sitkNearestNeighbor, 0))
    organs = {"pancreas": "Pancreas", "stomach": "Stomach", "duodenum": "Duodenum", "left_kidney": "Kidney_L"}
    for organ, name in organs.items():
        assert dice(case.labels == case.label_map[organ], truth == values[name]) >= 0.95, organ


def test_a_track_of_the_real_ct_writes_dicom_that_dciodvfy_accepts_and_says_what_left_the_dose_grid(tmp_path):
    """Issue 51: every DICOM object written from the real CT (its series written by plastimatch, another program; its
    organs as plastimatch's structure set; a synthetic cine of its session; a 40 Gy dose on its grid) passes dciodvfy
    with no error, and the organs the motion carries off the dose grid (the CT crops them at its edges) are reported
    per frame, never counted as 0 Gy in silence."""
    import glob
    import warnings

    from conftest import data_case
    from warpmpm.dicom_rt import read_series_reference
    from warpmpm.errors import InputWarning

    labels_path, image_path = data_case("totalseg_ct")
    pm, dv = need("plastimatch"), need("dciodvfy")
    lab = sitk.ReadImage(labels_path)
    (tmp_path / "masks").mkdir()
    for name, v in {"Pancreas": 7, "Stomach": 6, "Duodenum": 19, "Kidney_L": 3}.items():
        sitk.WriteImage(sitk.Cast(lab == v, sitk.sitkUInt8), str(tmp_path / "masks" / f"{name}.nrrd"))
    subprocess.run([pm, "convert", "--input", image_path, "--output-dicom", str(tmp_path / "ct")], check=True, capture_output=True)
    subprocess.run([pm, "convert", "--input-prefix", str(tmp_path / "masks"), "--referenced-ct", str(tmp_path / "ct"),
                    "--output-dicom", str(tmp_path / "rs")], check=True, capture_output=True)
    cine = tmp_path / "cine"
    assert main(["make-cine", "--image", image_path, "--labels", labels_path, "--preset", "totalseg_ct", "--frames", "3",
                 "--plane", "sagittal,coronal", "--out", str(cine)]) == 0
    ref = read_series_reference(str(tmp_path / "ct"))
    same_session(str(cine / "cine"), ref)
    write_rtdose(str(tmp_path / "RD.dcm"), ref, np.full(tuple(ref.geometry.size[::-1]), 40.0))
    out = tmp_path / "track"
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        assert main(["track", "--device", "cpu", "--image", str(tmp_path / "ct"), "--rtstruct", glob.glob(str(tmp_path / "rs" / "*.dcm"))[0],
                     "--cine", str(cine / "cine"), "--out", str(out), "--dicom", "--dose", str(tmp_path / "RD.dcm")]) == 0
    written = sorted(glob.glob(str(out / "dicom" / "**" / "*.dcm"), recursive=True))
    assert len(written) == 3 * 2 + 1
    for f in written:
        report = subprocess.run([dv, f], capture_output=True, text=True).stderr
        assert not [ln for ln in report.splitlines() if ln.startswith("Error")], (f, report)
    rows = list(csv.DictReader(open(out / "dose" / "dose_coverage.csv")))
    outside = {k: max(float(r[k]) for r in rows) for k in rows[0] if k != "frame"}
    named = [str(w.message) for w in seen if issubclass(w.category, InputWarning) and "outside the dose grid" in str(w.message)]
    for organ_column, pct in outside.items():  # every organ carried past the 1 % threshold is named in a warning
        organ = organ_column.replace("_outside_dose_grid_pct", "")
        if pct > 1.0:
            assert any(f"of the {organ}" in m for m in named), (organ, pct, named)
