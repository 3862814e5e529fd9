"""The main job: the product on the built-in phantom, from a truth to a scored track, in about half a minute on 2 cores.

    python examples/run_case.py                  # writes runs/main_job/
    python examples/run_case.py --out DIR --frames 8 --phantom-resolution 3

1. the phantom's planning scan and organ labels (``planning/``);
2. a finite-element truth the estimator did not make: breathing plus a duodenal push (``truth/``, ``warpmpm make-truth``);
3. a cine series imaged from it, interleaved sagittal / coronal DICOM frames (``cine/``, ``warpmpm make-cine``);
4. the series tracked from the planning scan alone, the truth never read (``track/``: label maps, displacement fields,
   ``track.csv``; ``track.rrd``, a Rerun recording);
5. the track scored against the truth, every organ, beside the baselines with the same information (``eval.json``,
   ``eval.png``).

Its table goes to stdout, one line per stage to stderr, and each stage's own output to ``log.txt``. The seed's
experiment (an MPM-made truth, one case) is ``examples/seed_experiment.py`` (= ``warpmpm run``).
"""

import argparse
import contextlib
import json
import os
import shutil
import sys
import time


from warpmpm.cli import main as warpmpm


def stage(name, argv, log):
    """Run one ``warpmpm`` command with its output in ``log``; one line to stderr."""
    t0 = time.perf_counter()
    with open(log, "a") as fh, contextlib.redirect_stdout(fh), contextlib.redirect_stderr(fh):
        print(f"\n$ warpmpm {' '.join(argv)}", flush=True)
        code = warpmpm(argv)
    if code != 0:
        raise SystemExit(f"{name} failed (exit {code}); see {log}")
    print(f"{name}: done in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=os.path.join("runs", "main_job"), help="output folder (replaced whole)")
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--phantom-resolution", type=float, default=3.0, help="phantom voxel size (mm)")
    p.add_argument("--device", default=None)
    a = p.parse_args(argv)
    from warpmpm.images import write_case
    from warpmpm.phantom import make_phantom

    from warpmpm.output_folder import written_by_warpmpm, write_record

    if os.path.lexists(a.out):  # replaced whole, but only when it is an earlier main job: never a folder of the user's
        if os.path.islink(a.out) or not os.path.isdir(a.out) or (os.listdir(a.out) and not written_by_warpmpm(a.out, "main-job")):
            raise SystemExit(f"error: --out {a.out} is not an earlier main job of this example (it holds other files, or is "
                             "a file or a link); name a new folder")
        shutil.rmtree(a.out)
    os.makedirs(os.path.join(a.out, "planning"))
    write_record(a.out, "main-job", arguments=vars(a))  # an interrupted main job is still recognised as one
    log = os.path.join(a.out, "log.txt")
    image, labels = (os.path.join(a.out, "planning", f) for f in ("image.nii.gz", "labels.nii.gz"))
    case = make_phantom(resolution=a.phantom_resolution)
    write_case(case, labels, image)
    print(f"planning: the phantom, {case.geometry.size[0]}x{case.geometry.size[1]}x{case.geometry.size[2]} voxels of "
          f"{case.geometry.spacing_mm[0]:.1f} mm", file=sys.stderr)
    plan = ["--image", image, "--labels", labels]
    dev = ["--device", a.device] if a.device else []
    stage("truth (finite elements: breathing + a duodenal push)",
          ["make-truth", *plan, "--load", "breathing,push", "--frames", str(a.frames), "--cell-mm", "10",
           "--out", os.path.join(a.out, "truth")], log)
    stage("cine (sagittal / coronal DICOM frames imaged from the truth)",
          ["make-cine", *plan, "--truth", os.path.join(a.out, "truth"), "--plane", "sagittal,coronal",
           "--out", os.path.join(a.out, "cine")], log)
    stage("track (the truth never read)",
          ["track", *plan, "--cine", os.path.join(a.out, "cine", "cine"), "--out", os.path.join(a.out, "track"),
           "--displacement", "--rrd", os.path.join(a.out, "track.rrd"), *dev], log)
    ev_json = os.path.join(a.out, "eval.json")
    stage("evaluation (every organ against the truth)",
          ["evaluate-track", "--track", os.path.join(a.out, "track"), "--truth", os.path.join(a.out, "truth"),
           "--json", ev_json], log)
    ev = json.load(open(ev_json))
    organs = list(ev["results"]["estimate"]["organs"])
    print(f"Tracked {a.frames} frames of a finite-element truth (breathing + a duodenal push) on the phantom from "
          "sagittal / coronal cine; mean error over the frames, mm (p95):\n")
    unseen = [o for o, s in ev["results"]["estimate"]["organs"].items() if not s.get("seen", True)]
    print("| method | " + " | ".join(o + (" (on no plane)" if o in unseen else "") for o in organs) + " |\n|---|" + "---|" * len(organs))
    for name, r in ev["results"].items():  # nearest / global: the baselines of an organ no plane measured
        print(f"| {name} | " + " | ".join(f"{r['organs'][o]['error_mm']:.2f} ({r['organs'][o]['p95_mm']:.2f})" if o in r["organs"]
                                          else "" for o in organs) + " |")
    print(f"\nlatency per frame: median {ev['latency_s']['median']:.2f} s, p95 {ev['latency_s']['p95']:.2f} s")
    print(f"wrote {a.out}/: planning/, truth/, cine/, track/ (labels/, displacement/, track.csv), track.rrd, eval.json, "
          f"eval.png, log.txt")
    return ev


if __name__ == "__main__":
    main()
