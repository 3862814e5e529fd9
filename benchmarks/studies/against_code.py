"""Study (2026-12-02; answer in benchmarks/studies/README.md). Frame times against an earlier commit of this repository, alternated in one session (issue 19's same-run peer).

    python benchmarks/studies/against_code.py [--rev 86f31b4] [--steps 2,1] [--pairs 4] [--stream 0] [--raw default]

Issue 19 set its frame targets against the code of the day it was filed (commit ``86f31b4``): a first frame of the
default phantom 5.0 -> 2.5 s (0.5x), a paper-resolution frame 17.8 -> 8 s (0.45x), a streamed frame 1.23 -> 0.4 s
(0.33x). This machine's speed drifts by 30-50 % between runs and runs the same code about 2x slower than the machine
those figures came from, so absolute times say little; this script measures the ratio. It checks ``--rev`` out into a
temporary git worktree, then alternates the two codes ``--pairs`` times (the other code first on every second pair):

* per particle step of ``--steps`` (2: the default phantom, 28k particles; 1: the paper's one particle per voxel,
  113k): ``warpmpm run --targets affine --no-volume-registration`` (the paper protocol, deformation 1, the fitted
  slice affine as targets, as the issue's figures were), reading the estimate's wall time, steps and error from its
  ``--json``;
* with ``--stream N``: each code's own ``benchmarks/error_vs_time.py --stream N`` (N frames of deformation 1 ramped
  from rest, each frame started from the last), reading its median and p95 latency (this tree's
  ``benchmarks/results/error_vs_time.json``, which that script rewrites, is put back afterwards).

Each code is imported from its own tree (the editable install's import hook is set aside in the child process).
Prints a table (medians over the pairs, the ratio new / old per pair and its median) and keeps every run as run
``--raw`` of ``benchmarks/studies/results/against_code.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile

import numpy as np


from warpmpm.experiment import raw_numbers as raw

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

#: run in the child, with PYTHONPATH naming the tree given first: import the package (and a benchmark script) from that
#: tree, not from the editable install
CHILD = """
import runpy, sys
root, what = sys.argv[1], sys.argv[2]
sys.meta_path = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
import warpmpm
if not warpmpm.__file__.startswith(root):
    raise SystemExit(f"warpmpm imported from {warpmpm.__file__}, not from {root}")
if what == "run":
    from warpmpm.cli import main
    raise SystemExit(main(["run"] + sys.argv[3:]))
sys.argv = [what] + sys.argv[3:]
runpy.run_path(what, run_name="__main__")
"""


def child(root: str, what: str, args: list[str]) -> str:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.path.join(root, "benchmarks")]))
    r = subprocess.run([sys.executable, "-c", CHILD, root, what] + args, cwd=root, capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise RuntimeError(f"{what} in {root} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    return r.stdout


def frame(root: str, step: int, tmp: str) -> dict:
    out = os.path.join(tmp, "run.json")
    child(root, "run", ["--targets", "affine", "--no-volume-registration", "--quiet", "--particle-step", str(step), "--json", out])
    with open(out) as f:
        d = json.load(f)
    e = d["results"]["estimate"]
    return {"wall_s": e["wall_s"], "steps": e["steps"], "error_mm": e["error_mm"], "propagate_mm": d["results"]["propagate"]["error_mm"]}


def stream(root: str, frames: int) -> dict:
    text = child(root, os.path.join(root, "benchmarks", "error_vs_time.py"), ["--stream", str(frames)])
    m = re.search(r"latency median (\d+) ms, p95 (\d+) ms \(first frame (\d+) ms.*median steps (\d+); mean error ([\d.]+) mm", text)
    if m is None:
        raise RuntimeError(f"no latency line in {root}'s stream output:\n{text[-1000:]}")
    med, p95, first, steps, err = m.groups()
    return {"median_s": int(med) / 1e3, "p95_s": int(p95) / 1e3, "first_s": int(first) / 1e3, "steps": int(steps), "error_mm": float(err)}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rev", default="86f31b4", help="the earlier commit (default: the code issue 19 was filed against)")
    p.add_argument("--steps", default="2,1", help="particle steps of the frames, comma-separated (empty: none)")
    p.add_argument("--pairs", type=int, default=4)
    p.add_argument("--stream", type=int, default=0, help="frames of the streaming comparison (0: none)")
    p.add_argument("--raw", type=raw.check_name, default="default", help="the run's name in benchmarks/studies/results/against_code.json")
    a = p.parse_args(argv)
    try:
        steps = [int(s) for s in a.steps.split(",") if s.strip()]
    except ValueError:
        p.error(f"--steps must be comma-separated integers, got {a.steps!r}")
    if any(s < 1 for s in steps) or a.pairs < 1 or a.stream < 0:
        p.error("--steps must be >= 1, --pairs >= 1, --stream >= 0")
    rev = subprocess.run(["git", "rev-parse", "--verify", a.rev + "^{commit}"], cwd=ROOT, capture_output=True, text=True)
    if rev.returncode != 0:
        p.error(f"--rev {a.rev!r} is not a commit of this repository")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    tmp = tempfile.mkdtemp(prefix="against_code_")
    old_root = os.path.join(tmp, "old")
    stream_json = os.path.join(ROOT, "benchmarks", "results", "error_vs_time.json")
    kept = open(stream_json).read() if os.path.exists(stream_json) else None
    subprocess.run(["git", "worktree", "add", "--detach", "-q", old_root, a.rev], cwd=ROOT, check=True)
    runs = []
    try:
        codes = {"old": old_root, "new": ROOT}
        for step in steps:
            for k in range(a.pairs):
                for code in (("new", "old") if k % 2 == 0 else ("old", "new")):
                    r = frame(codes[code], step, tmp) | {"code": code, "what": f"frame, particle step {step}", "pair": k}
                    runs.append(r)
                    print(f"  {r['what']}, pair {k}, {code}: {r['wall_s']:.2f} s, {r['steps']} steps, {r['error_mm']:.3f} mm", flush=True)
        if a.stream:
            for k in range(a.pairs):
                for code in (("new", "old") if k % 2 == 0 else ("old", "new")):
                    r = stream(codes[code], a.stream) | {"code": code, "what": f"stream of {a.stream} frames", "pair": k}
                    runs.append(r)
                    print(f"  {r['what']}, pair {k}, {code}: median {r['median_s']:.3f} s a frame", flush=True)
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", old_root], cwd=ROOT)
        shutil.rmtree(tmp, ignore_errors=True)
        if kept is not None:
            with open(stream_json, "w") as f:
                f.write(kept)
    print(f"\n| what | {a.rev} s (median) | {head} s (median) | new / old per pair | median ratio | steps old / new | error old / new mm |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for what in dict.fromkeys(r["what"] for r in runs):
        key = "median_s" if what.startswith("stream") else "wall_s"
        old = {r["pair"]: r for r in runs if r["what"] == what and r["code"] == "old"}
        new = {r["pair"]: r for r in runs if r["what"] == what and r["code"] == "new"}
        ratios = [new[k][key] / old[k][key] for k in sorted(old)]
        med_old = float(np.median([r[key] for r in old.values()]))
        med_new = float(np.median([r[key] for r in new.values()]))
        o, n = old[0], new[0]
        rows.append({"what": what, "old_s": med_old, "new_s": med_new, "ratios": ratios, "median_ratio": float(np.median(ratios))})
        print(f"| {what} | {med_old:.2f} | {med_new:.2f} | {', '.join(f'{x:.2f}' for x in ratios)} | **{np.median(ratios):.2f}** | "
              f"{o['steps']} / {n['steps']} | {o['error_mm']:.2f} / {n['error_mm']:.2f} |")
    raw.save(__file__, run=a.raw, data={"rev": a.rev, "head": head, "runs": runs, "table": rows})


if __name__ == "__main__":
    main()
