"""The MPM equilibrium against an independent finite-element solve (issue 17): one axial slice of a block
scaled 1.05, rotated 3 degrees or sheared 3 degrees in plane, everything else free.

    python benchmarks/fem_reference.py [--size 10,10,10]

Scenes: a soft (pancreas) block and a bonded pancreas + left kidney block, 2 mm particles. The FEM
(:mod:`warpmpm.fem`: trilinear hexahedra on the particles, selective reduced integration, the same Lame
parameters, the driven slice a Dirichlet condition) is the reference; the figure is the relative L2
difference of the non-driven particles' displacement, at the default stopping rule and once the whole
body has settled (``wait_settled``), at the default damping and at damping 1.
"""

import argparse
import math
import os
import sys
import time
import warnings

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import raw  # noqa: E402  (benchmarks/raw.py: raw numbers beside the README tables)
import warp as wp  # noqa: E402

from warpmpm.driving import ConvergenceConfig, SliceDrivenEstimator  # noqa: E402
from warpmpm.fem import fem_displacement_mm  # noqa: E402
from warpmpm.scenes import block_model, merge_models  # noqa: E402
from warpmpm.slices import DrivingSlice, InPlaneAffine  # noqa: E402
from warpmpm.solver import SolverConfig  # noqa: E402
from warpmpm.targets import affine_targets  # noqa: E402

A = math.radians(3.0)
LOADS = {"scale 1.05": InPlaneAffine(np.eye(2) * 1.05),
         "rotation 3 deg": InPlaneAffine([[math.cos(A), -math.sin(A)], [math.sin(A), math.cos(A)]]),
         "shear 3 deg": InPlaneAffine([[1.0, math.tan(A)], [0.0, 1.0]])}
RULES = [("default stop, damping 4", SolverConfig(device="cpu"), ConvergenceConfig()),
         ("settled, damping 4", SolverConfig(device="cpu"), ConvergenceConfig(wait_settled=True, max_steps=20000)),
         ("settled, damping 1", SolverConfig(device="cpu", damping_factor=1.0), ConvergenceConfig(wait_settled=True, max_steps=20000))]


def scenes(size):
    nx, ny, nz = size
    soft = block_model((nx, ny, nz), (2.0, 2.0, 2.0), "pancreas")
    half = block_model((nx // 2, ny, nz), (2.0, 2.0, 2.0), "pancreas")
    kidney = block_model((nx - nx // 2, ny, nz), (2.0, 2.0, 2.0), "left_kidney", origin_mm=(2.0 * (nx // 2), 0.0, 0.0))
    return {"pancreas block": soft, "pancreas + kidney (bonded)": merge_models(half, kidney)}


def compare(model, load, rule):
    k = int(model.voxel_ijk[:, 2].max()) // 2
    sl = [DrivingSlice("axial", k)]
    idx, tg = affine_targets(model, model.positions_mm, sl, [load], model.positions_mm.mean(0))
    u_fem = fem_displacement_mm(model, idx, tg)
    free = np.ones(model.n, bool)
    free[idx] = False
    _, cfg, conv = rule
    est = SliceDrivenEstimator(model, sl, solver_config=cfg, extra_points_mm=tg, convergence=conv)
    t0 = time.perf_counter()
    r = est.estimate(tg)
    wall = time.perf_counter() - t0
    u = r.positions_mm - model.positions_mm
    rel = float(np.linalg.norm(u[free] - u_fem[free]) / np.linalg.norm(u_fem[free]))
    return {"rel_l2": rel, "max_error_mm": float(np.abs(u[free] - u_fem[free]).max()), "steps": r.steps, "wall_s": wall,
            "settled": r.settled}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="10,10,10", help="block size in particles (x, y, z)")
    a = p.parse_args(argv)
    wp.config.log_level = wp.LOG_ERROR
    warnings.simplefilter("ignore")
    size = tuple(int(v) for v in a.size.split(","))
    rows = []
    print("| scene | load | " + " | ".join(r[0] for r in RULES) + " |")
    print("|---|---|" + "---|" * len(RULES))
    for sname, model in scenes(size).items():
        for lname, load in LOADS.items():
            res = [compare(model, load, rule) for rule in RULES]
            rows.append({"scene": sname, "load": lname, "particles": model.n,
                         "results": {rule[0]: r for rule, r in zip(RULES, res)}})
            cells = " | ".join(f"{100 * r['rel_l2']:.0f} % ({r['steps']} steps)" for r in res)
            print(f"| {sname} | {lname} | {cells} |", flush=True)
    raw.save("fem_reference", rows)


if __name__ == "__main__":
    main()
