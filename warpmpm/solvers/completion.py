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
and takes the equilibrium's along the rest; every other particle takes the equilibrium's. Without it, every particle
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
from typing import Literal

import numpy as np
import warp as wp

from ..anatomy import TISSUE_CODE, TISSUES, nominal_material, tissue_map
from ..elastic_amg import elasticity_preconditioner, rigid_body_modes
from ..errors import InputError, SimulationError
from ..images import ORGANS, Case
from ..model import PAPER_MATERIALS, ParticleModel
from . import completion_kernels as ck

__all__ = ["CompletionConfig", "CompletionModel", "CompletionResult", "ReducedCompletion", "complete", "seen_parts",
           "slice_tissue_motion"]

#: Nodes whose stiffness (diagonal) is below this fraction of the mean get a spring to no motion of that size.
FRINGE = 0.05


@dataclass(frozen=True)
class CompletionConfig:
    """How the completion model is built and solved."""

    cell_mm: float = 8.0
    """Edge of a grid cell (mm): the resolution of what the equilibrium decides (the organs' observed motion is kept
    at the particles' own resolution)."""
    point_mm: float | None = None
    """Spacing of the material points (mm); None: ``cell_mm / 2`` (8 points a cell)."""
    materials: Literal["tissue", "paper"] = "tissue"
    """``tissue``: every tissue at the middle of its published range (:data:`warpmpm.anatomy.TISSUE_RANGES`);
    ``paper``: the seed paper's four organ materials (:data:`warpmpm.model.PAPER_MATERIALS`), tissue as ``tissue``."""
    on_plane_stiffness: float = 100.0
    """Spring of a particle on a plane toward its observed displacement, in units of ``mu_soft V_p / dx^2``."""
    off_plane_stiffness: float = 100.0
    """Spring of a seen organ's particle off the planes toward its organ's observed motion copied off the plane,
    same units. 0: the off-plane parts follow the elasticity alone."""
    off_plane_motion: Literal["copy", "translation"] = "copy"
    """What a seen organ's off-plane springs pull toward: ``copy``, the planes' motion copied off the plane (the
    ``propagate`` / ``propagate_planes`` baseline's); ``translation``, the organ's observed translation (the
    ``rigid`` baseline's), which carries no in-plane strain for the incompressible tissue to turn into through-plane
    motion. Either way ``observed_first`` returns the copy along the observed directions."""
    tissue_stiffness: float = 0.0
    """Spring of a material point of the tissue around the organs lying on a plane toward the plane's observed motion
    there (the whole slice's in-plane motion), in units of ``mu_soft V / dx^2``; 0: only the organs are observed."""
    unseen_direction_stiffness: float = 1e-2
    """Spring of every node to no motion along the directions no plane measures (one sagittal plane: left-right), in
    units of the stiffness matrix's mean diagonal: without it a model that holds nothing still (no bone labelled)
    drifts freely along them (phantom, breathing + push, one sagittal plane, pancreas: 7.28 mm at 0, 0.49 at 1e-3,
    0.41 at 1e-2, the copy 0.37; MR sample, sagittal: 0.87 at 1e-3, 0.62 at 1e-2, the copy 0.37)."""
    anchor_stiffness: float = 1000.0
    """Spring holding an anchor point (back, bone) still, same units with the point's own volume."""
    hold_posterior_wall: bool = False
    """Also hold the most posterior body point of every column where the body ends on the couch. Off by default:
    without sliding between organs and wall, a held wall drags the organs beside it (phantom, sagittal + coronal:
    stomach 0.47 -> 4.52 mm, MR left kidney 2.34 -> 2.56 mm); bone is always held."""
    observed_first: bool = True
    """Return the observed motion for the seen organs' particles along their planes' directions (module docstring)."""
    rtol: float = 1e-6
    """Relative residual at which a frame's solve has converged."""
    max_iterations: int = 400
    """Conjugate-gradient iterations of one frame at most; a frame that stops short is not converged."""

    def __post_init__(self):
        if not (self.unseen_direction_stiffness >= 0 and np.isfinite(self.unseen_direction_stiffness)):
            raise InputError(f"CompletionConfig.unseen_direction_stiffness must be >= 0, got {self.unseen_direction_stiffness}")
        for name in ("cell_mm", "on_plane_stiffness", "anchor_stiffness", "rtol"):
            if not (getattr(self, name) > 0 and np.isfinite(getattr(self, name))):
                raise InputError(f"CompletionConfig.{name} must be > 0, got {getattr(self, name)}")
        if not (self.off_plane_stiffness >= 0 and np.isfinite(self.off_plane_stiffness)):
            raise InputError(f"CompletionConfig.off_plane_stiffness must be >= 0, got {self.off_plane_stiffness}")
        if self.point_mm is not None and not (self.point_mm > 0 and np.isfinite(self.point_mm)):
            raise InputError(f"CompletionConfig.point_mm must be > 0, got {self.point_mm}")
        if self.max_iterations < 1:
            raise InputError(f"CompletionConfig.max_iterations must be >= 1, got {self.max_iterations}")
        if self.off_plane_motion not in ("copy", "translation"):
            raise InputError(f"CompletionConfig.off_plane_motion must be 'copy' or 'translation', got {self.off_plane_motion!r}")
        if self.materials not in ("tissue", "paper"):
            raise InputError(f"CompletionConfig.materials must be 'tissue' or 'paper', got {self.materials!r}")


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


def _lattice(lo: np.ndarray, hi: np.ndarray, step: float) -> np.ndarray:
    axes = [np.arange(a + step / 2, b, step) for a, b in zip(lo, hi)]
    g = np.meshgrid(*axes, indexing="ij")
    return np.stack([a.ravel() for a in g], 1)


class CompletionModel:
    """The abdomen of one planning scan as material points on a B-spline grid, its stiffness assembled once."""

    def __init__(self, case: Case, preset: str | None, model: ParticleModel, config: CompletionConfig | None = None,
                 device: str | None = None):
        t0 = time.perf_counter()
        self.config = cfg = config or CompletionConfig()
        self.model = model
        self.device = device or "cpu"
        dx = cfg.cell_mm
        step = cfg.point_mm or dx / 2
        tissues = tissue_map(case, preset)
        g = case.geometry
        size = np.asarray(g.size)
        corners = np.array([[a, b, c] for a in (-0.5, size[0] - 0.5) for b in (-0.5, size[1] - 0.5) for c in (-0.5, size[2] - 0.5)])
        world = g.index_to_world(corners)
        lo, hi = world.min(0), world.max(0)
        pts = _lattice(lo, hi, step)
        ijk = np.rint(g.world_to_index(pts)).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < size), 1)
        pts, ijk = pts[inside], ijk[inside]
        code = tissues[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
        body = code != TISSUE_CODE["air"]
        pts, code = pts[body], code[body]
        if len(pts) == 0:
            raise InputError("the completion model found no body tissue in the planning crop (is the image's body outline empty?)")
        mu = np.zeros(len(TISSUES))
        lam = np.zeros(len(TISSUES))
        for t in TISSUES[1:]:
            mu[TISSUE_CODE[t]], lam[TISSUE_CODE[t]] = nominal_material(t)
        if cfg.materials == "paper":
            for o, m in PAPER_MATERIALS.items():
                mu[TISSUE_CODE[o]], lam[TISSUE_CODE[o]] = m.mu_pa, m.lam_pa
        self.mu_soft = float(mu[TISSUE_CODE["soft_tissue"]])
        # anchors: bone, and the most posterior body point of each (lateral, superior) column where the body ends there
        # (the voxel behind it is air inside the scan: the back on the couch; a crop that cuts through the back is free)
        anchor = code == TISSUE_CODE["bone"]
        if cfg.hold_posterior_wall:
            col = np.rint((pts[:, [0, 2]] - lo[[0, 2]]) / step).astype(np.int64)
            key = col[:, 0] * (int(col[:, 1].max()) + 1) + col[:, 1]
            order = np.lexsort((-pts[:, 1], key))
            first = np.ones(len(order), bool)
            first[1:] = key[order][1:] != key[order][:-1]
            back = order[first]
            behind = np.rint(g.world_to_index(pts[back] + np.array([0.0, step, 0.0]))).astype(np.int64)
            in_scan = np.all((behind >= 0) & (behind < size), 1)
            wall = np.zeros(len(back), bool)
            wall[in_scan] = tissues[behind[in_scan, 2], behind[in_scan, 1], behind[in_scan, 0]] == TISSUE_CODE["air"]
            anchor[back[wall]] = True
        self.n_points, self.n_anchors = len(pts), int(anchor.sum())
        self.anchor_points_mm = pts[anchor]
        self.point_tissue = code
        # the grid: two cells of padding so every stencil (and every particle's) lies inside
        allpts = np.vstack([pts, model.positions_mm])
        self.origin_mm = allpts.min(0) - 2.0 * dx
        shape = np.ceil((allpts.max(0) - self.origin_mm) / dx).astype(int) + 3
        self.shape = tuple(int(v) for v in shape)
        self.dx = dx
        n_nodes = int(np.prod(shape))
        xc = ((pts - self.origin_mm) / dx).astype(np.float32)
        # active nodes: every node a point or a particle touches
        base = np.floor(np.vstack([xc, (model.positions_mm - self.origin_mm) / dx]) - 0.5).astype(np.int64)
        touched = np.zeros(n_nodes, bool)
        off = np.array([[a, b, c] for a in range(3) for b in range(3) for c in range(3)])
        for o in off:
            n = base + o
            touched[(n[:, 0] * shape[1] + n[:, 1]) * shape[2] + n[:, 2]] = True
        self.active_nodes = np.nonzero(touched)[0]
        act = np.full(n_nodes, -1, np.int32)
        act[self.active_nodes] = np.arange(len(self.active_nodes), dtype=np.int32)
        self._act = act
        na = len(self.active_nodes)
        self._active_wp = wp.array(act, dtype=int, device=self.device)
        self._x_points = wp.array(xc, dtype=wp.vec3, device=self.device)
        self.stiffness_stencil = wp.zeros((na, 125, 9), dtype=wp.float64, device=self.device)
        vol = np.full(len(pts), step ** 3, np.float32)
        wp.launch(ck.assemble_stiffness, dim=len(pts), device=self.device,
                  inputs=[self._x_points, wp.array(vol, dtype=float, device=self.device),
                          wp.array(lam[code].astype(np.float32), dtype=float, device=self.device),
                          wp.array(mu[code].astype(np.float32), dtype=float, device=self.device), 1.0 / dx,
                          self.shape[1], self.shape[2], self._active_wp, self.stiffness_stencil])
        self.point_lam_pa, self.point_mu_pa, self.point_volume_mm3, self.points_mm = lam[code], mu[code], float(step ** 3), pts
        K = self._to_csr(self.stiffness_stencil)
        if anchor.any():
            k_anchor = (cfg.anchor_stiffness * self.mu_soft * step ** 3 / dx ** 2) * np.ones(int(anchor.sum()), np.float32)
            held = wp.zeros((na, 125, 9), dtype=wp.float64, device=self.device)
            self._add_springs(held, xc[anchor], k_anchor, np.tile(np.eye(3, dtype=np.float32), (int(anchor.sum()), 1, 1)))
            K = K + self._to_csr(held)
        # a node at the fringe of the body, where the points' B-spline weights fade out, has almost no stiffness (11 % of
        # the unknowns on the MR sample below 1 % of the mean diagonal): springs of FRINGE x the mean diagonal tie each
        # such node to its six neighbours (never to a place: a translation of the whole body stays free of energy), which
        # keeps the system well conditioned (CG-AMG 1000+ -> about 30 iterations there)
        self.K, self.n_fringe = self._tie_fringe(K, FRINGE)
        # and every node to no motion by 1e-9 of the mean diagonal: a model that holds nothing (no bone labelled) seen
        # along two directions only stays definite along the third (its translation there is then zero, not arbitrary)
        import scipy.sparse as sp

        self.K = (self.K + sp.identity(self.K.shape[0], format="csr") * (1e-9 * float(self.K.diagonal().mean()))).tocsr()
        self._x_particles = wp.array(((model.positions_mm - self.origin_mm) / dx).astype(np.float32), dtype=wp.vec3, device=self.device)
        self._plan = None
        self._u = None
        self.build_s = time.perf_counter() - t0

    def _tie_fringe(self, K, fraction: float):
        import scipy.sparse as sp

        diag = K.diagonal().reshape(-1, 3).min(1)
        weak = diag < fraction * float(K.diagonal().mean())
        w = fraction * float(K.diagonal().mean())
        ny, nz = self.shape[1], self.shape[2]
        nodes = self.active_nodes[weak]
        rows, cols = [], []
        for step in (ny * nz, nz, 1):
            for sgn in (1, -1):
                nb = nodes + sgn * step
                ok = (nb >= 0) & (nb < len(self._act))
                a, b = np.nonzero(weak)[0][ok], self._act[nb[ok]]
                ok2 = b >= 0
                rows.append(a[ok2])
                cols.append(b[ok2])
        a, b = np.concatenate(rows), np.concatenate(cols)
        n = len(self.active_nodes)
        E = sp.csr_matrix((np.r_[np.ones(len(a)), -np.ones(len(a))], (np.r_[np.arange(len(a)), np.arange(len(a))], np.r_[a, b])),
                          shape=(len(a), n))
        L = w * (E.T @ E)
        return (K + sp.kron(L, sp.identity(3), format="csr")).tocsr(), int(np.count_nonzero(weak))

    # -- assembly -------------------------------------------------------------------------------------------------
    def _add_springs(self, stencil, x_cells: np.ndarray, k: np.ndarray, P: np.ndarray) -> None:
        if len(k) == 0:
            return
        wp.launch(ck.assemble_springs, dim=len(k), device=self.device,
                  inputs=[wp.array(x_cells.astype(np.float32), dtype=wp.vec3, device=self.device),
                          wp.array(k.astype(np.float32), dtype=float, device=self.device),
                          wp.array(P.astype(np.float32), dtype=wp.mat33, device=self.device), self.shape[1], self.shape[2],
                          self._active_wp, stencil])

    def _to_csr(self, stencil):
        import scipy.sparse as sp

        S = stencil.numpy()
        na = S.shape[0]
        ny, nz = self.shape[1], self.shape[2]
        nodes = self.active_nodes
        i, j, k = nodes // (ny * nz), (nodes // nz) % ny, nodes % nz
        d = np.array([[a, b, c] for a in range(-2, 3) for b in range(-2, 3) for c in range(-2, 3)])
        ni, nj, nk = i[:, None] + d[None, :, 0], j[:, None] + d[None, :, 1], k[:, None] + d[None, :, 2]
        ok = (ni >= 0) & (nj >= 0) & (nk >= 0) & (ni < self.shape[0]) & (nj < ny) & (nk < nz)
        col = np.full(ni.shape, -1, np.int64)
        col[ok] = self._act[(ni[ok] * ny + nj[ok]) * nz + nk[ok]]
        a_idx, s_idx = np.nonzero(col >= 0)
        blocks = S[a_idx, s_idx]  # (m, 9)
        keep = np.any(blocks != 0.0, 1)
        a_idx, s_idx, blocks = a_idx[keep], s_idx[keep], blocks[keep]
        b_idx = col[a_idx, s_idx]
        r = (3 * a_idx[:, None] + np.repeat(np.arange(3), 3)[None]).ravel()
        c = (3 * b_idx[:, None] + np.tile(np.arange(3), 3)[None]).ravel()
        return sp.csr_matrix((blocks.ravel(), (r, c)), shape=(3 * na, 3 * na))

    def node_positions_mm(self) -> np.ndarray:
        ny, nz = self.shape[1], self.shape[2]
        n = self.active_nodes
        return self.origin_mm + self.dx * np.stack([n // (ny * nz), (n // nz) % ny, n % nz], 1)

    # -- a plane set ----------------------------------------------------------------------------------------------
    def observe(self, on_plane: np.ndarray, on_axes: np.ndarray, off_plane: np.ndarray, off_axes: np.ndarray,
                tissue: np.ndarray | None = None, tissue_axes: np.ndarray | None = None) -> None:
        """Set the springs of a plane set: ``on_plane`` particle indices with their projectors ``on_axes`` (n, 3, 3),
        ``off_plane`` (the seen organs' other particles) with theirs, ``tissue`` (indices of material points of the
        tissue around the organs lying on a plane) with theirs. Assembles the system and its preconditioner; a later
        call with the same sets keeps them."""
        import scipy.sparse as sp

        tissue = np.zeros(0, np.int64) if tissue is None else np.asarray(tissue, np.int64)
        tissue_axes = np.zeros((0, 3, 3)) if tissue_axes is None else np.asarray(tissue_axes)
        key = (on_plane.tobytes(), np.asarray(on_axes, np.float32).tobytes(), off_plane.tobytes(), np.asarray(off_axes, np.float32).tobytes(),
               tissue.tobytes())
        if self._plan is not None and self._plan["key"] == key:
            return
        t0 = time.perf_counter()
        cfg = self.config
        na = len(self.active_nodes)
        stencil = wp.zeros((na, 125, 9), dtype=wp.float64, device=self.device)
        xp = (self.model.positions_mm - self.origin_mm) / self.dx
        scale = self.mu_soft * self.model.volume_mm3 / self.dx ** 2
        k_on = (cfg.on_plane_stiffness * scale[on_plane]).astype(np.float32)
        k_off = (cfg.off_plane_stiffness * scale[off_plane]).astype(np.float32)
        k_t = np.full(len(tissue), cfg.tissue_stiffness * self.mu_soft * self.point_volume_mm3 / self.dx ** 2, np.float32)
        xs = np.concatenate([xp[on_plane], xp[off_plane], (self.points_mm[tissue] - self.origin_mm) / self.dx])
        idx = np.concatenate([on_plane, off_plane, -1 - tissue]).astype(np.int64)
        k = np.concatenate([k_on, k_off, k_t])
        P = np.concatenate([np.asarray(on_axes, np.float32).reshape(-1, 3, 3), np.asarray(off_axes, np.float32).reshape(-1, 3, 3),
                            np.asarray(tissue_axes, np.float32).reshape(-1, 3, 3)])
        use = k > 0
        idx, k, P, xs = idx[use], k[use], P[use], xs[use]
        self._add_springs(stencil, xs, k, P)
        A = self.K + self._to_csr(stencil)
        Q = np.eye(3) - observed_projector(np.concatenate([np.asarray(on_axes, np.float64).reshape(-1, 3, 3),
                                                           np.asarray(tissue_axes, np.float64).reshape(-1, 3, 3)]))
        if cfg.unseen_direction_stiffness > 0 and np.abs(Q).max() > 1e-6:
            A = A + sp.kron(sp.identity(na), cfg.unseen_direction_stiffness * float(self.K.diagonal().mean()) * Q, format="csr")
        A = A.tocsr()
        M, ml = elasticity_preconditioner(sp.bsr_matrix(A, blocksize=(3, 3)), rigid_body_modes(self.node_positions_mm()), max_coarse=1500)
        self._plan = {"key": key, "A": A, "M": M, "idx": idx, "k": k, "P": P,
                      "x": wp.array(xs.astype(np.float32), dtype=wp.vec3, device=self.device), "use": use,
                      "n_on": int(np.count_nonzero(use[: len(on_plane)])), "setup_s": time.perf_counter() - t0,
                      "levels": len(ml.levels), "nnz": int(A.nnz)}
        self._u = None
        self._plan["setup_s"] = time.perf_counter() - t0

    def solve(self, d_on_mm: np.ndarray, d_off_mm: np.ndarray, d_tissue_mm: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """Node displacements (n_active, 3) mm for the observed displacements of the ``on_plane``, ``off_plane`` and
        ``tissue`` springs of :meth:`observe`, and the solve's report (``converged``, ``iterations``, ``residual``)."""
        plan = self._plan
        if plan is None:
            raise SimulationError("CompletionModel.solve before observe(): no plane set")
        na = len(self.active_nodes)
        d = np.concatenate([np.asarray(d_on_mm, np.float32).reshape(-1, 3), np.asarray(d_off_mm, np.float32).reshape(-1, 3),
                            np.zeros((0, 3), np.float32) if d_tissue_mm is None else np.asarray(d_tissue_mm, np.float32).reshape(-1, 3)])
        if len(d) != len(plan["use"]):
            raise SimulationError(f"CompletionModel.solve: {len(d)} displacements for the {len(plan['use'])} springs of observe()")
        d = d[plan["use"]]  # springs of zero stiffness were dropped
        f = wp.zeros(na, dtype=wp.vec3d, device=self.device)
        wp.launch(ck.spring_load, dim=len(d), device=self.device,
                  inputs=[plan["x"], wp.array(plan["k"], dtype=float, device=self.device), wp.array(plan["P"], dtype=wp.mat33, device=self.device),
                          wp.array(d, dtype=wp.vec3, device=self.device), self.shape[1], self.shape[2], self._active_wp, f])
        b = f.numpy().reshape(-1)
        u, iters, res = self._cg(b, self._u)
        if not np.all(np.isfinite(u)):
            raise SimulationError("the completion solve produced non-finite displacements")
        self._u = u
        return u.reshape(-1, 3), {"converged": bool(res <= self.config.rtol * 1.01), "iterations": iters, "residual": res}

    def _cg(self, b: np.ndarray, x0: np.ndarray | None) -> tuple[np.ndarray, int, float]:
        from scipy.sparse.linalg import cg

        plan = self._plan
        count = [0]

        def cb(_):
            count[0] += 1

        norm = float(np.linalg.norm(b))
        if norm == 0.0:
            return np.zeros_like(b), 0, 0.0
        u, _ = cg(plan["A"], b, x0=x0, rtol=self.config.rtol, atol=0.0, maxiter=self.config.max_iterations, M=plan["M"], callback=cb)
        return u, count[0], float(np.linalg.norm(plan["A"] @ u - b)) / norm

    def particle_displacements(self, u_nodes: np.ndarray, x_cells: wp.array | None = None) -> np.ndarray:
        """``sum_a w_a u_a`` at the model's particles (or at ``x_cells``), mm."""
        x = self._x_particles if x_cells is None else x_cells
        out = wp.zeros(x.shape[0], dtype=wp.vec3, device=self.device)
        wp.launch(ck.interpolate, dim=x.shape[0], device=self.device,
                  inputs=[x, wp.array(np.asarray(u_nodes, np.float64), dtype=wp.vec3d, device=self.device), self.shape[1], self.shape[2],
                          self._active_wp, out])
        return out.numpy().astype(np.float64)

    def summary(self) -> dict:
        return {"cell_mm": self.dx, "points": self.n_points, "anchors": self.n_anchors, "active_nodes": int(len(self.active_nodes)),
                "unknowns": int(3 * len(self.active_nodes)), "build_s": self.build_s, "materials": self.config.materials}


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


def observed_projector(axes: np.ndarray) -> np.ndarray:
    """The projector onto every direction some of ``axes`` (n, 3, 3 projectors) measures: the span of their sum."""
    if len(axes) == 0:
        return np.zeros((3, 3))
    w, V = np.linalg.eigh(np.asarray(axes, np.float64).sum(0))
    keep = w > 1e-3 * max(w.max(), 1e-30)
    return (V[:, keep] @ V[:, keep].T)


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
                   d_off: np.ndarray) -> None:
    """``observed_first``: along the observed directions the seen particles take their observation (in place)."""
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
        _keep_observed(disp, idx, axes, d_on, off, offP, d_off)
    rms = lambda r: float(np.sqrt(np.mean(np.sum(r * r, 1)))) if len(r) else float("nan")  # noqa: E731
    return CompletionResult(x + disp, info["converged"], info["iterations"], info["residual"], time.perf_counter() - t0,
                            rms(r_on), rms(r_off), {"setup_s": cm._plan["setup_s"], "unknowns": 3 * len(cm.active_nodes)})


class ReducedCompletion:
    """The completion of one plane set as a precomputed linear response, for frame after frame.

    The equilibrium is linear in the observation. Each seen organ's observed displacements (its on-plane particles'
    and the copy on its off-plane ones, along their projectors) are fitted, frame by frame, by an affine motion of the
    organ (12 parameters, weighted by the springs' stiffness); the equilibrium's response to each of those 12 x organs
    motions is solved once here (:meth:`CompletionModel.solve`, one CG solve each), so a frame is a small least-squares
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
            Pg = np.concatenate([self.axes[sel], np.broadcast_to(P, (len(rest), 3, 3))])
            kg = np.concatenate([k_on[sel], k_off[start:start + len(rest)]])
            PPhi = np.einsum("nij,njm->nim", Pg, phi)
            G = np.einsum("n,nim,nil->ml", kg, PPhi, PPhi)
            self.fits.append((sel, slice(start, start + len(rest)), c0, L, phi, PPhi, kg, np.linalg.pinv(G, rcond=1e-9)))
            for m in range(12):  # the response to this organ moving by mode m alone
                d_on = np.zeros((len(self.idx), 3))
                d_off = np.zeros((len(self.off), 3))
                d_on[sel] = phi[: len(sel), :, m]
                d_off[start:start + len(rest)] = phi[len(sel):, :, m]
                cm._u = None
                u, info = cm.solve(d_on, d_off)
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
            _keep_observed(disp, self.idx, self.axes, d_on, self.off, self.offP, d_off)
        return CompletionResult(x + disp, True, 0, float("nan"), time.perf_counter() - t0, info={"setup_s": self.setup_s})
