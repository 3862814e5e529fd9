"""Try hostile and careless inputs against the command line, as a new user would, and count the outcomes.

    python scripts/hostile_inputs.py [--out hostile.md]

Each case runs ``warpmpm`` (or a Python snippet) in a fresh process on the tiny phantom (or on broken copies
of it) and is classified:

- ``clear error``: exit code 2 or 3, one ``error:`` / ``simulation error:`` line, no traceback, nothing written;
- ``handled``: exit code 0 with the reason on stderr (a ``warning:`` line), or the expected refusal;
- ``crash``: a traceback; ``silent``: exit 0 where an error or a warning was expected; ``partial output``:
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


def classify(proc, expected, outputs_before, d, api=False):
    err = proc.stderr
    left = set(os.listdir(d)) - outputs_before
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    if api and lines and lines[-1].startswith("warpmpm.errors.InputError"):
        return "clear error"  # the API raises InputError naming the problem (a traceback is how Python shows it)
    if "Traceback" in err:
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
    a = p.parse_args(argv)
    exe = os.path.join(os.path.dirname(sys.executable), "warpmpm")
    with tempfile.TemporaryDirectory() as d:
        make_files(d)
        rows, counts = [], {}
        for name, argv_, expected in cases(d):
            cmd = [exe] + argv_[1:] if argv_[0] == "warpmpm" else [sys.executable] + argv_[1:]
            before = set(os.listdir(d))
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=d, timeout=600, env=dict(os.environ, PYTHONPATH=ROOT))
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
