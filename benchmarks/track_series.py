"""The cine tracker on several synthetic MR cine series: accuracy and latency of tracker settings, same run.

Makes (once, kept under ``--work``) synthetic cine series of the MR sample with ``warpmpm make-cine``: sagittal
frames through the pancreas for each seed, and one interleaved sagittal/coronal series; then tracks each with
every configuration and scores it with ``warpmpm evaluate-track``. Prints one row per series and configuration:
the pancreas error of the estimate, ``propagate`` and ``initial`` (mm), the estimate's Dice, the median slice
registration time per frame, the median and p95 latency per frame after the first, and which solver finished the
frames. A configuration whose run fails (e.g. a degenerate registration) is reported with its error, not skipped.

    python benchmarks/track_series.py                         # seeds 0-3 sagittal + seed 0 interleaved, 20 frames
    python benchmarks/track_series.py --seeds 0 --no-interleaved --frames 8
    python benchmarks/track_series.py --case phantom --seeds 0 --no-interleaved --configs default,explicit

``--case phantom``: the built-in phantom at its default resolution and particle step 2 (the default phantom of
``warpmpm run``: 28k particles) instead of the MR sample (7k), so the tracker's frame can be set beside the
streamed-frame figures of issue 19; it needs no sample data.

Configurations: ``default`` (the tracker's defaults: each frame registered against the estimate rendered on its
plane), ``frames`` (``--reference previous-frame``: against the plane's last frame, the default before the eighth
session) and ``previous`` (``--solver explicit --registration itk --reference previous-frame``, the defaults before
the seventh session); ``explicit`` (``--solver explicit``: the paper's stopping rule on every frame instead of the
Newton iterations that confirm a predicted frame) and ``settled`` (``--wait-settled``: a frame the Newton iterations
do not settle goes on in the explicit settled mode). The MR case needs ``../shared/data/totalseg_mr`` (skipped with
a message if absent).
Raw numbers: ``benchmarks/results/track_series.json``.
"""

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys


from warpmpm.experiment import raw_numbers as raw

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
DATA = os.path.join(ROOT, "..", "shared", "data", "totalseg_mr")
CONFIGS = {"default": [], "frames": ["--reference", "previous-frame"],
           "previous": ["--solver", "explicit", "--registration", "itk", "--reference", "previous-frame"],
           "explicit": ["--solver", "explicit"], "settled": ["--wait-settled"]}


def warpmpm(*args: str, log: str) -> bool:
    with open(log, "a") as f:
        return subprocess.run([sys.executable, "-m", "warpmpm.cli", *args], stdout=f, stderr=subprocess.STDOUT, cwd=ROOT).returncode == 0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--case", default="mr", choices=["mr", "phantom"], help="the MR sample, or the built-in phantom (particle step 2)")
    p.add_argument("--seeds", default="0,1,2,3", help="sagittal series' seeds")
    p.add_argument("--no-interleaved", action="store_true", help="leave out the interleaved sagittal/coronal series (seed 0)")
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--configs", default="default,frames,previous", help=f"which of {', '.join(CONFIGS)}")
    p.add_argument("--work", default=os.path.join(ROOT, "runs", "track_series"), help="series and tracks go here (kept)")
    a = p.parse_args(argv)
    unknown = [c for c in a.configs.split(",") if c not in CONFIGS]
    if unknown:
        p.error(f"unknown configuration(s) {', '.join(unknown)}; use {', '.join(CONFIGS)}")
    if a.case == "mr" and not os.path.exists(os.path.join(DATA, "image.nii.gz")):
        print(f"skipped: the MR sample is not at {DATA}")
        return 0
    if a.case == "mr":
        case_args = ["--image", os.path.join(DATA, "image.nii.gz"), "--labels", os.path.join(DATA, "labels.nii.gz"),
                     "--preset", "totalseg_mr"]
        make_args, track_args = case_args, case_args
    else:  # the phantom's planning files are written beside each series by make-cine
        make_args, track_args = ["--phantom-resolution", "1", "--particle-step", "2"], None
    series = [(f"sagittal_s{s}", ["--seed", s]) for s in a.seeds.split(",")]
    if not a.no_interleaved:
        series.append(("interleaved_s0", ["--seed", "0", "--plane", "sagittal,coronal"]))
    os.makedirs(a.work, exist_ok=True)
    print("| series | configuration | estimate mm | propagate mm | initial mm | Dice | registration ms | reference ms | latency s (p95) | solver | settled frames |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for name, opts in series:
        cine = os.path.join(a.work, f"{name}_f{a.frames}" if a.case == "mr" else f"phantom_{name}_f{a.frames}")
        log = cine + ".log"
        if not os.path.exists(os.path.join(cine, "truth", "positions.npz")):
            if not warpmpm("make-cine", *make_args, "--frames", str(a.frames), *opts, "--out", cine, log=log):
                print(f"| {name} | (make-cine failed: {log}) |")
                continue
        for cfg in a.configs.split(","):
            out = f"{cine}_{cfg}"
            case_args = track_args or ["--image", os.path.join(cine, "planning", "image.nii.gz"), "--labels",
                                       os.path.join(cine, "planning", "labels.nii.gz"), "--particle-step", "2"]
            ok = warpmpm("track", *case_args, "--cine", os.path.join(cine, "cine"), "--out", out, "--overwrite", *CONFIGS[cfg],
                         log=out + ".log")  # re-measured each run: the earlier track is replaced whole
            ok = ok and warpmpm("evaluate-track", "--track", out, "--truth", os.path.join(cine, "truth"), "--json", out + ".json",
                                log=out + ".log")
            if not ok:
                with open(out + ".log") as f:
                    err = [ln.strip() for ln in f if ln.startswith("error")][:1] or ["see " + out + ".log"]
                print(f"| {name} | {cfg} | failed: {err[0][:160]} |")
                rows.append({"series": name, "config": cfg, "failed": err[0]})
                continue
            with open(out + ".json") as f:
                res = json.load(f)["results"]
            with open(os.path.join(out, "track.csv")) as f:
                track = list(csv.DictReader(f))
            later = track[1:] or track
            lat = sorted(float(r["latency_s"]) for r in later)
            row = {"series": name, "config": cfg, "estimate_mm": res["estimate"]["error_mm"], "propagate_mm": res["propagate"]["error_mm"],
                   "initial_mm": res["initial"]["error_mm"], "dice": res["estimate"]["dice"],
                   "registration_ms": statistics.median(float(r["registration_ms"]) for r in later),
                   "reference_ms": statistics.median(float(r["reference_ms"]) for r in later),
                   "latency_s": statistics.median(lat), "p95_s": lat[int(round(0.95 * (len(lat) - 1)))],
                   "solvers": sorted({r["solver"] for r in track}), "converged": sum(r["converged"] == "True" for r in track),
                   "settled": sum(r.get("settled") == "True" for r in track),
                   "frames": len(track), "latencies_s": lat}
            rows.append(row)
            print(f"| {name} | {cfg} | {row['estimate_mm']:.3f} | {row['propagate_mm']:.3f} | {row['initial_mm']:.3f} | {row['dice']:.3f} | "
                  f"{row['registration_ms']:.0f} | {row['reference_ms']:.0f} | {row['latency_s']:.3f} ({row['p95_s']:.3f}) | {'/'.join(row['solvers'])} | "
                  f"{row['settled']} of {row['frames']} |")
    raw.save(__file__, rows, run=a.case)
    return 0


if __name__ == "__main__":
    sys.exit(main())
