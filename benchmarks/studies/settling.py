"""Study (2026-12-02; answer in benchmarks/studies/README.md). How fast a whole abdomen settles in the settled mode, with and without the rigid-mode acceleration (issue 17).

    python benchmarks/studies/settling.py [--scenes res3,default] [--max-steps 8000] [--variants off,organs,40,25,affine] [--raw settling]

The load of the diagnosis in docs/decisions/2026-12-03-solver-defaults.md ("Rigid-mode acceleration"): the phantom's
mid-pancreas axial slice scaled 2 % in plane about the volume's centre (small and linear), all four organs, the
settled mode (``ConvergenceConfig(wait_settled=True)``: adaptive damping, PD drive) with at most ``--max-steps``.
Variants: ``off`` (no acceleration), ``organs`` (the coarse space of each organ's rigid motions), a number (the
edge in mm of the cubes each organ is cut into, with their 6 rigid motions), or ``affine`` / ``affineNN`` (25 or NN
mm cubes with their 12 affine motions: ``AccelerationConfig.basis``); the package's default is 25 mm cubes with
the basis :data:`warpmpm.solvers.RIGID_MODE_BASIS`. Reported per variant: steps, whether the
package's own settled rule said settled, wall time (and its ratio to ``off`` in the same run), the time a step (and
its ratio), the 99th-percentile motion of the last 500 steps (``-`` for a run of fewer than 1,000 steps), and how far the answer lies from the default variant's
(mean and 99th percentile, mm): where ``off`` has not settled, that is how far it still had to go.
"""

import argparse
import sys
import time
import warnings

import numpy as np


from warpmpm.experiment import raw_numbers as raw
import warp as wp

from warpmpm import InPlaneAffine, build_model, make_phantom
from warpmpm.driving import ConvergenceConfig, SliceDrivenEstimator
from warpmpm.errors import InputError
from warpmpm.slices import DrivingSlice
from warpmpm.solvers import AccelerationConfig, RIGID_MODE_AGGREGATE_MM, RIGID_MODE_BASIS, SolverConfig
from warpmpm.targets import affine_targets

SCENES = {"res3": ("phantom resolution 3 mm", dict(resolution=3.0), 1),
          "default": ("default phantom (particle step 2)", {}, 2)}


def variant_config(name: str) -> SolverConfig:
    if name.startswith("affine"):  # affineNN: NN mm cubes with the 12 affine motions each
        return SolverConfig(acceleration=AccelerationConfig(aggregate_mm=float(name[6:] or RIGID_MODE_AGGREGATE_MM), basis="affine"))
    if name == "off":
        return SolverConfig(acceleration=AccelerationConfig(mode="off"))
    if name == "organs":
        return SolverConfig(acceleration=AccelerationConfig(aggregate_mm=None, basis="rigid"))
    return SolverConfig(acceleration=AccelerationConfig(aggregate_mm=float(name), basis="rigid"))


def run(scene: str, variant: str, max_steps: int) -> dict:
    _, kw, step = SCENES[scene]
    case = make_phantom(**kw)
    m = build_model(case, "psdl", sampling_step=step)
    k = int(np.median(m.voxel_ijk[m.organ_slice("pancreas"), 2]))
    sl = [DrivingSlice("axial", k)]
    _, tg = affine_targets(m, m.positions_mm, sl, [InPlaneAffine(1.02 * np.eye(2))], case.geometry.center_mm())
    snaps = {}

    def keep(est, s, rel, rms):
        if s % 500 == 0:
            snaps[s] = est.positions_mm().copy()

    est = SliceDrivenEstimator(m, sl, solver_config=variant_config(variant), callback=keep,
                               convergence=ConvergenceConfig(wait_settled=True, max_steps=max_steps),
                               extra_points_mm=np.vstack([m.positions_mm - 5, m.positions_mm + 5]))
    t0 = time.perf_counter()
    r = est.estimate(tg)
    wall = time.perf_counter() - t0
    last = sorted(snaps)
    motion = (float(np.percentile(np.linalg.norm(snaps[last[-1]] - snaps[last[-2]], axis=1), 99))
              if len(last) > 1 else float("nan"))
    acc = est.accelerator
    return {"scene": scene, "variant": variant, "particles": m.n, "dx_mm": est.mpm.dx_mm, "steps": r.steps,
            "settled": bool(r.settled), "wall_s": wall, "step_ms": 1e3 * wall / max(r.steps, 1),
            "last_500_p99_mm": motion, "groups": None if acc is None else acc.n_groups,
            "largest_boost": None if acc is None else float(acc.boosts.max()), "positions_mm": r.positions_mm}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default="res3,default", help=f"comma-separated of {sorted(SCENES)}")
    p.add_argument("--max-steps", type=int, default=8000)
    p.add_argument("--variants", default=f"off,organs,40,{RIGID_MODE_AGGREGATE_MM:g},affine")
    p.add_argument("--raw", type=raw.check_name, default="default", help="the run's name in benchmarks/studies/results/settling.json")
    a = p.parse_args(argv)
    scenes = a.scenes.split(",")
    bad = [s for s in scenes if s not in SCENES]
    if bad:
        p.error(f"unknown scene(s) {bad}: choose from {sorted(SCENES)}")
    variants = a.variants.split(",")
    for v in variants:  # each variant's configuration, built once here to check it (SolverConfig refuses a cube <= 0)
        try:
            variant_config(v)
        except (ValueError, InputError):
            p.error(f"variant {v!r}: 'off', 'organs', a cube edge in mm > 0, or 'affine' / 'affineNN' (NN mm cubes, affine motions)")
    if a.max_steps < 500:
        p.error("--max-steps must be at least 500")
    wp.config.log_level = wp.LOG_ERROR
    warnings.simplefilter("ignore")
    ref = "affine" if RIGID_MODE_BASIS == "affine" else f"{RIGID_MODE_AGGREGATE_MM:g}"
    rows = []
    print("| scene | variant | groups | steps | settled | wall s (/ off) | ms a step (/ off) | p99 motion, last 500 steps, mm "
          "| from the default variant, mean / p99 mm |")
    print("|---|---|---|---|---|---|---|---|---|")
    for scene in scenes:
        res = {v: run(scene, v, a.max_steps) for v in variants}
        base = res.get("off")
        for v, r in res.items():
            d = np.linalg.norm(r["positions_mm"] - res[ref]["positions_mm"], axis=1) if ref in res else None
            r["from_default_mean_mm"] = None if d is None else float(d.mean())
            r["from_default_p99_mm"] = None if d is None else float(np.percentile(d, 99))
            wr = f" ({r['wall_s'] / base['wall_s']:.2f})" if base else ""
            sr = f" ({r['step_ms'] / base['step_ms']:.2f})" if base else ""
            mo = "-" if not np.isfinite(r['last_500_p99_mm']) else f"{r['last_500_p99_mm']:.3f}"
            dd = "" if d is None else f"{r['from_default_mean_mm']:.3f} / {r['from_default_p99_mm']:.3f}"
            print(f"| {SCENES[scene][0]} ({r['particles']}, cell {r['dx_mm']:.1f} mm) | {v} | {r['groups'] or '-'} | {r['steps']} | "
                  f"{'yes' if r['settled'] else 'no'} | {r['wall_s']:.1f}{wr} | {r['step_ms']:.1f}{sr} | {mo} | {dd} |",
                  flush=True)
            rows.append({k: v2 for k, v2 in r.items() if k != "positions_mm"})
    raw.save(__file__, rows, run=a.raw)
    return 0


if __name__ == "__main__":
    sys.exit(main())
