"""The completion model (:class:`CompletionModel`): the organs and the tissue around them as material points on a
B-spline grid, their stiffness assembled once per case, with :class:`CompletionConfig`; the solve is
:mod:`warpmpm.solvers.completion`."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import warp as wp

from ..anatomy import TISSUE_CODE, TISSUES, tissue_map
from ..elastic_amg import elasticity_preconditioner, rigid_body_modes
from ..errors import InputError, SimulationError
from ..images import Case
from ..materials import material_table
from ..model import ParticleModel
from . import completion_kernels as ck


__all__ = ["FRINGE", "CompletionConfig", "CompletionModel", "observed_projector"]

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
    materials: str = "tissue"
    """A material table (:func:`warpmpm.materials.material_table`): ``tissue``, every tissue at the middle of its
    published range (:data:`warpmpm.anatomy.TISSUE_RANGES`); ``paper``, the seed paper's four organ materials
    (:data:`warpmpm.model.PAPER_MATERIALS`), tissue as ``tissue``; or a JSON file of one's own."""
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
    through_plane: Literal["copy", "equilibrium"] = "copy"
    """With ``observed_first``, what a seen organ's particles take along the directions none of its planes measures:
    ``copy`` (default), the copy's motion there (with one plane: none); ``equilibrium``, the solve's. Measured on the
    finite-element truths (``benchmarks/studies/completion_ceiling.py``) the equilibrium's through-plane motion is worse
    than the copy's in 6 of 7 cases, even given the true in-plane motion of the whole organ: MR sample, sagittal,
    pancreas left-right 0.56 mm (0.50 with the whole organ's) against 0.28; duodenum seen on the coronal plane only,
    anterior-posterior 0.60 against 0.41 (MR), 1.39 against 0.18 (CT)."""
    rtol: float = 1e-6
    """Relative residual at which a frame's solve has converged."""
    max_iterations: int = 400
    """Conjugate-gradient iterations of one frame at most; a frame that stops short is not converged."""
    reduced_modes: Literal["affine", "translation"] = "affine"
    """:class:`~warpmpm.solvers.completion.ReducedCompletion` (the tracker's): the motions of each seen organ whose
    equilibrium responses are precomputed, ``affine`` (12 an organ) or ``translation`` (3 an organ, 4x fewer solves)."""
    response_rtol: float = 1e-3
    """Relative residual of each precomputed response of :class:`~warpmpm.solvers.completion.ReducedCompletion` (a
    response is a unit motion; 1e-3 against 1e-6 changed no organ's tracked error by 0.01 mm on the phantom's main job,
    for a third of the set-up time)."""

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
        if self.through_plane not in ("copy", "equilibrium"):
            raise InputError(f"CompletionConfig.through_plane must be 'copy' or 'equilibrium', got {self.through_plane!r}")
        if self.reduced_modes not in ("affine", "translation"):
            raise InputError(f"CompletionConfig.reduced_modes must be 'affine' or 'translation', got {self.reduced_modes!r}")
        if not (self.response_rtol > 0 and np.isfinite(self.response_rtol)):
            raise InputError(f"CompletionConfig.response_rtol must be > 0, got {self.response_rtol}")
        material_table(self.materials)  # a name or a readable table: checked before any work


def observed_projector(axes: np.ndarray) -> np.ndarray:
    """The projector onto every direction some of ``axes`` (n, 3, 3 projectors) measures: the span of their sum."""
    if len(axes) == 0:
        return np.zeros((3, 3))
    w, V = np.linalg.eigh(np.asarray(axes, np.float64).sum(0))
    keep = w > 1e-3 * max(w.max(), 1e-30)
    return (V[:, keep] @ V[:, keep].T)


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
        table = material_table(cfg.materials)
        for t in TISSUES[1:]:
            mu[TISSUE_CODE[t]], lam[TISSUE_CODE[t]] = table.entries[t]
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

    def solve(self, d_on_mm: np.ndarray, d_off_mm: np.ndarray, d_tissue_mm: np.ndarray | None = None,
              rtol: float | None = None) -> tuple[np.ndarray, dict]:
        """Node displacements (n_active, 3) mm for the observed displacements of the ``on_plane``, ``off_plane`` and
        ``tissue`` springs of :meth:`observe`, and the solve's report (``converged``, ``iterations``, ``residual``);
        ``rtol``: the relative residual to reach (default the config's)."""
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
        rtol = self.config.rtol if rtol is None else rtol
        u, iters, res = self._cg(b, self._u, rtol)
        if not np.all(np.isfinite(u)):
            raise SimulationError("the completion solve produced non-finite displacements")
        self._u = u
        return u.reshape(-1, 3), {"converged": bool(res <= rtol * 1.01), "iterations": iters, "residual": res}

    def _cg(self, b: np.ndarray, x0: np.ndarray | None, rtol: float) -> tuple[np.ndarray, int, float]:
        from scipy.sparse.linalg import cg

        plan = self._plan
        count = [0]

        def cb(_):
            count[0] += 1

        norm = float(np.linalg.norm(b))
        if norm == 0.0:
            return np.zeros_like(b), 0, 0.0
        u, _ = cg(plan["A"], b, x0=x0, rtol=rtol, atol=0.0, maxiter=self.config.max_iterations, M=plan["M"], callback=cb)
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
                "unknowns": int(3 * len(self.active_nodes)), "build_s": self.build_s,
                "materials": material_table(self.config.materials).name}
