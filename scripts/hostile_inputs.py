"""Try hostile and careless inputs against the command line, as a new user would, and count the outcomes.

    python scripts/hostile_inputs.py [--out hostile.md]
    python scripts/hostile_inputs.py --clinic     # the clinic's broken files: cine, planning series, RTSTRUCT, RT Dose, CSVs

Each case runs ``warpmpm`` (or a Python snippet) in a fresh process on the tiny phantom (or on broken copies
of it) and is classified:

- ``clear error``: exit code 2 or 3, one ``error:`` / ``simulation error:`` line, no traceback, nothing written;
- ``handled``: exit code 0 with the reason on stderr (a ``warning:`` line), or the expected refusal;
- ``crash``: a traceback (or an ``internal error:`` line: an error warpmpm did not foresee); ``silent``: exit 0 where an error or a warning was expected; ``partial output``:
  an output file left behind by a failed run.
"""

import argparse
import gzip
import os
import subprocess
import sys
import tempfile

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
TINY = ["--phantom-resolution", "3", "--device", "cpu", "--quiet", "--no-volume-registration"]


def make_files(d):
    """Broken copies of the tiny phantom: truncated, NaN voxels, far duodenum, junk, empty."""
    from dataclasses import replace

    import numpy as np

    from warpmpm.images import write_case
    from warpmpm.phantom import make_phantom

    c = make_phantom(resolution=3.0)
    write_case(c, f"{d}/labels.nii.gz", f"{d}/image.nii.gz")
    data = open(f"{d}/labels.nii.gz", "rb").read()
    open(f"{d}/truncated.nii.gz", "wb").write(data[: len(data) // 2])
    raw = gzip.decompress(data)
    open(f"{d}/short.nii.gz", "wb").write(gzip.compress(raw[: len(raw) * 2 // 3]))
    img = c.image.copy()
    img[2, 3, 4] = np.nan
    write_case(replace(c, image=img), f"{d}/nan_labels.nii.gz", f"{d}/nan_image.nii.gz")
    lab = c.labels.copy()
    lab[lab == c.label_map["duodenum"]] = 0
    lab[-3:, -6:, -6:] = c.label_map["duodenum"]
    write_case(replace(c, labels=lab), f"{d}/far.nii.gz")
    lab = c.labels.copy()
    lab[lab == c.label_map["pancreas"]] = 0
    write_case(replace(c, labels=lab), f"{d}/nopancreas.nii.gz")
    open(f"{d}/junk.nii.gz", "wb").write(b"this is not an image")
    open(f"{d}/empty.nii", "wb").write(b"")
    open(f"{d}/junk.rrd", "wb").write(b"junk")
    open(f"{d}/empty.rrd", "wb").write(b"")
    far = replace(c, geometry=replace(c.geometry, origin_mm=(5000.0, 0.0, 0.0)))
    write_case(far, f"{d}/far_labels.nii.gz", f"{d}/other_grid.nii.gz")
    import SimpleITK as sitk

    sitk.WriteImage(sitk.Flip(sitk.ReadImage(f"{d}/labels.nii.gz"), [False, True, False]), f"{d}/flipped.nii.gz")
    os.makedirs(f"{d}/adir", exist_ok=True)
    # the clinic's files: a planning series with its structure set and dose, and broken cine / dose / structure files
    from warpmpm.dicom_rt import write_rtdose, write_rtstruct, write_series

    ref = write_series(c.intensity_image(), f"{d}/series", "MR")
    masks = {o: c.labels == v for o, v in c.label_map.items()}
    write_rtstruct(f"{d}/RS.dcm", ref, masks, {"pancreas": "Pancreas", "stomach": "Stomach", "duodenum": "Duodenum",
                                               "left_kidney": "Kidney_L"})
    write_rtstruct(f"{d}/RS_nopancreas.dcm", ref, {o: m for o, m in masks.items() if o != "pancreas"})
    write_rtdose(f"{d}/RD.dcm", ref, np.full(c.labels.shape, 2.0))
    other = write_series(c.intensity_image(), f"{d}/other_series", "MR")  # the same pixels, another frame of reference
    write_rtstruct(f"{d}/RS_other.dcm", other, masks)
    os.makedirs(f"{d}/badcine", exist_ok=True)
    open(f"{d}/badcine/frame.bin", "wb").write(b"\x00\x01\x00\x00\x00" + b"junk" * 10)
    open(f"{d}/junk.bin", "wb").write(b"not a cine frame")
    open(f"{d}/beam.csv", "w").write("frame,beam_on_s\n0,-1\n")
    os.makedirs(f"{d}/cine", exist_ok=True)
    sitk.WriteImage(c.intensity_image()[20:21, :, :], f"{d}/cine/frame_000.nii.gz")


def cases(d):
    w = ["warpmpm"]
    run = w + ["run"] + TINY
    return [
        # (name, argv, expected: "error" | "warning" | "ok")
        ("missing labels file", run + ["--labels", f"{d}/nope.nii.gz"], "error"),
        ("image without labels", run + ["--image", f"{d}/image.nii.gz"], "error"),
        ("truncated gzip", run + ["--labels", f"{d}/truncated.nii.gz"], "error"),
        ("complete gzip of a cut NIfTI", run + ["--labels", f"{d}/short.nii.gz"], "error"),
        ("junk file as labels", run + ["--labels", f"{d}/junk.nii.gz"], "error"),
        ("empty file as labels", run + ["--labels", f"{d}/empty.nii"], "error"),
        ("NaN voxels in the image", run + ["--labels", f"{d}/nan_labels.nii.gz", "--image", f"{d}/nan_image.nii.gz"], "error"),
        ("image that does not overlap the labels", run + ["--labels", f"{d}/labels.nii.gz", "--image", f"{d}/other_grid.nii.gz"], "error"),
        ("labels on a flipped grid", run + ["--labels", f"{d}/flipped.nii.gz", "--image", f"{d}/image.nii.gz", "--organs", "p",
                                           "--max-steps", "50"], "warning"),
        ("no pancreas in the labels", run + ["--labels", f"{d}/nopancreas.nii.gz"], "error"),
        ("wrong preset (a far 'duodenum')", run + ["--labels", f"{d}/far.nii.gz", "--organs", "pd", "--max-steps", "50"], "warning"),
        ("unknown preset", run + ["--preset", "foo"], "error"),
        ("unknown organ letter", run + ["--organs", "px"], "error"),
        ("combination without pancreas", run + ["--organs", "sd"], "error"),
        ("slice outside the volume", run + ["--slices", "axial:9999"], "error"),
        ("negative slice", run + ["--slices", "axial:-3"], "error"),
        ("empty slice", run + ["--slices", "axial:0"], "error"),
        ("bad orientation", run + ["--slices", "oblique:3"], "error"),
        ("slice without index", run + ["--slices", "axial"], "error"),
        ("non-integer slice", run + ["--slices", "axial:x"], "error"),
        ("repeated slice", run + ["--slices", "axial:8,axial:8", "--organs", "p", "--max-steps", "100"], "warning"),
        ("unknown auto mode", run + ["--slices", "auto:zz"], "error"),
        ("deformation 0", run + ["--deformation", "0"], "error"),
        ("deformation 9", run + ["--deformation", "9"], "error"),
        ("negative contact scenario", run + ["--protocol", "contact", "--deformation", "-1"], "error"),
        ("negative phantom seed", run + ["--phantom-seed", "-1"], "error"),
        ("huge phantom seed", run + ["--phantom-seed", str(2**40)], "error"),
        ("NaN phantom resolution", run + ["--phantom-resolution", "nan"], "error"),
        ("zero phantom resolution", run + ["--phantom-resolution", "0"], "error"),
        ("particle step 0", run + ["--particle-step", "0"], "error"),
        ("particle step 1000", run + ["--particle-step", "1000"], "error"),
        ("max steps 0", run + ["--max-steps", "0"], "error"),
        ("rrd-every 0", run + ["--rrd-every", "0"], "error"),
        ("--json onto a directory", run + ["--json", f"{d}/adir"], "error"),
        ("--rrd onto a directory", run + ["--rrd", f"{d}/adir"], "error"),
        ("--json into a missing folder", run + ["--json", f"{d}/missing/o.json"], "error"),
        ("--device cuda without a GPU", run + ["--device", "cuda"], "error"),
        ("missing selector model", run + ["--slices", "auto", "--selector", f"{d}/nope.json"], "error"),
        ("junk recording", w + ["view", "--summary", f"{d}/junk.rrd"], "error"),
        ("empty recording", w + ["view", "--summary", f"{d}/empty.rrd"], "error"),
        ("missing recording", w + ["view", "--summary", f"{d}/nope.rrd"], "error"),
        ("sweep: slice stride 0", w + ["sweep", "--slice-stride", "0", "--out", f"{d}/s.csv"], "error"),
        ("sweep: bad seeds", w + ["sweep", "--phantom-seeds", "a,b", "--out", f"{d}/s.csv"], "error"),
        ("sweep: negative seed", w + ["sweep", "--phantom-seeds", "-1", "--out", f"{d}/s.csv"], "error"),
        ("sweep: deformation 12", w + ["sweep", "--deformations", "12", "--out", f"{d}/s.csv"], "error"),
        ("sweep: bad organs", w + ["sweep", "--organs", "zz", "--out", f"{d}/s.csv"], "error"),
        ("sweep: workers 0", w + ["sweep", "--workers", "0", "--out", f"{d}/s.csv"], "error"),
        ("multi: top 0", w + ["multi", "--top", "0", "--out", f"{d}/m.csv"], "error"),
        ("train: missing CSV", w + ["train", f"{d}/nope.csv"], "error"),
        ("cfl 3 (API)", ["python", "-c", "from warpmpm.solvers import ExplicitConfig; ExplicitConfig(cfl=3)"], "error"),
        ("cfl 0 (API)", ["python", "-c", "from warpmpm.solvers import ExplicitConfig; ExplicitConfig(cfl=0)"], "error"),
        ("quasi-static with sliding contact", run + ["--solver", "quasistatic", "--contact", "sliding"], "error"),
        ("threads 0", run + ["--threads", "0"], "error"),
        ("auto solver with sliding contact", run + ["--solver", "auto", "--contact", "sliding"], "error"),
        ("unknown registration backend", run + ["--registration", "lbfgs"], "error"),
        ("registration passes 0", run + ["--registration-passes", "0"], "error"),
        ("unknown tracker reference (API)", ["python", "-c", "from warpmpm.tracker import TrackerConfig, Tracker; "
                                             "from warpmpm.phantom import make_phantom; "
                                             "Tracker(make_phantom(resolution=3.0), [], TrackerConfig(reference='none'))"], "error"),
        ("NaN linear prior (API)", ["python", "-c", "from warpmpm.gauss_newton import GaussNewtonConfig; "
                                    "GaussNewtonConfig(linear_prior=float('nan'))"], "error"),
        ("auto: 0 Newton iterations (API)", ["python", "-c", "from warpmpm.solvers import QuasiStaticConfig; "
                                             "QuasiStaticConfig(auto_newton_iterations=0)"], "error"),
        ("quasi-static: CG tolerance 2 (API)", ["python", "-c", "from warpmpm.solvers import QuasiStaticConfig; "
                                                "QuasiStaticConfig(cg_tolerance=2.0)"], "error"),
        ("NaN extra points (API)", ["python", "-c", "import numpy as np; from warpmpm.scenes import block_model; "
                                    "from warpmpm.solvers import MPMModel, SolverConfig; "
                                    "MPMModel(block_model((3,3,3)), SolverConfig(device='cpu'), np.full((1,3), np.nan))"], "error"),
        ("cell smaller than the slice gap (API)", ["python", "-c", "from warpmpm.images import *; import numpy as np; "
                                                   "from warpmpm.model import build_model; from warpmpm.solvers import GridConfig, MPMModel, SolverConfig; "
                                                   "l=np.zeros((10,20,20),np.int32); l[2:8,4:16,4:16]=10; "
                                                   "m=build_model(Case(l, Geometry((20,20,10),(0.8,0.8,5.0),(0,0,0)), PRESETS['amos']), 'p', lattice='voxel'); "
                                                   "MPMModel(m, SolverConfig(device='cpu', grid=GridConfig(cell_size_mm=1.0)))"], "error"),
        ("less than one particle layer a cell (API)", ["python", "-c", "from warpmpm.solvers import GridConfig; "
                                                       "GridConfig(min_layers_per_cell=0.5)"], "error"),
        ("an unknown rigid-mode acceleration (API)", ["python", "-c", "from warpmpm.solvers import AccelerationConfig; "
                                                      "AccelerationConfig(mode='yes')"], "error"),
        ("rigid-mode acceleration forced on with sliding contact (API)",
         ["python", "-c", "from warpmpm.solvers import *; SolverConfig(acceleration=AccelerationConfig(mode='on'), explicit=ExplicitConfig(contact='sliding'))"],
         "error"),
        ("a negative rigid-mode cube (API)", ["python", "-c", "from warpmpm.solvers import AccelerationConfig; "
                                              "AccelerationConfig(aggregate_mm=-5.0)"], "error"),
        ("make-truth: NaN phantom resolution", w + ["make-truth", "--phantom-resolution", "nan", "--out", f"{d}/mt1"], "error"),
        ("make-truth: negative phantom seed", w + ["make-truth", "--phantom-seed", "-3", "--out", f"{d}/mt2"], "error"),
        ("make-cine: NaN phantom resolution", w + ["make-cine", "--phantom-resolution", "nan", "--out", f"{d}/mc1"], "error"),
        ("make-cine: particle step 0", w + ["make-cine", "--particle-step", "0", "--out", f"{d}/mc2"], "error"),
        ("track: --organs with unknown letters", w + ["track", "--image", f"{d}/image.nii.gz", "--labels", f"{d}/labels.nii.gz",
                                                      "--organs", "pxz", "--cine", f"{d}/cine", "--out", f"{d}/t13"], "error"),
        ("track: --max-steps 0", w + ["track", "--image", f"{d}/image.nii.gz", "--labels", f"{d}/labels.nii.gz",
                                      "--max-steps", "0", "--cine", f"{d}/cine", "--out", f"{d}/t14"], "error"),
        ("cine-info: a junk .bin", w + ["cine-info", f"{d}/junk.bin"], "error"),
        ("cine-info: a missing file", w + ["cine-info", f"{d}/nope.dcm"], "error"),
        ("track: a cine folder holding a broken .bin", w + ["track", "--image", f"{d}/image.nii.gz", "--labels", f"{d}/labels.nii.gz",
                                                          "--cine", f"{d}/badcine", "--out", f"{d}/t1"], "error"),
        ("track: --rtstruct without a DICOM series", w + ["track", "--image", f"{d}/image.nii.gz", "--rtstruct", f"{d}/RS.dcm",
                                                         "--cine", f"{d}/cine", "--out", f"{d}/t2"], "error"),
        ("track: --rtstruct and --labels both", w + ["track", "--image", f"{d}/series", "--rtstruct", f"{d}/RS.dcm", "--labels",
                                                   f"{d}/labels.nii.gz", "--cine", f"{d}/cine", "--out", f"{d}/t3"], "error"),
        ("track: a structure set without the pancreas", w + ["track", "--image", f"{d}/series", "--rtstruct", f"{d}/RS_nopancreas.dcm",
                                                            "--cine", f"{d}/cine", "--out", f"{d}/t4"], "error"),
        ("track: a structure set of another scan", w + ["track", "--image", f"{d}/series", "--rtstruct", f"{d}/RS_other.dcm",
                                                       "--cine", f"{d}/cine", "--out", f"{d}/t5"], "error"),
        ("track: --structure without '='", w + ["track", "--image", f"{d}/series", "--rtstruct", f"{d}/RS.dcm", "--structure",
                                               "pancreas", "--cine", f"{d}/cine", "--out", f"{d}/t6"], "error"),
        ("track: --structure naming an unknown organ", w + ["track", "--image", f"{d}/series", "--rtstruct", f"{d}/RS.dcm",
                                                           "--structure", "liver=Liver", "--cine", f"{d}/cine", "--out", f"{d}/t7"], "error"),
        ("track: --structure naming a missing ROI", w + ["track", "--image", f"{d}/series", "--rtstruct", f"{d}/RS.dcm",
                                                        "--structure", "pancreas=GTV", "--cine", f"{d}/cine", "--out", f"{d}/t8"], "error"),
        ("track: a junk --dose", w + ["track", "--image", f"{d}/image.nii.gz", "--labels", f"{d}/labels.nii.gz", "--dose",
                                     f"{d}/junk.nii.gz", "--cine", f"{d}/cine", "--out", f"{d}/t9"], "error"),
        ("track: a negative beam-on time", w + ["track", "--image", f"{d}/image.nii.gz", "--labels", f"{d}/labels.nii.gz", "--dose",
                                               f"{d}/RD.dcm", "--beam-on", f"{d}/beam.csv", "--cine", f"{d}/cine", "--out", f"{d}/t10"],
         "error"),
        ("track: --beam-on without --dose", w + ["track", "--image", f"{d}/image.nii.gz", "--labels", f"{d}/labels.nii.gz",
                                                "--beam-on", f"{d}/beam.csv", "--cine", f"{d}/cine", "--out", f"{d}/t11"], "error"),
        ("track: --trackrad-centre on a plain cine", w + ["track", "--image", f"{d}/image.nii.gz", "--labels", f"{d}/labels.nii.gz",
                                                         "--trackrad-centre", "1,2,3", "--cine", f"{d}/cine", "--out", f"{d}/t12"], "error"),
        ("an unknown rigid-mode coarse basis (API)", ["python", "-c", "from warpmpm.solvers import AccelerationConfig; "
                                                     "AccelerationConfig(basis='quadratic')"], "error"),
    ]


# the clinic's files, broken as a careless or unlucky clinic would (issue 51) ---------------------------------------------

def _edit_dicom(src, dst, edit):
    """Copy the DICOM file ``src`` to ``dst`` with ``edit(ds)`` applied."""
    import pydicom

    ds = pydicom.dcmread(src)
    edit(ds)
    ds.save_as(dst)


def _copy_folder(src, dst, edit_each=None, only=None):
    """Copy a folder of DICOM files, editing each (or the file names in ``only``) with ``edit_each(ds, k)``."""
    import shutil

    os.makedirs(dst, exist_ok=True)
    for k, name in enumerate(sorted(os.listdir(src))):
        if edit_each is not None and (only is None or k in only):
            _edit_dicom(os.path.join(src, name), os.path.join(dst, name), lambda ds, k=k: edit_each(ds, k))
        else:
            shutil.copy(os.path.join(src, name), os.path.join(dst, name))


def make_clinic_files(d):
    """A phantom clinic set (planning MR series, RT Structure Set, RT Dose of 50 Gy around the pancreas, a sagittal DICOM
    cine of the same session: its frame of reference and patient) and broken copies of each of its files."""
    import shutil

    import numpy as np
    import pydicom

    from warpmpm.cli import main as warpmpm
    from warpmpm.dicom_rt import write_rtdose, write_rtstruct, write_series
    from warpmpm.images import load_case

    c = f"{d}/clinic"
    os.makedirs(c, exist_ok=True)
    with open(os.devnull, "w") as null:
        import contextlib

        with contextlib.redirect_stdout(null), contextlib.redirect_stderr(null):
            assert warpmpm(["make-cine", "--phantom-resolution", "3", "--frames", "3", "--plane", "sagittal", "--out",
                            f"{c}/made"]) == 0
    case = load_case(f"{c}/made/planning/labels.nii.gz", f"{c}/made/planning/image.nii.gz")
    ref = write_series(case.intensity_image(), f"{c}/series", "MR", patient_id="CLINIC-1")
    masks = {o: case.labels == v for o, v in case.label_map.items()}
    names = {"pancreas": "Pancreas", "stomach": "Stomach", "duodenum": "Duodenum", "left_kidney": "Kidney_L"}
    write_rtstruct(f"{c}/RS.dcm", ref, masks, names)
    dose = np.where(masks["pancreas"], 50.0, 10.0)
    write_rtdose(f"{c}/RD.dcm", ref, dose)

    from warpmpm.experiment.cine_series import same_session

    _copy_folder(f"{c}/made/cine", f"{c}/cine")
    same_session(f"{c}/cine", ref)  # the cine of the planning session: its frame of reference and patient
    shutil.rmtree(f"{c}/made/truth")
    first = sorted(os.listdir(f"{c}/cine"))
    # cine
    _copy_folder(f"{c}/cine", f"{c}/cine_negative_spacing", lambda ds, k: setattr(ds, "PixelSpacing", ["-2", "-2"]))
    _copy_folder(f"{c}/cine", f"{c}/cine_one_untimed", lambda ds, k: delattr(ds, "AcquisitionTime"), only={1})
    _copy_folder(f"{c}/cine", f"{c}/cine_no_spacing", lambda ds, k: delattr(ds, "PixelSpacing"), only={0})
    _copy_folder(f"{c}/cine", f"{c}/cine_no_position", lambda ds, k: delattr(ds, "ImagePositionPatient"), only={0})
    _copy_folder(f"{c}/cine", f"{c}/cine_hours", lambda ds, k: setattr(ds, "AcquisitionTime", f"{10 + k:02d}"))
    _copy_folder(f"{c}/cine", f"{c}/cine_other_for", lambda ds, k: setattr(ds, "FrameOfReferenceUID", "1.2.826.0.1.3680043.2.1125.77"))
    _copy_folder(f"{c}/cine", f"{c}/cine_other_patient", lambda ds, k: setattr(ds, "PatientID", "SOMEONE-ELSE"))
    # structure sets
    rs = pydicom.dcmread(f"{c}/RS.dcm")

    def dup_number(ds):
        ds.StructureSetROISequence[1].ROINumber = ds.StructureSetROISequence[0].ROINumber

    _edit_dicom(f"{c}/RS.dcm", f"{c}/RS_dup_number.dcm", dup_number)

    def nan_point(ds):
        cd = list(ds.ROIContourSequence[0].ContourSequence[0].ContourData)
        cd[0] = "nan"
        ds.ROIContourSequence[0].ContourSequence[0].ContourData = cd

    _edit_dicom(f"{c}/RS.dcm", f"{c}/RS_nan.dcm", nan_point)
    data = open(f"{c}/RS.dcm", "rb").read()
    open(f"{c}/RS_cut.dcm", "wb").write(data[: int(len(data) * 0.6)])
    k_top = max(float(cc.ContourData[2]) for cc in rs.ROIContourSequence[0].ContourSequence)

    def off_series(ds):  # the pancreas's top contours moved 200 mm up: off the series
        for cc in ds.ROIContourSequence[0].ContourSequence:
            pts = [float(v) for v in cc.ContourData]
            if pts[2] >= k_top - 10:
                cc.ContourData = [f"{v + 200.0 if i % 3 == 2 else v:.3f}" for i, v in enumerate(pts)]

    _edit_dicom(f"{c}/RS.dcm", f"{c}/RS_off_series.dcm", off_series)
    # doses
    _edit_dicom(f"{c}/RD.dcm", f"{c}/RD_no_scaling.dcm", lambda ds: delattr(ds, "DoseGridScaling"))
    _edit_dicom(f"{c}/RD.dcm", f"{c}/RD_nan_scaling.dcm", lambda ds: setattr(ds, "DoseGridScaling", "nan"))
    _edit_dicom(f"{c}/RD.dcm", f"{c}/RD_zero_spacing.dcm", lambda ds: setattr(ds, "PixelSpacing", ["0", "0"]))
    _edit_dicom(f"{c}/RD.dcm", f"{c}/RD_cgy.dcm", lambda ds: setattr(ds, "DoseGridScaling", f"{float(ds.DoseGridScaling) * 100:.8g}"))
    _edit_dicom(f"{c}/RD.dcm", f"{c}/RD_other_for.dcm", lambda ds: setattr(ds, "FrameOfReferenceUID", "1.2.826.0.1.3680043.2.1125.78"))

    def negative(ds):
        ds.PixelRepresentation = 1
        arr = ds.pixel_array.astype(np.int32) // 2
        arr.flat[0] = -1000
        ds.PixelData = arr.astype("<i2").tobytes()

    _edit_dicom(f"{c}/RD.dcm", f"{c}/RD_negative.dcm", negative)

    def small_grid(ds):  # the dose grid covers the lower half of the slices only
        n = int(ds.NumberOfFrames) // 3
        arr = ds.pixel_array[:n]
        ds.NumberOfFrames = n
        ds.GridFrameOffsetVector = list(ds.GridFrameOffsetVector)[:n]
        ds.PixelData = np.ascontiguousarray(arr).astype("<u2").tobytes()

    _edit_dicom(f"{c}/RD.dcm", f"{c}/RD_small_grid.dcm", small_grid)
    # beam-on files
    open(f"{c}/beam_binary.csv", "wb").write(bytes(range(256)) * 4)
    open(f"{c}/beam_bom.csv", "w", encoding="utf-8-sig").write("frame,beam_on_s\n0,0.2\n1,0.2\n2,0.2\n")
    open(f"{c}/beam_huge.csv", "w").write("frame,beam_on_s\n0,1e308\n1,1e308\n2,0.2\n")
    # planning series
    series = sorted(os.listdir(f"{c}/series"))
    _copy_folder(f"{c}/series", f"{c}/series_gap")
    os.remove(f"{c}/series_gap/{series[len(series) // 2]}")
    _copy_folder(f"{c}/series", f"{c}/series_spacing", lambda ds, k: setattr(ds, "PixelSpacing", ["3.5", "3.5"]), only={4})
    tilt = np.radians(10.0)
    _copy_folder(f"{c}/series", f"{c}/series_tilted", lambda ds, k: setattr(
        ds, "ImageOrientationPatient", ["1", "0", "0", "0", f"{np.cos(tilt):.6f}", f"{np.sin(tilt):.6f}"]), only={4})

    def no_uids(ds, k):
        for tag in ("StudyInstanceUID", "SeriesInstanceUID", "FrameOfReferenceUID"):
            setattr(ds, tag, "")

    _copy_folder(f"{c}/series", f"{c}/series_empty_uids", no_uids)
    # other commands' files
    import json

    open(f"{c}/model_list.json", "w").write(json.dumps([1, 2, 3]))
    open(f"{c}/random.csv", "wb").write(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    open(f"{c}/other_columns.csv", "w").write("a,b,c\n1,2,3\n4,5,6\n")
    os.makedirs(f"{c}/cut_track")
    open(f"{c}/cut_track/track.csv", "w").write("frame,time_s,plane,latency_s\n0,0.0,0,0.1\n1,0.3,0,0.")
    return first


def clinic_cases(d):
    """(name, argv, expected) for the clinic's broken files of :func:`make_clinic_files` (issue 51)."""
    c = f"{d}/clinic"
    track = ["warpmpm", "track", "--device", "cpu", "--image", f"{c}/series", "--rtstruct", f"{c}/RS.dcm"]

    def t(name, *extra, expected="error", cine=f"{c}/cine"):
        return (f"clinic: {name}", [*track, "--cine", cine, "--out", f"{d}/out_{abs(hash(name)) % 10**8}", *extra], expected)

    w = ["warpmpm"]
    return [
        t("the clean clinic set", "--dose", f"{c}/RD.dcm", "--dicom", expected="ok"),
        ("clinic: --overwrite onto the cine folder", [*track, "--cine", f"{c}/cine", "--out", f"{c}/cine", "--overwrite"], "error"),
        ("clinic: --overwrite onto the planning series", [*track, "--cine", f"{c}/cine", "--out", f"{c}/series", "--overwrite"],
         "error"),
        t("negative PixelSpacing on every cine frame", cine=f"{c}/cine_negative_spacing"),
        t("one cine frame without AcquisitionTime", cine=f"{c}/cine_one_untimed"),
        t("a cine frame without PixelSpacing", cine=f"{c}/cine_no_spacing"),
        t("a cine frame without ImagePositionPatient", cine=f"{c}/cine_no_position"),
        t("AcquisitionTime given as hours only", cine=f"{c}/cine_hours", expected="ok"),
        t("a cine on another frame of reference", cine=f"{c}/cine_other_for"),
        t("a cine on another frame of reference, said to be registered", "--assume-registered", cine=f"{c}/cine_other_for",
          expected="warning"),
        t("a cine of another patient", cine=f"{c}/cine_other_patient"),
        ("clinic: two ROIs sharing a ROINumber", [*track[:6], "--rtstruct", f"{c}/RS_dup_number.dcm", "--cine", f"{c}/cine",
                                                  "--out", f"{d}/o1"], "error"),
        ("clinic: a NaN contour point", [*track[:6], "--rtstruct", f"{c}/RS_nan.dcm", "--cine", f"{c}/cine", "--out", f"{d}/o2"],
         "error"),
        ("clinic: a structure set cut at 60 %", [*track[:6], "--rtstruct", f"{c}/RS_cut.dcm", "--cine", f"{c}/cine", "--out",
                                                 f"{d}/o3"], "error"),
        ("clinic: pancreas contours off the series", [*track[:6], "--rtstruct", f"{c}/RS_off_series.dcm", "--cine", f"{c}/cine",
                                                      "--out", f"{d}/o4"], "warning"),
        t("an RT Dose without DoseGridScaling", "--dose", f"{c}/RD_no_scaling.dcm"),
        t("an RT Dose with DoseGridScaling NaN", "--dose", f"{c}/RD_nan_scaling.dcm"),
        t("an RT Dose with PixelSpacing 0", "--dose", f"{c}/RD_zero_spacing.dcm"),
        t("an RT Dose in cGy labelled GY", "--dose", f"{c}/RD_cgy.dcm"),
        t("an RT Dose with negative voxels", "--dose", f"{c}/RD_negative.dcm"),
        t("an RT Dose on another frame of reference", "--dose", f"{c}/RD_other_for.dcm"),
        t("a dose grid that misses part of the organs", "--dose", f"{c}/RD_small_grid.dcm", expected="warning"),
        t("a binary beam-on CSV", "--dose", f"{c}/RD.dcm", "--beam-on", f"{c}/beam_binary.csv"),
        t("a beam-on CSV with a UTF-8 BOM", "--dose", f"{c}/RD.dcm", "--beam-on", f"{c}/beam_bom.csv", expected="ok"),
        t("a beam-on time of 1e308 s", "--dose", f"{c}/RD.dcm", "--beam-on", f"{c}/beam_huge.csv"),
        ("clinic: a planning series with a missing slice", ["warpmpm", "track", "--device", "cpu", "--image", f"{c}/series_gap",
                                                            "--rtstruct", f"{c}/RS.dcm", "--cine", f"{c}/cine", "--out", f"{d}/o5"],
         "error"),
        ("clinic: a planning slice of another pixel spacing", ["warpmpm", "track", "--device", "cpu", "--image", f"{c}/series_spacing",
                                                               "--rtstruct", f"{c}/RS.dcm", "--cine", f"{c}/cine", "--out", f"{d}/o6"],
         "error"),
        ("clinic: a planning slice tilted 10 degrees", ["warpmpm", "track", "--device", "cpu", "--image", f"{c}/series_tilted",
                                                        "--rtstruct", f"{c}/RS.dcm", "--cine", f"{c}/cine", "--out", f"{d}/o7"],
         "error"),
        ("clinic: /dev/zero as the labels", w + ["make-truth", "--image", f"{c}/made/planning/image.nii.gz", "--labels",
                                                 "/dev/zero", "--out", f"{d}/o8"], "error"),
        ("clinic: plan-planes --model on a JSON list", w + ["plan-planes", "--image", f"{c}/made/planning/image.nii.gz",
                                                            "--labels", f"{c}/made/planning/labels.nii.gz", "--method", "model",
                                                            "--model", f"{c}/model_list.json"], "error"),
        ("clinic: plan-planes --picture where nothing can be written", w + [
            "plan-planes", "--image", f"{c}/made/planning/image.nii.gz", "--labels", f"{c}/made/planning/labels.nii.gz",
            "--method", "model", "--picture", "/proc/warpmpm-planes.png"], "error"),
        ("clinic: train-planes on random bytes", w + ["train-planes", f"{c}/random.csv", "--out", f"{d}/o9.json"], "error"),
        ("clinic: train-planes on a CSV of other columns", w + ["train-planes", f"{c}/other_columns.csv", "--out", f"{d}/o10.json"],
         "error"),
        ("clinic: sweep-planes resuming a CSV of random bytes", w + ["sweep-planes", "--out", f"{c}/random.csv"], "error"),
        ("clinic: sweep-planes resuming a CSV of other columns", w + ["sweep-planes", "--out", f"{c}/other_columns.csv"], "error"),
        ("clinic: evaluate-track on a track.csv cut mid-line", w + ["evaluate-track", "--track", f"{c}/cut_track", "--truth",
                                                                    f"{c}/made/truth"], "error"),
    ]


def run_in_process(argv):
    """Run ``warpmpm argv`` in this process: (exit code, stderr). An exception that escapes :func:`warpmpm.cli.main` is
    reported as a traceback (it would be one on the command line)."""
    import contextlib
    import io
    import traceback
    import warnings

    from warpmpm.cli import main as warpmpm

    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out), warnings.catch_warnings():
        warnings.simplefilter("always")
        import warnings as w

        show = w.showwarning
        w.showwarning = lambda m, c, f, n, file=None, line=None: print(f"warning: {m}", file=sys.stderr)
        try:
            code = warpmpm(argv)
        except SystemExit as exc:  # argparse
            code = exc.code
        except BaseException:  # noqa: BLE001
            print(traceback.format_exc(), file=sys.stderr)
            code = 1
        finally:
            w.showwarning = show
    return code, err.getvalue()


def classify(proc, expected, outputs_before, d, api=False):
    err = proc.stderr
    left = set(os.listdir(d)) - outputs_before
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    if api and lines and lines[-1].startswith("warpmpm.errors.InputError"):
        return "clear error"  # the API raises InputError naming the problem (a traceback is how Python shows it)
    if "Traceback" in err or "internal error:" in err:
        return "crash"
    if proc.returncode not in (0,) and left:
        return "partial output"
    if expected == "error":
        if proc.returncode in (2, 3) and lines and (lines[-1].startswith(("error:", "simulation error:"))
                                                    or lines[-1].startswith("warpmpm") and ": error:" in lines[-1]):  # argparse
            return "clear error"
        return "silent" if proc.returncode == 0 else f"unclear (exit {proc.returncode})"
    if expected == "warning":
        return "handled" if proc.returncode == 0 and "warning:" in err else ("clear error" if proc.returncode == 2 else "silent")
    return "handled" if proc.returncode == 0 else f"unexpected exit {proc.returncode}"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=None, help="write the table here (Markdown)")
    p.add_argument("--clinic", action="store_true", help="the clinic's broken files instead (issue 51), run in this process")
    a = p.parse_args(argv)
    exe = os.path.join(os.path.dirname(sys.executable), "warpmpm")
    with tempfile.TemporaryDirectory() as d:
        import types

        if a.clinic:
            make_clinic_files(d)
        else:
            make_files(d)
        rows, counts = [], {}
        for name, argv_, expected in (clinic_cases(d) if a.clinic else cases(d)):
            before = set(os.listdir(d))
            if a.clinic:
                code, err = run_in_process(argv_[1:])
                proc = types.SimpleNamespace(returncode=code, stderr=err)
            else:
                cmd = [exe] + argv_[1:] if argv_[0] == "warpmpm" else [sys.executable] + argv_[1:]
                proc = subprocess.run(cmd, capture_output=True, text=True, cwd=d, timeout=600,
                                      env=dict(os.environ, PYTHONPATH=ROOT))
            outcome = classify(proc, expected, before, d, api=argv_[0] == "python")
            counts[outcome] = counts.get(outcome, 0) + 1
            lines = proc.stderr.strip().splitlines() or [""]
            last = (next((ln for ln in lines if ln.startswith("warning:")), lines[-1]) if expected == "warning" else lines[-1])[:150]
            rows.append(f"| {name} | {expected} | {outcome} | {last} |")
            print(rows[-1], flush=True)
    table = "| input | expected | outcome | last stderr line |\n|---|---|---|---|\n" + "\n".join(rows)
    summary = f"{len(rows)} hostile inputs: " + ", ".join(f"{v} {k}" for k, v in sorted(counts.items()))
    print(summary)
    if a.out:
        with open(a.out, "w") as f:
            f.write(table + "\n\n" + summary + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
