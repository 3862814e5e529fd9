"""The MPM equilibrium against an independent finite-element solve (issue 17): one axial slice of a block
scaled 1.05, rotated 3 degrees or sheared 3 degrees in plane, everything else free.

    python benchmarks/fem_reference.py [--size 20,20,21] [--ppc-sweep | --grid-shift | --quasistatic | --fem-convergence
                                        | --acceleration]

Scenes: a soft (pancreas) block, a bonded pancreas + left kidney block and a pancreas + duodenum block
(~3000x stiffer), 2 mm particles. The FEM
(:mod:`warpmpm.fem`: trilinear hexahedra on the particles, selective reduced integration, the same Lame
parameters, the driven slice a Dirichlet condition) is the reference; the figure is the relative L2
difference of the non-driven particles' displacement, at the default stopping rule, once the whole
body has settled (``wait_settled``: the settled mode, adaptive damping and a PD drive; and each of its two
changes alone against the fixed damping and PID drive it replaced), and run on to a fixed 6,000 steps (does
the answer drift?). ``--grid-shift``: the soft block moved by 0, 1/4 and 1/2 cell against the grid. ``--quasistatic``: the settled mode's explicit solver beside the quasi-static one (:mod:`warpmpm.solvers.quasistatic`), same
run, with the time ratio. ``--fem-convergence``: how far the reference is from its own continuum limit: the FEM on
the particles' mesh against the FEM on meshes 2 and 3 times finer (``--levels``), the settled MPM against each, and
with three levels the observed order of convergence and every answer against the Richardson-extrapolated
continuum (a difference below the reference's own cannot be resolved by it). ``--acceleration``: the settled mode
with and without its rigid-mode acceleration (:mod:`warpmpm.solvers.rigid_modes`), on the three blocks and two more where a
stiff block (duodenum, kidney) hangs on the pancreas block, 3 layers above the driven slice, nothing driving it. ``--ppc-sweep``: the scaled soft block, settled (the default settled mode), for 1, 2, 4
and 8 particles per cell, with the error by distance from the slice (in-plane and through-plane parts).
"""

import argparse
import math
import time
import warnings

import numpy as np


from warpmpm.experiment import raw_numbers as raw
import warp as wp

from warpmpm.driving import ConvergenceConfig, DriveConfig, SliceDrivenEstimator
from warpmpm.fem import fem_displacement_mm
from warpmpm.scenes import block_model, inclusion_model, merge_models
from warpmpm.slices import DrivingSlice, InPlaneAffine
from warpmpm.solvers import AccelerationConfig, ExplicitConfig, GridConfig, SolverConfig
from warpmpm.targets import affine_targets

A = math.radians(3.0)
LOADS = {"scale 1.05": InPlaneAffine(np.eye(2) * 1.05),
         "rotation 3 deg": InPlaneAffine([[math.cos(A), -math.sin(A)], [math.sin(A), math.cos(A)]]),
         "shear 3 deg": InPlaneAffine([[1.0, math.tan(A)], [0.0, 1.0]])}
FIXED = SolverConfig(device="cpu", explicit=ExplicitConfig(damping_rule="fixed"))  # the damping before the fourth session: fixed, factor 4
ADAPTIVE = SolverConfig(device="cpu", explicit=ExplicitConfig(damping_rule="adaptive"))
SETTLED = ConvergenceConfig(wait_settled=True, max_steps=20000)
PID, PD = DriveConfig(ki_ratio=0.02), DriveConfig(ki_ratio=0.0)
#: (name, solver, stopping rule, drive): the defaults first, then what each change of the settled mode does alone
RULES = [("default stop", SolverConfig(device="cpu"), ConvergenceConfig(), None),
         ("settled, fixed damping 4, PID (before)", FIXED, SETTLED, PID),
         ("settled, adaptive damping, PID", ADAPTIVE, SETTLED, PID),
         ("settled (default: adaptive damping, PD)", SolverConfig(device="cpu"), SETTLED, None),
         ("6,000 steps, adaptive damping, PD", ADAPTIVE, ConvergenceConfig(th_v=1e-12, th_d=12, max_steps=6000), PD)]


#: the settled mode's two solvers side by side (``--quasistatic``): explicit dynamic relaxation and Newton / CG
SOLVERS = [("settled, explicit (adaptive damping, PD)", SolverConfig(device="cpu"), SETTLED, None),
           ("quasi-static (Newton / CG)", SolverConfig(device="cpu", method="quasistatic"), ConvergenceConfig(), None)]

#: the settled mode without and with its rigid-mode acceleration (``--acceleration``)
ACCELERATION = [("settled, no acceleration", SolverConfig(device="cpu", acceleration=AccelerationConfig(mode="off")), SETTLED, None),
                ("settled, rigid-mode acceleration (default)", SolverConfig(device="cpu"), SETTLED, None)]


def scenes(size):
    nx, ny, nz = size
    soft = block_model((nx, ny, nz), (2.0, 2.0, 2.0), "pancreas")
    half = block_model((nx // 2, ny, nz), (2.0, 2.0, 2.0), "pancreas")
    kidney = block_model((nx - nx // 2, ny, nz), (2.0, 2.0, 2.0), "left_kidney", origin_mm=(2.0 * (nx // 2), 0.0, 0.0))
    duodenum = block_model((nx - nx // 2, ny, nz), (2.0, 2.0, 2.0), "duodenum", origin_mm=(2.0 * (nx // 2), 0.0, 0.0))
    return {"pancreas block": soft, "pancreas + kidney (bonded)": merge_models(half, kidney),
            "pancreas + duodenum (~3000x)": merge_models(half, duodenum)}


def hanging_scenes(size):
    """A stiff block in one upper corner of the pancreas block (half its width, from 3 layers above the driven middle
    slice to the top): it hangs on the soft block, nothing drives it."""
    nx, ny, nz = size
    box = ((nx // 2, nx), (0, ny), ((nz - 1) // 2 + 3, nz))
    return {f"pancreas + hanging {o} ({r})": inclusion_model(size, box, inclusion=o) for o, r in (("duodenum", "~3000x"), ("left_kidney", "66x"))}


def compare(model, load, rule):
    k = int(model.voxel_ijk[:, 2].max()) // 2
    sl = [DrivingSlice("axial", k)]
    idx, tg = affine_targets(model, model.positions_mm, sl, [load], model.positions_mm.mean(0))
    u_fem = fem_displacement_mm(model, idx, tg)
    free = np.ones(model.n, bool)
    free[idx] = False
    _, cfg, conv, drive = rule
    est = SliceDrivenEstimator(model, sl, solver_config=cfg, extra_points_mm=tg, convergence=conv, drive_config=drive)
    t0 = time.perf_counter()
    r = est.estimate(tg)
    wall = time.perf_counter() - t0
    u = r.positions_mm - model.positions_mm
    rel = float(np.linalg.norm(u[free] - u_fem[free]) / np.linalg.norm(u_fem[free]))
    e = u - u_fem
    dist = np.abs(model.voxel_ijk[:, 2] - k)
    by_distance = {int(dd): {"in_plane_mm": float(np.linalg.norm(e[dist == dd][:, :2], axis=1).mean()),
                             "through_plane_mm": float(np.abs(e[dist == dd][:, 2]).mean()),
                             "fem_mm": float(np.linalg.norm(u_fem[dist == dd], axis=1).mean())} for dd in np.unique(dist)}
    return {"rel_l2": rel, "max_error_mm": float(np.abs(u[free] - u_fem[free]).max()),
            "mean_error_mm": float(np.linalg.norm(e[free], axis=1).mean()), "steps": r.steps, "wall_s": wall,
            "slice_rms_residual_mm": r.final_rms_mm,
            "slice_rms_motion_mm": float(np.sqrt(np.mean(np.sum((tg - model.positions_mm[idx]) ** 2, axis=1)))),
            "settled": r.settled, "dx_mm": est.mpm.dx_mm, "by_layer_distance": by_distance, "method": r.method,
            "linear_iterations": r.linear_iterations}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="20,20,21", help="block size in particles (x, y, z)")
    p.add_argument("--ppc-sweep", action="store_true", help="only the particles-per-cell sweep of the scaled soft block")
    p.add_argument("--grid-shift", action="store_true", help="only the soft block moved by 0, 1/4 and 1/2 cell against the grid")
    p.add_argument("--quasistatic", action="store_true", help="only the settled mode's explicit solver against the quasi-static one")
    p.add_argument("--acceleration", action="store_true", help="only the settled mode with and without its rigid-mode acceleration")
    p.add_argument("--affine", action="store_true",
                   help="--acceleration: add a column with the coarse space's affine cube motions (AccelerationConfig.basis)")
    p.add_argument("--fem-convergence", action="store_true",
                   help="the FEM on the particles' mesh against finer ones (--levels), and the settled MPM against each")
    p.add_argument("--levels", default="1,2", help="--fem-convergence: mesh refinements (1,2 or 1,2,3: with three, the "
                   "observed order and the extrapolated continuum; h/3 needs ~10 GB and ~8 minutes a solve)")
    p.add_argument("--scenes", default=None, help="--fem-convergence: comma-separated parts of scene names (default: all)")
    p.add_argument("--loads", default=None, help="--fem-convergence: comma-separated parts of load names (default: all)")
    a = p.parse_args(argv)
    wp.config.log_level = wp.LOG_ERROR
    warnings.simplefilter("ignore")
    size = tuple(int(v) for v in a.size.split(","))
    if a.ppc_sweep:
        return ppc_sweep(size)
    if a.grid_shift:
        return grid_shift(size)
    if a.fem_convergence:
        return fem_convergence(size, tuple(int(v) for v in a.levels.split(",")), a.scenes and a.scenes.split(","),
                               a.loads and a.loads.split(","))
    if a.affine and not a.acceleration:
        p.error("--affine adds a column to --acceleration's table; give both")
    rules = SOLVERS if a.quasistatic else ACCELERATION if a.acceleration else RULES
    if a.acceleration and a.affine:
        rules = rules + [("settled, affine cube motions", SolverConfig(device="cpu", acceleration=AccelerationConfig(basis="affine")), SETTLED, None)]
    ratio_name = "quasi-static / explicit" if a.quasistatic else "with / without" if a.acceleration else None
    rows = []
    print("| scene | load | " + " | ".join(r[0] for r in rules) + (f" | time, {ratio_name} |" if ratio_name else " |"))
    print("|---|---|" + "---|" * (len(rules) + int(ratio_name is not None)))
    all_scenes = {**scenes(size), **(hanging_scenes(size) if a.acceleration else {})}
    for sname, model in all_scenes.items():
        for lname, load in LOADS.items():
            res = [compare(model, load, rule) for rule in rules]
            rows.append({"scene": sname, "load": lname, "particles": model.n,
                         "results": {rule[0]: r for rule, r in zip(rules, res)}})
            cells = " | ".join(f"{100 * r['rel_l2']:.1f} % ({r['steps']} {'iterations' if r['method'] == 'quasistatic' else 'steps'}, "
                               f"{r['wall_s']:.1f} s)" for r in res)
            ratio = (" | " + " / ".join(f"{r['wall_s'] / res[0]['wall_s']:.2f}" for r in res[1:])) if ratio_name else ""
            print(f"| {sname} | {lname} | {cells}{ratio} |", flush=True)
    raw.save(__file__, run="quasistatic" if a.quasistatic else ("acceleration_affine" if a.affine else "acceleration") if a.acceleration
             else "default", data=rows)


def _extrapolate(u):
    """Richardson extrapolation of FEM answers on meshes of size h / r for r = 1, 2, 3 (``u[r]``): the observed order
    p from the ratio of successive differences, and the continuum estimate ``u3 + (u3 - u2) 3^-p / (2^-p - 3^-p)``."""
    from scipy.optimize import brentq

    e12, e23 = np.linalg.norm(u[1] - u[2]), np.linalg.norm(u[2] - u[3])
    ratio = e12 / max(e23, 1e-300)
    try:
        p = brentq(lambda q: (1 - 2.0**-q) / (2.0**-q - 3.0**-q) - ratio, 0.05, 8.0)
    except ValueError:  # not in the asymptotic range: no extrapolation
        return float("nan"), None
    return float(p), u[3] + (u[3] - u[2]) * 3.0**-p / (2.0**-p - 3.0**-p)


def fem_convergence(size, levels=(1, 2), scene_names=None, load_names=None):
    """Each scene and load: the FEM on the particles' mesh (h) and on meshes ``levels`` times finer (h/2, h/3), the
    settled MPM against each, and with three levels the observed order of convergence and every answer against the
    Richardson-extrapolated continuum. The slice is pinned (all three components), as in the other tables: these
    blocks are mirror-symmetric about it, so an in-plane drive has the same answer, and leaves the through-plane
    translation and tilts free (a singular FEM system)."""
    rows = []
    cols = [f"FEM h/{a} against h/{b}" for a, b in zip(levels, levels[1:])] + [f"MPM against FEM h/{r}" for r in levels]
    if len(levels) == 3:
        cols += ["order p", "FEM h against continuum", "FEM h/3 against continuum", "MPM against continuum"]
    print("| scene | load | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    settled = SolverConfig(device="cpu")
    for sname, model in scenes(size).items():
        if scene_names and not any(n in sname for n in scene_names):
            continue
        for lname, load in LOADS.items():
            if load_names and not any(n in lname for n in load_names):
                continue
            k = int(model.voxel_ijk[:, 2].max()) // 2
            sl = [DrivingSlice("axial", k)]
            idx, tg = affine_targets(model, model.positions_mm, sl, [load], model.positions_mm.mean(0))
            free = np.ones(model.n, bool)
            free[idx] = False
            u, walls = {}, {}
            for r in levels:
                t0 = time.perf_counter()
                u[r] = fem_displacement_mm(model, idx, tg, refine=r)[free]
                walls[r] = time.perf_counter() - t0
            est = SliceDrivenEstimator(model, sl, solver_config=settled, extra_points_mm=tg, convergence=SETTLED)
            u_mpm = (est.estimate(tg).positions_mm - model.positions_mm)[free]

            def rel(a, b):
                return float(np.linalg.norm(a - b) / np.linalg.norm(b))

            row = {"scene": sname, "load": lname, "fem_wall_s": walls,
                   "fem_steps": {f"h/{a} vs h/{b}": rel(u[a], u[b]) for a, b in zip(levels, levels[1:])},
                   "mpm_vs_fem": {f"h/{r}": rel(u_mpm, u[r]) for r in levels}}
            cells = [f"{100 * v:.1f} %" for v in row["fem_steps"].values()] + [f"{100 * v:.1f} %" for v in row["mpm_vs_fem"].values()]
            if len(levels) == 3:
                p, ustar = _extrapolate(u)
                row["order"] = p
                if ustar is not None:
                    row["against_continuum"] = {"fem_h": rel(u[1], ustar), "fem_h3": rel(u[3], ustar), "mpm": rel(u_mpm, ustar)}
                    cells += [f"{p:.2f}"] + [f"{100 * v:.1f} %" for v in row["against_continuum"].values()]
                else:
                    cells += ["not asymptotic", "", "", ""]
            rows.append(row)
            print(f"| {sname} | {lname} | " + " | ".join(cells) + " |", flush=True)
    raw.save(__file__, rows, run="fem_convergence" + ("_3levels" if len(levels) == 3 else ""))


def ppc_sweep(size):
    model = scenes(size)["pancreas block"]
    rows = []
    print("| particles per cell | cell mm | settled at step | rel. L2 | mean error mm | 2 mm from the slice: in-plane / "
          "through-plane mm | far half: through-plane mm | FEM there mm |")
    print("|---|---|---|---|---|---|---|---|")
    for ppc in (1.0, 2.0, 4.0, 8.0):
        rule = ("settled", SolverConfig(device="cpu", grid=GridConfig(particles_per_cell=ppc)), SETTLED, None)
        r = compare(model, LOADS["scale 1.05"], rule)
        near, far = r["by_layer_distance"][1], r["by_layer_distance"][max(r["by_layer_distance"])]
        rows.append({"particles_per_cell": ppc, **r})
        print(f"| {ppc:g} | {r['dx_mm']:.2f} | {r['steps']} | {100 * r['rel_l2']:.1f} % | {r['mean_error_mm']:.3f} | "
              f"{near['in_plane_mm']:.3f} / {near['through_plane_mm']:.3f} | {far['through_plane_mm']:.3f} | {far['fem_mm']:.3f} |",
              flush=True)
    raw.save(__file__, rows, run="ppc")


def grid_shift(size):
    """The soft block moved against the grid by a fraction of the default cell, settled mode: does the answer
    depend on where the grid lies?"""
    rows = []
    print("| shift (cells) | " + " | ".join(LOADS) + " |")
    print("|---|" + "---|" * len(LOADS))
    for frac in (0.0, 0.25, 0.5):
        dx = (4.0 * 8.0) ** (1.0 / 3.0)  # the default cell: (4 particles per cell x 8 mm^3 each)^(1/3)
        model = block_model(size, (2.0, 2.0, 2.0), "pancreas", origin_mm=(frac * dx,) * 3)
        res = {name: compare(model, load, ("settled", SolverConfig(device="cpu"), SETTLED, None)) for name, load in LOADS.items()}
        rows.append({"shift_cells": frac, **res})
        print(f"| {frac:g} | " + " | ".join(f"{100 * r['rel_l2']:.1f} % ({r['steps']} steps)" for r in res.values()) + " |", flush=True)
    raw.save(__file__, rows, run="grid_shift")


if __name__ == "__main__":
    main()
