"""The estimate as the completion of what the planes see: a linear elastic equilibrium of the whole abdomen
(organs, surrounding tissue, the held spine) that takes the planes' observed motion as boundary data and
decides what no plane shows.

The model (built once from the labelled planning scan, :class:`CompletionModel`):

- **Material points** fill the body outline (:func:`warpmpm.anatomy.body_mask`) inside the planning crop on a lattice
  of ``point_mm``; each takes the tissue of its voxel (:func:`warpmpm.anatomy.tissue_map`: the organs, liver, bone
  where the preset labels vertebrae, else surrounding soft tissue) and that tissue's modulus
  (:func:`warpmpm.anatomy.nominal_material`: the middle of the published range; ``materials="paper"`` gives the
  four organs the seed paper's table instead).
- **The grid** is the MPM's: quadratic B-splines on cells of ``cell_mm`` along the world axes; the points are its
  quadrature. The unknowns are the node displacements ``u`` (mm); a point moves by ``sum_a w_a u_a``.
- **Anchors**: every bone point (vertebrae, where the preset labels them) is tied to no motion by a stiff spring;
  optionally (``hold_posterior_wall``) also the back where it lies on the couch. Nodes at the fringe of the body,
  where the points' weights fade out, are tied to their neighbours (not to a place).

A frame (:meth:`CompletionModel.solve`) minimises ::

    E(u) = 1/2 u^T K u + sum_p k_p / 2 |P_p (S_p u - d_p)|^2

with ``K`` the small-strain stiffness of the points, and a spring for every particle of an organ a plane sees: the
particles *on* a plane pulled (``on_plane_stiffness``) toward their observed displacement ``d_p`` along the
directions their planes measure (projector ``P_p``), the organ's particles *off* the planes pulled
(``off_plane_stiffness``) toward the organ's observed motion copied off the plane (the copy's displacement), along the
directions its planes measure; springs, never pins: the elasticity decides between them. Organs on no plane, the tissue, the through-plane direction of a single
plane and the parts of an organ a plane does not show are the equilibrium's. The springs' weights are relative to
the surrounding tissue's stiffness of a particle's volume over a cell (``mu_soft V_p / dx^2``).

The linear system ``(K + sum k S^T P S) u = sum k S^T P d`` is assembled once per plane set (Warp kernels,
:mod:`warpmpm.solvers.completion_kernels`) and solved by conjugate gradients preconditioned with smoothed-
aggregation algebraic multigrid (``pyamg``; near-null space: the rigid motions of the nodes), warm-started from the
previous frame. ``converged`` is the solve's relative residual reaching ``rtol``: the whole model is then an
equilibrium (the system is linear; there is nothing else to settle).

Returned positions: with ``observed_first`` (the default) every particle of a seen organ keeps its observed motion
along the directions its planes measure (the particles on a plane their own, the others the copy of their organ's)
and, with ``through_plane="copy"`` (the default), the copy's along the rest (a single plane: no through-plane motion
of a seen organ beyond the copy's); with ``through_plane="equilibrium"`` the equilibrium's there. Every other particle
(the organs on no plane, the tissue) takes the equilibrium's. Without it, every particle
takes the equilibrium's motion (how far the elasticity moves a seen organ from its observation is then part of the
score).

Not modelled yet, and what it costs (measured on the finite-element truths, ``benchmarks/studies/completion_study.py``,
``docs/decisions/2026-12-03-completion-solve.md``): sliding between organs and between organs and wall (the tissue is
bonded: a held back drags the organs beside it, hence ``hold_posterior_wall=False``), and the loads that move the body
(breathing enters through the diaphragm; here motion enters only through the observed organs and decays away from
them, so an organ far from the seen ones moves too little: CT sample left kidney 4.84 mm against 4.33 for the nearest
seen organ's motion, while the MR sample's is 2.34 against 4.83). Through-plane motion of a single plane comes out
worse than the copy's "no through-plane motion" (MR sample, sagittal only: pancreas 0.62 mm against 0.37).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..anatomy import TISSUE_CODE
from ..errors import SimulationError
from ..images import ORGANS
from ..model import ParticleModel
from .completion_model import CompletionConfig, CompletionModel, observed_projector

__all__ = ["CompletionConfig", "CompletionModel", "CompletionResult", "ReducedCompletion", "complete", "seen_parts",
           "slice_tissue_motion"]


@dataclass
class CompletionResult:
    """One frame's completion: particle positions (mm, world LPS), whether the solve converged, its iterations,
    relative residual and wall time (s), and the springs' mismatch on the seen particles (RMS mm along the observed
    directions, of the equilibrium before ``observed_first``)."""

    positions_mm: np.ndarray
    converged: bool
    iterations: int
    residual: float
    wall_s: float
    on_plane_rms_mm: float = float("nan")
    off_plane_rms_mm: float = float("nan")
    info: dict = field(default_factory=dict)


def slice_tissue_motion(geometry, slices, affines, axes_of, centre_mm: np.ndarray, half_width_mm: float):
    """A ``tissue_motion`` for :func:`complete`: the points within ``half_width_mm`` of a slice (``slices``, indices on
    ``geometry``) move by that slice's in-plane motion (``affines[k].apply``; ``axes_of(orientation)`` gives the
    in-plane axes), observed along the slice's two in-plane directions."""
    from ..slices import orientation_image_axis

    def motion(pts: np.ndarray):
        ijk = geometry.world_to_index(pts)
        sel, d, P = [], [], []
        for s, aff in zip(slices, affines):
            ax = orientation_image_axis(geometry, s.orientation)
            on = np.nonzero(np.abs(ijk[:, ax] - s.index) * geometry.spacing_mm[ax] <= half_width_mm)[0]
            e_u, e_v = axes_of(s.orientation)
            sel.append(on)
            d.append(aff.apply(pts[on], e_u, e_v, centre_mm) - pts[on])
            P.append(np.broadcast_to(np.outer(e_u, e_u) + np.outer(e_v, e_v), (len(on), 3, 3)))
        return np.concatenate(sel), np.concatenate(d), np.concatenate(P)

    return motion


#: Fewest particles of an organ on the planes for its off-plane particles to be tied to its observed motion.
MIN_SEEN = 10


def seen_parts(model: ParticleModel, idx: np.ndarray, axes: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per organ the planes see (at least :data:`MIN_SEEN` of its particles in ``idx``): the positions in ``idx`` of its
    particles on a plane, the indices of its other particles, and the projector of every direction its planes measure."""
    organ_of = model.organ_index[idx]
    on_plane = np.zeros(model.n, bool)
    on_plane[idx] = True
    out = []
    for k in range(len(model.organs)):
        sel = np.nonzero(organ_of == k)[0]
        if len(sel) >= MIN_SEEN:
            out.append((sel, np.nonzero((model.organ_index == k) & ~on_plane)[0], observed_projector(axes[sel])))
    return out


def _off_plane(parts: list) -> tuple[np.ndarray, np.ndarray]:
    """The seen organs' off-plane particle indices and their projectors, in the order of :func:`seen_parts`."""
    if not parts:
        return np.zeros(0, np.int64), np.zeros((0, 3, 3))
    return (np.concatenate([rest for _, rest, _ in parts]),
            np.concatenate([np.broadcast_to(P, (len(rest), 3, 3)) for _, rest, P in parts]))


def _project(P: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("nij,nj->ni", P, v)


def _keep_observed(disp: np.ndarray, idx: np.ndarray, axes: np.ndarray, d_on: np.ndarray, off: np.ndarray, offP: np.ndarray,
                   d_off: np.ndarray, d_copy_on: np.ndarray | None = None) -> None:
    """``observed_first``: along the observed directions the seen particles take their observation (in place); with
    ``d_copy_on`` (``through_plane="copy"``) they take the copy's motion along every other direction too (the
    particles on a plane ``d_copy_on``, the seen organs' others ``d_off``)."""
    if d_copy_on is not None:
        disp[idx] = d_copy_on + _project(axes, d_on - d_copy_on)
        disp[off] = d_off
        return
    disp[idx] += _project(axes, d_on - disp[idx])
    disp[off] += _project(offP, d_off - disp[off])


def complete(cm: CompletionModel, idx: np.ndarray, targets_mm: np.ndarray, axes: np.ndarray | None,
             copy_mm: np.ndarray, tissue_motion=None) -> CompletionResult:
    """One frame: the model's particles completed from the observed displacements of the particles ``idx`` on the
    planes (``targets_mm``, along the projectors ``axes``; None: all three directions) and the planes' motion copied
    off them (``copy_mm``: every particle's position under the copy; only the seen organs' are used)."""
    t0 = time.perf_counter()
    model = cm.model
    x = model.positions_mm
    idx = np.asarray(idx, np.int64)
    axes = np.tile(np.eye(3), (len(idx), 1, 1)) if axes is None else np.asarray(axes, np.float64)
    d_on = targets_mm - x[idx]
    parts = seen_parts(model, idx, axes)
    off, offP = _off_plane(parts)
    t_idx, t_d, t_P = None, None, None
    if tissue_motion is not None and cm.config.tissue_stiffness > 0:
        organ_codes = [TISSUE_CODE[o] for o in ORGANS if o in TISSUE_CODE]
        around = np.nonzero(~np.isin(cm.point_tissue, organ_codes))[0]
        sel, t_d, t_P = tissue_motion(cm.points_mm[around])
        t_idx = around[sel]
    cm.observe(idx, axes, off, offP, t_idx, t_P)
    d_off = copy_mm[off] - x[off]
    pull = d_off
    if parts and cm.config.off_plane_motion == "translation":  # each organ's observed translation
        pull = np.concatenate([np.broadcast_to(np.linalg.pinv(axes[sel].sum(0), rcond=1e-6) @ _project(axes[sel], d_on[sel]).sum(0),
                                               (len(rest), 3)) for sel, rest, _ in parts])
    u, info = cm.solve(d_on, pull, t_d)
    disp = cm.particle_displacements(u)
    r_on = _project(axes, disp[idx] - d_on)
    r_off = _project(offP, disp[off] - pull)
    if cm.config.observed_first:
        _keep_observed(disp, idx, axes, d_on, off, offP, d_off,
                       copy_mm[idx] - x[idx] if cm.config.through_plane == "copy" else None)
    rms = lambda r: float(np.sqrt(np.mean(np.sum(r * r, 1)))) if len(r) else float("nan")  # noqa: E731
    return CompletionResult(x + disp, info["converged"], info["iterations"], info["residual"], time.perf_counter() - t0,
                            rms(r_on), rms(r_off), {"setup_s": cm._plan["setup_s"], "unknowns": 3 * len(cm.active_nodes)})


class ReducedCompletion:
    """The completion of one plane set as a precomputed linear response, for frame after frame.

    The equilibrium is linear in the observation. Each seen organ's observed displacements (its on-plane particles'
    and the copy on its off-plane ones, along their projectors) are fitted, frame by frame, by an affine motion of the
    organ (12 parameters, weighted by the springs' stiffness; ``reduced_modes="translation"``: its translation, 3);
    the equilibrium's response to each of those motions is solved once here (to ``response_rtol``) (:meth:`CompletionModel.solve`, one CG solve each), so a frame is a small least-squares
    fit and a matrix product. ``observed_first`` still returns the exact observation along the observed directions;
    the affine fit only shapes what the planes do not show (a local push seen on a plane reaches the unseen parts only
    through its organ's affine part)."""

    def __init__(self, cm: CompletionModel, idx: np.ndarray, axes: np.ndarray | None):
        t0 = time.perf_counter()
        model = cm.model
        x = model.positions_mm
        self.cm, self.idx = cm, np.asarray(idx, np.int64)
        self.axes = np.tile(np.eye(3), (len(self.idx), 1, 1)) if axes is None else np.asarray(axes, np.float64)
        self.groups = seen_parts(model, self.idx, self.axes)
        self.off, self.offP = _off_plane(self.groups)
        cm.observe(self.idx, self.axes, self.off, self.offP)
        k_all = np.zeros(len(self.idx) + len(self.off))
        k_all[cm._plan["use"]] = cm._plan["k"]
        k_on, k_off = k_all[: len(self.idx)], k_all[len(self.idx):]
        self.fits, responses = [], []
        start = 0
        for sel, rest, P in self.groups:
            pts = np.concatenate([x[self.idx[sel]], x[rest]])
            c0 = pts.mean(0)
            L = max(float(np.ptp(pts, 0).max()) / 2, 1.0)
            phi = self._phi((pts - c0) / L)  # (n, 3, 12)
            if cm.config.reduced_modes == "translation":
                phi = np.ascontiguousarray(phi[:, :, :3])
            Pg = np.concatenate([self.axes[sel], np.broadcast_to(P, (len(rest), 3, 3))])
            kg = np.concatenate([k_on[sel], k_off[start:start + len(rest)]])
            PPhi = np.einsum("nij,njm->nim", Pg, phi)
            G = np.einsum("n,nim,nil->ml", kg, PPhi, PPhi)
            self.fits.append((sel, slice(start, start + len(rest)), c0, L, phi, PPhi, kg, np.linalg.pinv(G, rcond=1e-9)))
            for m in range(phi.shape[-1]):  # the response to this organ moving by mode m alone
                d_on = np.zeros((len(self.idx), 3))
                d_off = np.zeros((len(self.off), 3))
                d_on[sel] = phi[: len(sel), :, m]
                d_off[start:start + len(rest)] = phi[len(sel):, :, m]
                cm._u = None
                u, info = cm.solve(d_on, d_off, rtol=cm.config.response_rtol)
                if not info["converged"]:
                    raise SimulationError(f"ReducedCompletion: the response to mode {m} did not converge (residual {info['residual']:.1e})")
                responses.append(cm.particle_displacements(u))
            start += len(rest)
        self.R = np.stack(responses, -1) if responses else np.zeros((model.n, 3, 0))  # (N, 3, 12 x organs)
        self.setup_s = time.perf_counter() - t0

    @staticmethod
    def _phi(xs: np.ndarray) -> np.ndarray:
        phi = np.zeros((len(xs), 3, 12))
        for a in range(3):
            phi[:, a, a] = 1.0
            phi[:, a, 3 + 3 * a:6 + 3 * a] = xs
        return phi

    def complete(self, targets_mm: np.ndarray, copy_mm: np.ndarray) -> CompletionResult:
        """One frame of the plane set: the particles' positions (mm) from the on-plane targets and the copy."""
        t0 = time.perf_counter()
        x = self.cm.model.positions_mm
        d_on = targets_mm - x[self.idx]
        d_off = copy_mm[self.off] - x[self.off]
        coef = []
        for sel, off_sl, c0, L, phi, PPhi, kg, Ginv in self.fits:
            d = np.concatenate([d_on[sel], d_off[off_sl]])
            coef.append(Ginv @ np.einsum("n,nim,ni->m", kg, PPhi, d))
        disp = self.R @ np.concatenate(coef) if coef else np.zeros_like(x)
        if self.cm.config.observed_first:
            _keep_observed(disp, self.idx, self.axes, d_on, self.off, self.offP, d_off,
                           copy_mm[self.idx] - x[self.idx] if self.cm.config.through_plane == "copy" else None)
        return CompletionResult(x + disp, True, 0, float("nan"), time.perf_counter() - t0,
                                info={"setup_s": self.setup_s, "responses": int(self.R.shape[-1])})
