"""Pseudo ground-truth protocols.

``paper``: the paper's 8 deformation types, ``A = R G S`` applied to every axial slice about the
image centre; every particle is driven to its transformed position and the converged simulation is
the ground truth (GT).

``contact``: aperiodic, contact-driven motion that differs along the body axis: one neighbour
(stomach or duodenum) is displaced toward the pancreas and swells; optionally the left kidney
shifts superior-inferiorly by an amount that varies along the body axis. Only those neighbours
are driven; the pancreas moves through contact. The GT is the converged simulation.

No inverse crime: by default the GT is simulated with seeded, perturbed material parameters
(+-30 % per organ) and its own solver settings, recorded in :attr:`GroundTruth.params`; the
estimator uses the nominal table.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from .driving import ConvergenceConfig, DriveConfig, SliceDrivenEstimator
from .errors import InputError
from .model import Material, ParticleModel
from .imaging import particle_label_map
from .slices import InPlaneAffine, in_plane_axes
from .solvers import SolverConfig

__all__ = ["PAPER_DEFORMATIONS", "paper_affine", "perturb_materials", "GroundTruth", "GT_CFL", "gt_solver_config",
           "simulate_gt", "paper_ground_truth", "contact_targets", "contact_ground_truth"]

#: The paper's deformation table: type -> (r, g, s).
PAPER_DEFORMATIONS = {
    1: (-2.0, -2.0, 0.8), 2: (-2.0, -2.0, 1.2), 3: (-2.0, 2.0, 0.8), 4: (-2.0, 2.0, 1.2),
    5: (2.0, -2.0, 0.8), 6: (2.0, -2.0, 1.2), 7: (2.0, 2.0, 0.8), 8: (2.0, 2.0, 1.2),
}


def paper_affine(deformation: int, literal: bool = False) -> np.ndarray:
    """2x2 matrix ``A = R G S`` of a paper deformation type (1..8).

    r and g are read as degrees (default), or literally as the paper writes them (angle ``r / 2 pi``
    radians) with ``literal=True``.
    """
    if deformation not in PAPER_DEFORMATIONS:
        raise InputError(f"deformation must be 1..8, got {deformation!r}")
    r, g, s = PAPER_DEFORMATIONS[deformation]
    ra, ga = (r / (2 * math.pi), g / (2 * math.pi)) if literal else (math.radians(r), math.radians(g))
    R = np.array([[math.cos(ra), -math.sin(ra)], [math.sin(ra), math.cos(ra)]])
    G = np.array([[1.0, math.tan(ga)], [math.tan(ga), 1.0]])
    S = np.diag([s, s])
    return R @ G @ S


def perturb_materials(materials: dict[str, Material], seed: int, fraction: float = 0.3) -> dict[str, Material]:
    """Each organ's lambda and mu scaled by one seeded factor in [1 - fraction, 1 + fraction]."""
    rng = np.random.default_rng(seed)
    out = {}
    for organ in sorted(materials):
        f = rng.uniform(1 - fraction, 1 + fraction)
        m = materials[organ]
        out[organ] = Material(m.lam_pa * f, m.mu_pa * f, m.density_kg_m3)
    return out


@dataclass
class GroundTruth:
    """GT positions of every particle of ``model`` (same order), with what produced them."""

    model: ParticleModel
    positions_mm: np.ndarray
    protocol: str
    params: dict = field(default_factory=dict)
    steps: int = 0
    wall_s: float = 0.0
    converged: bool = True
    cache: dict = field(default_factory=dict, repr=False, compare=False)
    """Derived data computed once per GT by its users (e.g. the GT-warped image volume)."""

    def organ_positions(self, organ: str) -> np.ndarray:
        return self.positions_mm[self.model.organ_slice(organ)]

    def label_map(self, label_values: dict[str, int]) -> np.ndarray:
        """Deformed label map at the GT state on the planning grid, (z, y, x), with ``label_values``."""
        return particle_label_map(self.model, self.positions_mm, label_values)


#: Courant number of the ground-truth simulations. Driving EVERY particle at the estimator's CFL 0.5
#: diverged (phantom seed 8, resolution 3, deformation 8: NaN at step 1730) and left about half the
#: resolution-3 GTs at the 4000-step cap 3 mm off their targets; at 0.3 (the estimator's CFL before
#: the speed tuning) that GT converges in 1328 steps, 0.96 mm RMS from its targets.
GT_CFL = 0.3


def gt_solver_config(base: SolverConfig | None = None, device: str | None = None) -> SolverConfig:
    """The ground truth's solver settings: the estimator's (every field kept) on a finer discretisation.

    Changed from ``base`` (the estimator's settings), and only these: half the particles per cell
    (at least 1) and, for an explicit ``cell_size_mm``, a cell ``0.5^(1/3)`` as wide (the same
    refinement); a Courant number of at most :data:`GT_CFL`; ``dt_s`` cleared, since a time step fixed
    for the estimator's grid is above the finer grid's limit (the GT derives its own stable step);
    ``device`` defaults to ``device``; and the cell may be finer than the particles' largest gap when
    every particle is driven (the paper protocol; :func:`simulate_gt` turns it back on otherwise); and the
    explicit method whatever the estimator's (``SolverConfig.method``): the truth does not change with the way the
    estimate is solved.
    """
    b = base or SolverConfig(device=device)
    g = b.grid
    grid = replace(g, particles_per_cell=max(1.0, g.particles_per_cell * 0.5),
                   cell_size_mm=None if g.cell_size_mm is None else g.cell_size_mm * 0.5 ** (1.0 / 3.0), cell_at_least_gap=False)
    return replace(b, grid=grid, explicit=replace(b.explicit, cfl=min(b.explicit.cfl, GT_CFL), dt_s=None),
                   device=b.device or device, method="explicit")


def simulate_gt(model: ParticleModel, driven: np.ndarray, targets_mm: np.ndarray, *, perturb: bool, seed: int,
                solver_config: SolverConfig | None, device: str | None, max_steps: int = 4000, callback=None,
                wait_settled: bool = False):
    """Simulate a GT: ``targets_mm`` of the ``driven`` particles, perturbed materials; returns ``(params, result)``.

    ``wait_settled``: run on until the whole body has settled (the settled mode: adaptive damping, PD drive; up
    to ``max_steps``), an elastic equilibrium instead of the paper rule's snapshot taken when the driven
    particles have arrived (the contact truth's body still moves ~5 mm per 100 steps then).

    ``callback(estimator, step, rel_residual, rms_mm)`` is called every step (progress)."""
    params: dict = {"perturbed": bool(perturb), "material_seed": int(seed)}
    mats = dict(model.materials)
    if perturb:
        mats = perturb_materials(mats, seed)
        params["materials"] = {o: {"lam_pa": m.lam_pa, "mu_pa": m.mu_pa} for o, m in mats.items()}
    gt_model = replace(model, materials=mats, meta=dict(model.meta))
    cfg = gt_solver_config(solver_config, device)
    if len(driven) < model.n:  # undriven particles must stay coupled through the grid (thick slices)
        # the cell at least the gap: the rule every protocol's truth was made with. Its finer grid holds 1.16 (phantom)
        # to 1.26 (3 mm samples) layers a cell, outside the one-layer-a-cell mode (docs/decisions/2026-12-03-solver-defaults.md; on a thick-slice
        # block 1.16 layers already give the FEM's answer within 2.8 %, one layer 9.7 %)
        cfg = replace(cfg, grid=replace(cfg.grid, cell_at_least_gap=True, min_layers_per_cell=1.0))
        if cfg.grid.cell_size_mm is not None and cfg.grid.cell_size_mm < model.max_gap_mm:
            cfg = replace(cfg, grid=replace(cfg.grid, cell_size_mm=model.max_gap_mm))  # the refinement stops at the particles' own gap
    # the truth is held to the paper's stricter stopping rule (TH_D = 4), not the estimator's default
    est = SliceDrivenEstimator(gt_model, driven=driven, solver_config=cfg, drive_config=DriveConfig(),
                               convergence=replace(ConvergenceConfig.paper(), max_steps=max_steps, wait_settled=wait_settled),
                               extra_points_mm=targets_mm,
                               callback=callback)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = est.estimate(targets_mm)
    for w in caught:  # say whose simulation it was
        warnings.warn(f"ground truth: {str(w.message).removeprefix('estimate ')}", w.category, stacklevel=2)
    params["solver"] = est.mpm.summary()
    params["gt_steps"] = res.steps
    params["gt_converged"] = res.converged
    params["gt_rms_residual_mm"] = res.final_rms_mm
    params["gt_settled"] = res.settled
    params["gt_body_motion_mm"] = res.body_motion_mm
    params["gt_reason"] = res.reason
    params["gt_acceleration"] = res.acceleration  # whether the settled mode's coarse level ran (warpmpm.solvers.rigid_modes)
    return params, res


def paper_ground_truth(model: ParticleModel, deformation: int, *, literal: bool = False, perturb: bool = True, seed: int = 0,
                       centre_mm: np.ndarray | None = None, solver_config: SolverConfig | None = None,
                       device: str | None = None, simulate: bool = True, callback=None) -> GroundTruth:
    """The paper protocol on ``model``: every particle driven to its axial-slice affine target.

    ``simulate=False`` returns the targets themselves (the purely geometric GT, for debugging).
    """
    A = paper_affine(deformation, literal)
    centre = model.geometry.center_mm() if centre_mm is None else np.asarray(centre_mm, dtype=np.float64)
    e_u, e_v = in_plane_axes(model, "axial")
    targets = InPlaneAffine(A).apply(model.positions_mm, e_u, e_v, centre)
    r, g, s = PAPER_DEFORMATIONS[deformation]
    params = {"deformation": deformation, "r": r, "g": g, "s": s, "literal": literal, "A": A.tolist(), "centre_mm": centre.tolist()}
    if not simulate:
        return GroundTruth(model, targets, "paper", params)
    sim, res = simulate_gt(model, np.arange(model.n), targets, perturb=perturb, seed=seed + 1000 * deformation,
                           solver_config=solver_config, device=device, callback=callback)
    return GroundTruth(model, res.positions_mm, "paper", params | sim, res.steps, res.wall_s, res.converged)


def contact_targets(model: ParticleModel, seed: int, neighbour: str | None = None, push_mm: float | None = None,
                    swell: float | None = None, si_shift_mm: float | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Driven indices and targets of the contact protocol (see module docstring)."""
    rng = np.random.default_rng(seed)
    choices = [o for o in ("stomach", "duodenum") if o in model.organs]
    if not choices:
        raise InputError("the contact protocol needs the stomach or the duodenum in the model (organs 'ps', 'pd', ...)")
    if neighbour is None:
        neighbour = choices[int(rng.integers(len(choices)))]
    if neighbour not in model.organs:
        raise InputError(f"contact neighbour {neighbour!r} is not in the model ({model.letters})")
    push = float(rng.uniform(5.0, 15.0)) if push_mm is None else float(push_mm)
    swell = float(rng.uniform(1.05, 1.15)) if swell is None else float(swell)
    nmask = model.organ_slice(neighbour)
    pmask = model.organ_slice("pancreas")
    nc = model.positions_mm[nmask].mean(0)
    # Push toward the pancreas particles nearest the neighbour, not toward the far-away centroid.
    pan = model.positions_mm[pmask]
    near = pan[np.argsort(np.linalg.norm(pan - nc, axis=1))[: max(1, len(pan) // 5)]].mean(0)
    direction = (near - nc) / max(np.linalg.norm(near - nc), 1e-9)
    idx = [np.nonzero(nmask)[0]]
    tgt = [nc + swell * (model.positions_mm[nmask] - nc) + push * direction]
    params = {"neighbour": neighbour, "push_mm": push, "swell": swell, "direction": direction.tolist()}
    if "left_kidney" in model.organs:
        si = float(rng.uniform(4.0, 10.0)) if si_shift_mm is None else float(si_shift_mm)
        kmask = model.organ_slice("left_kidney")
        z = model.positions_mm[kmask, 2]
        ramp = (z - z.min()) / max(z.max() - z.min(), 1e-9)
        shift = si * (0.5 + ramp)  # breathing-like: more at the superior pole
        k_t = model.positions_mm[kmask].copy()
        k_t[:, 2] -= shift
        idx.append(np.nonzero(kmask)[0])
        tgt.append(k_t)
        params["kidney_si_shift_mm"] = si
    idx = np.concatenate(idx)
    order = np.argsort(idx)
    return idx[order], np.concatenate(tgt)[order], params


def contact_ground_truth(model: ParticleModel, *, seed: int = 0, perturb: bool = True, neighbour: str | None = None,
                         push_mm: float | None = None, solver_config: SolverConfig | None = None,
                         device: str | None = None, callback=None, wait_settled: bool = False,
                         max_steps: int = 4000) -> GroundTruth:
    """The contact protocol on ``model``; parameters and seed recorded in ``params``; ``wait_settled`` and
    ``max_steps`` as :func:`simulate_gt`."""
    idx, targets, params = contact_targets(model, seed, neighbour, push_mm)
    params["seed"] = seed
    sim, res = simulate_gt(model, idx, targets, perturb=perturb, seed=seed + 77, solver_config=solver_config, device=device,
                           callback=callback, wait_settled=wait_settled, max_steps=max_steps)
    return GroundTruth(model, res.positions_mm, "contact", params | sim, res.steps, res.wall_s, res.converged)
