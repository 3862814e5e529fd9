"""Accuracy against wall time per frame, over the speed knobs, and a streaming benchmark.

For one case (the phantom by default, or ``--labels/--image/--preset``), organs ``psdl``, the paper's
deformations (``--deformations``), the mid-pancreas axial slice: a sweep over particle sampling step,
particles per cell (grid cell size) and convergence threshold TH_D. Prints a table of mean error
(mm) and median wall time per frame, with the ``initial`` and ``propagate`` baselines and the
paper's point (5.11 mm, 2587 s per estimate on a CPU), and writes a PNG plot.

``--stream N`` instead follows N frames of slowly changing motion (deformation 1 ramped in N steps)
from captured targets to 3D estimate, each frame from the last, and reports per-frame latency
(median, p95) and error.

    python benchmarks/error_vs_time.py --out benchmarks/results/error_vs_time.png
    python benchmarks/error_vs_time.py --stream 20 [--solver explicit,quasistatic]
"""

from __future__ import annotations

import argparse
import os
import re
import time
import numpy as np


from warpmpm.experiment import raw_numbers as raw

import warp as wp

from warpmpm.driving import ConvergenceConfig, SliceDrivenEstimator
from warpmpm.slices import InPlaneAffine, in_plane_axes
from warpmpm.targets import affine_targets
from warpmpm.groundtruth import paper_affine, paper_ground_truth
from warpmpm.metrics import evaluate
from warpmpm.experiment import CaseConfig, prepare_case
from warpmpm.solvers import GridConfig, SolverConfig


# The settings before issue 9's tuning (CFL 0.3, damping factor 1, the paper's TH_D 4): kept as a
# row of every sweep, the peer the new defaults are compared with in the same run.
LEGACY = {"cfl": 0.3, "damping_factor": 1.0}


def frame(prep, gt, organs, step, ppc, th_d, device, legacy=False):
    model = prep.full_model.subset(organs)
    keep = np.isin(gt.model.organ_index, [gt.model.organs.index(o) for o in model.organs])
    gt_pos = gt.positions_mm[keep]
    sl = prep.resolve_slices(model, None)
    A = paper_affine(gt.params["deformation"])
    idx, tg = affine_targets(model, model.positions_mm, sl, [InPlaneAffine(A)], prep.centre_mm)
    extra = LEGACY if legacy else {}
    est = SliceDrivenEstimator(model, sl, solver_config=SolverConfig(device=device, **extra, grid=GridConfig(particles_per_cell=ppc)),
                               convergence=ConvergenceConfig(th_d=th_d), extra_points_mm=np.vstack([tg, gt_pos]))
    res = est.estimate(tg)
    pan = model.organ_slice("pancreas")
    return res, evaluate(res.positions_mm[pan], gt_pos[pan], prep.case.geometry, sampling_step=step), est


def sweep_knobs(a, device):
    rows = []
    for step in [int(s) for s in a.steps.split(",")]:
        base = CaseConfig(estimator="slice-driven", labels=a.labels, image=a.image, preset=a.preset, phantom_resolution=a.phantom_resolution,
                          particle_step=step, device=device)
        prep = prepare_case(base)
        gts = {d: paper_ground_truth(prep.full_model, d, centre_mm=prep.centre_mm, device=device)
               for d in [int(x) for x in a.deformations.split(",")]}
        knobs = [(float(ppc), int(th_d), False) for ppc in a.ppc.split(",") for th_d in a.th_d.split(",")]
        if not a.no_legacy:
            knobs.append((4.0, 4, True))
        for ppc, th_d, legacy in knobs:
            errs, walls, steps, init = [], [], [], []
            for d, gt in gts.items():
                res, m, _ = frame(prep, gt, ("pancreas", "stomach", "duodenum", "left_kidney"), step, ppc, th_d, device, legacy)
                errs.append(m["error_mm"])
                walls.append(res.wall_s)
                steps.append(res.steps)
                pan = gt.model.organ_slice("pancreas")
                init.append(np.linalg.norm(gt.positions_mm[pan] - gt.model.positions_mm[pan], axis=1).mean())
            rows.append({"step": step, "ppc": ppc, "th_d": th_d, "legacy": legacy, "n": prep.full_model.n, "error": np.mean(errs),
                         "wall": np.median(walls), "steps": np.median(steps), "initial": np.mean(init)})
            r = rows[-1]
            print(f"  step {step} ppc {ppc} TH_D {th_d}{' (before tuning)' if legacy else ''}: {r['n']} particles, error {r['error']:.2f} mm, "
                  f"{r['wall']:.2f} s/frame, {r['steps']:.0f} steps", flush=True)
    return rows


def pareto(rows):
    front = []
    for r in rows:
        if not any(o["error"] <= r["error"] and o["wall"] <= r["wall"] and (o["error"] < r["error"] or o["wall"] < r["wall"]) for o in rows):
            front.append(r)
    return front


def stream(a, device):
    """``--stream N``: one row per solver of ``--solver`` (same run), latency and error per frame; raw numbers: run ``stream`` of ``results/error_vs_time.json``."""
    rows = {}
    threads = [None] if a.threads is None else [int(t) for t in a.threads.split(",")]
    for method in a.solver.split(","):
        for th in threads:
            name = method if th is None else f"{method}, {th} thread{'s' if th > 1 else ''}"
            print(f"solver {name}:")
            rows[name] = stream_one(a, device, method, th)
    raw.save(__file__, rows | {"solvers": list(rows)}, run="stream")
    base = rows[next(iter(rows))]
    print("\n| solver | median latency ms | p95 ms | first frame ms | median steps (Newton iterations) | mean error mm | latency / first solver's |")
    print("|---|---|---|---|---|---|---|")
    for method, r in rows.items():
        lat = np.array(r["latency_s"])
        print(f"| {method} | {np.median(lat) * 1e3:.0f} | {np.percentile(lat, 95) * 1e3:.0f} | {lat[0] * 1e3:.0f} | {np.median(r['steps']):.0f} | "
              f"{np.mean(r['error_mm']):.2f} | {np.median(lat) / np.median(base['latency_s']):.2f} |")


def stream_one(a, device, method, threads=None):
    prep = prepare_case(CaseConfig(estimator="slice-driven", labels=a.labels, image=a.image, preset=a.preset, phantom_resolution=a.phantom_resolution,
                                   particle_step=int(a.steps.split(",")[0]), device=device))
    model = prep.full_model
    sl = prep.resolve_slices(model, None)
    A_end = paper_affine(1)
    est = None
    lat, errs, steps = [], [], []
    idx = None
    for f in range(1, a.stream + 1):
        s = f / a.stream
        A = np.eye(2) + s * (A_end - np.eye(2))
        # the truth of this frame: every particle moved by the ramped affine (geometric GT)

        e_u, e_v = in_plane_axes(model, "axial")
        truth = InPlaneAffine(A).apply(model.positions_mm, e_u, e_v, prep.centre_mm)
        t0 = time.perf_counter()
        if est is None:
            idx, _ = affine_targets(model, model.positions_mm, sl, [InPlaneAffine(A)], prep.centre_mm)
            est = SliceDrivenEstimator(model, sl, solver_config=SolverConfig(device=device, method=method, cpu_threads=threads),
                                       extra_points_mm=truth)
        res = est.estimate(truth[idx])
        lat.append(time.perf_counter() - t0)
        steps.append(res.steps)
        pan = model.organ_slice("pancreas")
        errs.append(np.linalg.norm(res.positions_mm[pan] - truth[pan], axis=1).mean())
        print(f"  frame {f}: {lat[-1] * 1e3:.0f} ms, {res.steps} steps, error {errs[-1]:.2f} mm", flush=True)
    lat = np.array(lat)
    print(f"\nstreaming {a.stream} frames, {model.n} particles on {device}: latency median {np.median(lat) * 1e3:.0f} ms, "
          f"p95 {np.percentile(lat, 95) * 1e3:.0f} ms (first frame {lat[0] * 1e3:.0f} ms, from rest); "
          f"median steps {np.median(steps):.0f}; mean error {np.mean(errs):.2f} mm")
    return {"particles": model.n, "latency_s": lat.tolist(), "steps": steps, "error_mm": [float(e) for e in errs]}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--labels")
    p.add_argument("--image")
    p.add_argument("--preset", default="amos")
    p.add_argument("--phantom-resolution", type=float, default=1.0)
    p.add_argument("--deformations", default="1,2,3,4,5,6,7,8")
    p.add_argument("--steps", default="2,3", help="particle sampling steps")
    p.add_argument("--ppc", default="4,8", help="particles per cell")
    p.add_argument("--th-d", default="3,4", help="TH_D values")
    p.add_argument("--no-legacy", action="store_true", help="leave out the row with the settings before tuning")
    p.add_argument("--device", default=None)
    p.add_argument("--stream", type=int, default=0)
    p.add_argument("--solver", default="explicit", help="--stream: solvers to compare, comma-separated (explicit, quasistatic)")
    p.add_argument("--threads", default=None, help="--stream: CPU threads of a step to compare, comma-separated (e.g. 1,2; "
                   "default: the solver's default)")
    p.add_argument("--out", default="benchmarks/results/error_vs_time.png")
    a = p.parse_args(argv)
    wp.config.log_level = wp.LOG_ERROR  # no init banner or module-load lines
    wp.init()
    device = a.device or ("cuda" if wp.is_cuda_available() else "cpu")
    print(f"device {device} ({wp.get_device(device).name}), {os.cpu_count()} cores")
    if a.stream:
        stream(a, device)
        return
    rows = sweep_knobs(a, device)
    front = pareto(rows)
    print("\n| particle step | ppc | TH_D | damping, CFL | particles | mean error mm | s per frame | steps | Pareto |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        solver = "1x, 0.3 (before tuning)" if r["legacy"] else "4x, 0.5"
        print(f"| {r['step']} | {r['ppc']:g} | {r['th_d']} | {solver} | {r['n']} | {r['error']:.2f} | {r['wall']:.2f} | {r['steps']:.0f} | "
              f"{'yes' if r in front else ''} |")
    print(f"| initial (no estimation) | | | | | {np.mean([r['initial'] for r in rows]):.2f} | | | |")
    raw.save(__file__, run="default" if a.labels is None else "case_" + re.sub(r"[^A-Za-z0-9_.-]", "_", os.path.basename(os.path.dirname(os.path.abspath(a.labels)))),
             data=[dict(r, pareto=r in front) for r in rows])
    print("| paper, psdl best slice (AMOS, 96-core CPU) | | | | | 5.11 | 2587 | | |")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        ax.scatter([r["wall"] for r in rows], [r["error"] for r in rows], label=f"warpmpm ({device})")
        for r in rows:
            ax.annotate(f"s{r['step']} ppc{r['ppc']:g} D{r['th_d']}" + (" old" if r["legacy"] else ""), (r["wall"], r["error"]), fontsize=7)
        ax.scatter([2587], [5.11], marker="x", color="k", label="paper (CPU)")
        ax.axhline(np.mean([r["initial"] for r in rows]), ls="--", color="grey", label="initial")
        ax.set_xscale("log")
        ax.set_xlabel("wall time per frame (s)")
        ax.set_ylabel("mean pancreas error (mm)")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(a.out, dpi=120)
        print(f"wrote {a.out}")
    except ImportError:
        print("matplotlib not installed: no plot (pip install matplotlib)")


if __name__ == "__main__":
    main()
