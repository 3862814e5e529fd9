"""Finite-element truths of abdominal motion, made by a solver the estimator does not use.

A truth frame is the elastic equilibrium of the abdomen around the organs under anatomical loads, solved by
finite elements: small-strain linear elasticity on trilinear hexahedra (element matrices from scikit-fem,
selective reduced integration so that nearly incompressible tissue does not lock), assembled in numpy/scipy and
solved by a sparse direct factorisation or by conjugate gradients preconditioned with smoothed-aggregation
algebraic multigrid (``pyamg``). Nothing here calls the MPM.

The model (:func:`build_abdomen_mesh`):

- **Region**: a box around the organs of the method plus ``margin_mm`` (clipped to the scan), cut into cells of
  ``cell_mm`` along the scan's axes. A cell is tissue when most of it lies inside the body outline (the
  intensity image's foreground, holes filled slice by slice, joined with every labelled voxel); air outside the
  body is not meshed.
- **Tissues**: each cell is sampled at points about 1.5 mm apart; each point takes the tissue of its voxel
  (pancreas, stomach, duodenum, left kidney, liver, bone where the preset labels vertebrae, else surrounding soft
  tissue: fat and connective tissue). The cell's shear modulus is the harmonic mean of its points' (thin soft
  layers are not stiffened by the cell around them), its first Lame parameter the arithmetic mean.
- **Sliding**: organs slide along their neighbours through a *compliant interface layer*: the points within
  ``interface_mm / 2`` of another organ take a shear modulus ``interface_ratio`` times the softer side's (the
  loose areolar tissue and peritoneal fluid between viscera), keeping their bulk modulus. A layer rather than
  frictionless contact because it keeps the problem linear (one factorisation serves every frame, every frame is
  an exact equilibrium) and needs no conforming surface mesh, which a voxel label map does not give.
- **Materials** are drawn per case (``seed``) from published soft-tissue ranges (:data:`TISSUE_RANGES`), never from
  the estimator's table. All loads are kinematic (prescribed displacements and eigenstrains), so the answer
  depends only on the ratios of the moduli, not on their scale (MR elastography's dynamic moduli serve as well
  as quasi-static ones for that).
- **Anchors**: the patient lies supine on the couch: the most posterior tissue node of every column across the
  back (the posterior wall) is held, and so is every node of a bone cell (vertebrae where the preset labels them,
  :data:`ANCHOR_LABELS`).
- **Loads** (:data:`LOADS`), any combination:
  ``breathing``: the superior face (the diaphragm side) moves inferior by 8-20 mm and anterior by 2-5 mm at peak
  inhale, with a Lujan waveform ``sin^4(pi t / T)`` whose period (3.5-5 s), amplitude and exhale baseline
  (+-1.5 mm) are drawn per cycle; the motion fades to zero over ``posterior_taper_mm`` toward the held back
  (the crura of the diaphragm are tied to the spine).
  ``drift``: a slow superior-inferior drift of the diaphragm side, 0.05-0.2 mm/s inferior.
  ``filling``: the stomach swells (an isotropic eigenstrain growing linearly to a 5-15 % volume gain at the
  series' end).
  ``push``: a local swelling of the duodenum (the stomach when the case has no duodenum) where it touches the
  pancreas: a Gaussian bolus of 12-20 mm radius, 30-60 % volumetric eigenstrain at its centre (a bowel segment
  going from collapsed to distended), rising and falling over the series (``sin^2``).
  ``peristalsis``: a contraction band (-5 to -10 % volumetric eigenstrain, Gaussian of 12 mm) running along the
  duodenum's long axis at 5-15 mm/s (it forms over the first 0.5 s).
- **Frames**: frame ``n`` at ``t = n / fps``; frame 0 is the planning state (exhale) plus whatever the aperiodic
  loads hold at t = 0 (nothing). Each frame is solved on its own (the previous frame's answer warm-starts the
  iterative solver) and reports its residual ``||K u - f|| / ||f||`` on the free unknowns.

The truth leaves the program as a displacement field on the planning image's grid (:mod:`warpmpm.fields`):
at each planning voxel the displacement (mm, world LPS axes) of the tissue there. Outside the meshed region
(air, or beyond the box) the field takes its nearest meshed node's value.

Not modelled, and why: hyperelasticity (the frames record the 99th-percentile principal strain in the organs so a
reader sees where linear elasticity is stretched; 3-8 % on the samples at 8-20 mm breathing), gravity and
pressure (the loads are kinematic), frictionless contact (see sliding above).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass

import numpy as np

from .elastic_amg import elasticity_preconditioner, rigid_body_modes
from .errors import InputError, SimulationError
from .anatomy import ANCHOR_LABELS, LIVER_LABELS, TISSUE_RANGES, TISSUES, TissueRange, body_mask, tissue_map  # noqa: F401 (re-exported)
from .anatomy import TISSUE_CODE as _T
from .images import ORGANS, Case, Geometry

__all__ = ["LOADS", "DIRECT_MAX_DOFS", "TruthConfig", "CORNERS", "reference_matrices", "assemble", "ElasticSolver",
           "BoxMesh", "draw_materials", "build_abdomen_mesh", "anatomical_axes", "BreathingCycles", "draw_loads",
           "cell_eigenstrain", "load_state", "diaphragm_displacement", "TruthSeries", "AbdomenModel", "make_truth",
           "write_truth"]

#: The loads a truth frame can combine.
LOADS = ("breathing", "drift", "filling", "push", "peristalsis")

#: Free unknowns above which the equilibrium is solved by AMG-preconditioned conjugate gradients (below: SuperLU;
#: measured on the MR sample, 71k unknowns: SuperLU 60 s to factorise, AMG-CG 1.2-1.5 s a frame, 23 iterations).
DIRECT_MAX_DOFS = 20_000


@dataclass(frozen=True)
class TruthConfig:
    """How a finite-element truth series is made (:func:`make_truth`)."""

    loads: tuple[str, ...] = ("breathing",)
    """Loads of every frame, from :data:`LOADS`; ``breathing`` alone is free breathing."""
    frames: int = 16
    """Number of frames; frame ``n`` is at ``n / fps`` seconds."""
    fps: float = 4.0
    """Frames per second (a cine frame every 0.1-0.3 s on an MR-Linac)."""
    seed: int = 0
    """Seeds the materials, the breathing cycles and the aperiodic loads."""
    cell_mm: float = 5.0
    """Edge of the hexahedral cells (mm); mesh convergence h against h/2 is in ``benchmarks/fem_truth.py``."""
    margin_mm: float = 30.0
    """Tissue meshed around the organs' bounding box (mm, each side; clipped to the scan)."""
    interface_mm: float = 3.0
    """Thickness of the sliding layer between two organs (mm); 0: organs bonded to each other."""
    interface_ratio: float | None = None
    """Shear modulus of the sliding layer over the softer neighbour's; None: drawn in 0.02-0.1."""
    posterior_taper_mm: float = 40.0
    """Distance from the held back over which the diaphragm side's motion grows from zero to full (mm)."""
    sample_mm: float = 1.5
    """Spacing of the points that give a cell its tissue (mm)."""
    rtol: float = 1e-8
    """Relative residual the iterative solver stops at."""

    def __post_init__(self):
        bad = [x for x in self.loads if x not in LOADS]
        if bad or not self.loads:
            raise InputError(f"unknown load(s) {bad or '(none)'}; choose from {', '.join(LOADS)}, comma-separated")
        if "breathing" not in self.loads and "drift" not in self.loads and not set(self.loads) & {"filling", "push", "peristalsis"}:
            raise InputError("a truth needs at least one load")
        if not (isinstance(self.frames, int) and not isinstance(self.frames, bool) and 1 <= self.frames <= 10_000):
            raise InputError(f"--frames must be a whole number in 1..10000, got {self.frames!r}")
        for name, lo, hi in (("fps", 0.1, 100.0), ("cell_mm", 0.5, 50.0), ("margin_mm", 0.0, 200.0), ("interface_mm", 0.0, 20.0),
                             ("posterior_taper_mm", 0.0, 500.0), ("sample_mm", 0.2, 10.0)):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise InputError(f"--{name.replace('_', '-')} must be a finite number in {lo}..{hi}, got {v!r}")
        if self.interface_ratio is not None and not (0 < self.interface_ratio <= 1):
            raise InputError(f"interface ratio must be in (0, 1], got {self.interface_ratio!r}")
        if not (isinstance(self.seed, int) and 0 <= self.seed < 2**31):
            raise InputError(f"--seed must be a whole number in 0..{2**31 - 1}, got {self.seed!r}")


# ---------------------------------------------------------------------------------------------------------------
# Element matrices and assembly
# ---------------------------------------------------------------------------------------------------------------

#: Corner offsets (a, b, c) of a hexahedron in the order of :func:`reference_matrices` (corner = a + 2 b + 4 c).
CORNERS = np.array([[a, b, c] for c in (0, 1) for b in (0, 1) for a in (0, 1)])


def reference_matrices(h_mm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stiffness of one box-shaped trilinear hexahedron of edges ``h_mm`` (x, y, z), from scikit-fem.

    Returns ``(K_mu, K_lam, g)``: 24x24 matrices with ``K = mu K_mu + lam K_lam`` (``2 eps(u):eps(v)`` at 3x3x3
    Gauss points, ``div u div v`` at the centre: selective reduced integration), and ``g`` (24,) the load of a unit
    isotropic eigenstrain per unit bulk term, ``f = 3 K e* g`` with ``g = int div v`` at the centre. Unknowns are
    ordered ``3 * corner + component``, corners as :data:`CORNERS`; lengths in mm.
    """
    from skfem import Basis, BilinearForm, ElementHex1, ElementVector, LinearForm, MeshHex, asm
    from skfem.helpers import ddot, div, sym_grad

    hx, hy, hz = (float(v) for v in h_mm)
    mesh = MeshHex.init_tensor(np.array([0.0, hx]), np.array([0.0, hy]), np.array([0.0, hz]))
    e = ElementVector(ElementHex1())
    # scikit-fem's hexahedral rules never go below 2x2x2 points (intorder 0..3 all give 8): the one-point rule at the
    # reference cube's centre is given explicitly, else the volumetric term would be fully integrated and lock
    full = Basis(mesh, e, intorder=3)
    reduced = Basis(mesh, e, quadrature=(np.array([[0.5], [0.5], [0.5]]), np.array([1.0])))

    @BilinearForm
    def dev(u, v, w):
        return 2.0 * ddot(sym_grad(u), sym_grad(v))

    @BilinearForm
    def vol(u, v, w):
        return div(u) * div(v)

    @LinearForm
    def dil(v, w):
        return div(v)

    Km, Kl = asm(dev, full).toarray(), asm(vol, reduced).toarray()
    g = asm(dil, reduced)
    corner = np.rint(mesh.p.T / np.array([hx, hy, hz])).astype(int) @ np.array([1, 2, 4])  # skfem node -> our corner
    order = np.empty(24, dtype=int)
    for node in range(8):
        for comp in range(3):
            order[3 * corner[node] + comp] = full.nodal_dofs[comp, node]
    return Km[np.ix_(order, order)], Kl[np.ix_(order, order)], g[order]


def assemble(element_dofs: np.ndarray, mu: np.ndarray, lam: np.ndarray, K_mu: np.ndarray, K_lam: np.ndarray, n_dofs: int,
             chunk: int = 40_000):
    """The global stiffness (CSR) of elements with unknowns ``element_dofs`` (n_el, 24) and moduli ``mu``, ``lam``
    (Pa), summed chunk by chunk to bound memory."""
    from scipy.sparse import coo_matrix

    K = None
    for s in range(0, len(element_dofs), chunk):
        d = element_dofs[s:s + chunk]
        data = mu[s:s + chunk, None] * K_mu.ravel()[None] + lam[s:s + chunk, None] * K_lam.ravel()[None]
        rows = np.repeat(d, 24, axis=1).ravel()
        cols = np.tile(d, (1, 24)).ravel()
        part = coo_matrix((data.ravel(), (rows, cols)), shape=(n_dofs, n_dofs)).tocsr()
        K = part if K is None else K + part
    return K


class ElasticSolver:
    """``K u = f`` with some unknowns prescribed, factorised or preconditioned once, solved for many right-hand sides.

    ``fixed``: indices of prescribed unknowns. Above :data:`DIRECT_MAX_DOFS` free unknowns: CG with smoothed-
    aggregation AMG (near-null space: the rigid motions of ``points_mm``), else SuperLU.
    """

    def __init__(self, K, fixed: np.ndarray, points_mm: np.ndarray | None = None, rtol: float = 1e-8):
        n = K.shape[0]
        self.fixed = np.unique(np.asarray(fixed, dtype=np.int64))
        free = np.ones(n, dtype=bool)
        free[self.fixed] = False
        self.free = np.nonzero(free)[0]
        self.K = K
        self.Kff = K[self.free][:, self.free].tocsr()
        self.Kfd = K[self.free][:, self.fixed].tocsr()
        self.rtol = rtol
        self.method = "superlu" if len(self.free) <= DIRECT_MAX_DOFS else "amg-cg"
        if self.method == "superlu":
            from scipy.sparse.linalg import splu

            self._lu = splu(self.Kff.tocsc())
        else:
            B = None if points_mm is None else rigid_body_modes(points_mm)[self.free]
            self._M, self._ml = elasticity_preconditioner(self.Kff, B, max_coarse=2000)

    def solve(self, f: np.ndarray, prescribed: np.ndarray, x0: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """Solution ``u`` (all unknowns) with ``u[fixed] = prescribed`` and load ``f``, and ``{residual, iterations}``:
        ``residual = ||K_ff u_f - (f_f - K_fd u_d)|| / ||f_f - K_fd u_d||``."""
        u = np.zeros(self.K.shape[0])
        u[self.fixed] = prescribed
        rhs = f[self.free] - self.Kfd @ prescribed
        norm = float(np.linalg.norm(rhs))
        iters = 0
        if norm == 0.0:
            return u, {"residual": 0.0, "iterations": 0}
        if self.method == "superlu":
            uf = self._lu.solve(rhs)
        else:
            from scipy.sparse.linalg import cg

            count = [0]

            def cb(_):
                count[0] += 1

            uf, info = cg(self.Kff, rhs, x0=None if x0 is None else x0[self.free], rtol=self.rtol, atol=0.0, maxiter=2000,
                          M=self._M, callback=cb)
            iters = count[0]
            if info != 0:
                raise SimulationError(f"finite-element truth: conjugate gradients did not reach {self.rtol:g} in 2000 iterations")
        u[self.free] = uf
        res = float(np.linalg.norm(self.Kff @ uf - rhs)) / norm
        return u, {"residual": res, "iterations": iters}


# ---------------------------------------------------------------------------------------------------------------
# The abdomen's mesh
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class BoxMesh:
    """A box of hexahedral cells along the scan's axes, only the tissue cells kept.

    Attributes:
        geometry: the planning scan's grid.
        lo_index: continuous voxel index of the box's corner node (i, j, k).
        n_cells: cells along the scan's i, j, k axes.
        h_mm: cell edges along i, j, k (mm).
        keep: (n_k, n_j, n_i) bool, tissue cells.
        tissue: (n_k, n_j, n_i) int8 majority tissue code (:data:`TISSUES`).
        sample_mm: spacing of the points that give a cell its tissue (mm).
        mu_pa, lam_pa: (n_k, n_j, n_i) cell moduli (Pa).
        fractions: tissue -> (n_k, n_j, n_i) share of the cell's sample points in that tissue.
        point_tissue: (n_cells, S) tissue codes of every cell's sample points (their positions: :meth:`sample_local_mm`).
        materials: the drawn material of every tissue (``mu_pa``, ``nu``, ``lam_pa``) and the interface ratio.
    """

    geometry: Geometry
    lo_index: np.ndarray
    n_cells: tuple[int, int, int]
    h_mm: np.ndarray
    keep: np.ndarray
    tissue: np.ndarray
    mu_pa: np.ndarray
    lam_pa: np.ndarray
    fractions: dict
    point_tissue: np.ndarray
    materials: dict
    sample_mm: float = 1.5

    @property
    def node_shape(self) -> tuple[int, int, int]:
        """Nodes along k, j, i (numpy order)."""
        return (self.n_cells[2] + 1, self.n_cells[1] + 1, self.n_cells[0] + 1)

    def node_local_mm(self) -> np.ndarray:
        """(n_nodes, 3) node positions along the scan's axes from the box corner (mm), node id = i + nx (j + ny k)."""
        nk, nj, ni = self.node_shape
        k, j, i = np.meshgrid(np.arange(nk), np.arange(nj), np.arange(ni), indexing="ij")
        return np.stack([i.ravel(), j.ravel(), k.ravel()], 1) * self.h_mm

    def local_to_world(self, local_mm: np.ndarray) -> np.ndarray:
        return self.geometry.index_to_world(self.lo_index + np.asarray(local_mm) / np.asarray(self.geometry.spacing_mm))

    def world_to_local(self, xyz: np.ndarray) -> np.ndarray:
        return (self.geometry.world_to_index(xyz) - self.lo_index) * np.asarray(self.geometry.spacing_mm)

    def element_nodes(self) -> np.ndarray:
        """(n_kept, 8) node ids of the kept cells, corners as :data:`CORNERS`."""
        nk, nj, ni = self.node_shape
        kk, jj, ii = np.nonzero(self.keep)
        return np.stack([(ii + a) + ni * ((jj + b) + nj * (kk + c)) for a, b, c in CORNERS], 1)

    def sample_local_mm(self, cells: np.ndarray | None = None) -> np.ndarray:
        """(n_cells, S, 3) local positions of every cell's sample points (cells in C order of (k, j, i)); the whole
        set is computed once and kept (the loads read it every frame)."""
        if cells is None:
            if getattr(self, "_samples", None) is None:
                self._samples = self._sample_points(None)
            return self._samples
        return self._sample_points(cells)

    def _sample_points(self, cells: np.ndarray | None) -> np.ndarray:
        s = _samples_per_edge(self.h_mm, self.sample_mm)
        off = (np.stack(np.meshgrid(*[(np.arange(n) + 0.5) / n for n in s], indexing="ij"), -1).reshape(-1, 3)) * self.h_mm
        nk, nj, ni = self.keep.shape
        kk, jj, ii = np.meshgrid(np.arange(nk), np.arange(nj), np.arange(ni), indexing="ij")
        base = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], 1) * self.h_mm
        if cells is not None:
            base = base[cells]
        return base[:, None, :] + off[None, :, :]


def _samples_per_edge(h_mm, sample_mm: float) -> np.ndarray:
    return np.maximum(1, np.ceil(np.asarray(h_mm) / sample_mm).astype(int))


def draw_materials(seed: int, interface_ratio: float | None = None) -> dict:
    """Every tissue's ``mu_pa``, ``nu`` and ``lam_pa`` drawn uniformly from :data:`TISSUE_RANGES`, and the sliding
    layer's ratio; the same seed gives the same materials."""
    rng = np.random.default_rng([seed, 101])
    out = {}
    for t in TISSUES[1:]:
        r = TISSUE_RANGES[t]
        mu = 1e3 * rng.uniform(*r.mu_kpa)
        nu = rng.uniform(*r.nu)
        out[t] = {"mu_pa": float(mu), "nu": float(nu), "lam_pa": float(2 * mu * nu / (1 - 2 * nu)), "source": r.source}
    out["interface_ratio"] = float(interface_ratio if interface_ratio is not None else rng.uniform(0.02, 0.1))
    return out


def build_abdomen_mesh(case: Case, preset: str | None, cfg: TruthConfig, materials: dict | None = None) -> BoxMesh:
    """The meshed abdomen around ``case``'s organs (see the module's docstring)."""
    from scipy import ndimage

    g = case.geometry
    sp = np.asarray(g.spacing_mm)
    tissues = tissue_map(case, preset)
    organs = [o for o in ORGANS if o in case.label_map and np.any(case.labels == case.label_map[o])]
    if "pancreas" not in organs:
        raise InputError("the finite-element truth needs a pancreas in the label map")
    mask = np.isin(case.labels, [case.label_map[o] for o in organs])
    kk, jj, ii = np.nonzero(mask)
    lo = np.array([ii.min(), jj.min(), kk.min()]) - 0.5 - cfg.margin_mm / sp
    hi = np.array([ii.max(), jj.max(), kk.max()]) + 0.5 + cfg.margin_mm / sp
    lo = np.maximum(lo, -0.5)
    hi = np.minimum(hi, np.asarray(g.size) - 0.5)
    extent = (hi - lo) * sp
    n_cells = np.maximum(1, np.round(extent / cfg.cell_mm).astype(int))
    h = extent / n_cells
    materials = materials or draw_materials(cfg.seed, cfg.interface_ratio)

    mesh = BoxMesh(g, lo, tuple(int(v) for v in n_cells), h, np.zeros(tuple(n_cells[::-1]), bool),
                   np.zeros(tuple(n_cells[::-1]), np.int8), None, None, {}, None, materials, cfg.sample_mm)
    # sample points -> voxel -> tissue; the sliding layer from each organ's distance map
    pts = mesh.sample_local_mm()  # (n_cells, S, 3)
    n_cells_total, S = pts.shape[0], pts.shape[1]
    vox = np.rint(lo + pts.reshape(-1, 3) / sp).astype(np.int64)
    vox = np.clip(vox, 0, np.asarray(g.size) - 1)
    pt = tissues[vox[:, 2], vox[:, 1], vox[:, 0]].reshape(n_cells_total, S)
    interface = np.zeros(pt.shape, bool)
    if cfg.interface_mm > 0:
        near = {}
        for o in organs:
            d = ndimage.distance_transform_edt(tissues != _T[o], sampling=sp[::-1])
            near[o] = d[vox[:, 2], vox[:, 1], vox[:, 0]].reshape(pt.shape) <= cfg.interface_mm / 2
        for o in organs:  # a point of one organ near another organ
            others = np.zeros(pt.shape, bool)
            for o2 in organs:
                if o2 != o:
                    others |= near[o2]
            interface |= (pt == _T[o]) & others
    mu_t = np.zeros(len(TISSUES))
    lam_t = np.zeros(len(TISSUES))
    for t, m in materials.items():
        if t in _T:
            mu_t[_T[t]], lam_t[_T[t]] = m["mu_pa"], m["lam_pa"]
    mu_pt, lam_pt = mu_t[pt], lam_t[pt]
    if interface.any():
        soft = min(materials[o]["mu_pa"] for o in organs)
        mu_pt = np.where(interface, materials["interface_ratio"] * np.minimum(mu_pt, soft), mu_pt)
    tissue_pt = pt != _T["air"]
    keep = tissue_pt.mean(1) > 0.5
    with np.errstate(divide="ignore", invalid="ignore"):
        mu_cell = np.where(tissue_pt.any(1), tissue_pt.sum(1) / np.where(tissue_pt, 1.0 / np.maximum(mu_pt, 1e-30), 0.0).sum(1), 0.0)
        lam_cell = np.where(tissue_pt.any(1), np.where(tissue_pt, lam_pt, 0.0).sum(1) / np.maximum(tissue_pt.sum(1), 1), 0.0)
    counts = np.stack([(pt == i).sum(1) for i in range(len(TISSUES))], 1)
    shape = tuple(n_cells[::-1])
    mesh.keep = keep.reshape(shape)
    mesh.tissue = np.argmax(counts, 1).astype(np.int8).reshape(shape)
    mesh.mu_pa, mesh.lam_pa = mu_cell.reshape(shape), lam_cell.reshape(shape)
    mesh.fractions = {t: (counts[:, _T[t]] / S).reshape(shape) for t in TISSUES}
    mesh.point_tissue = pt
    if not mesh.keep.any():
        raise InputError("the finite-element truth found no tissue around the organs (is the image's body outline empty?)")
    return mesh


# ---------------------------------------------------------------------------------------------------------------
# Loads and boundary conditions
# ---------------------------------------------------------------------------------------------------------------


def anatomical_axes(geometry: Geometry) -> dict:
    """The scan axis (0, 1, 2 = i, j, k) and sign of posterior (+y) and superior (+z) in world LPS."""
    D = geometry.direction_matrix
    out = {}
    for name, row in (("lateral", 0), ("posterior", 1), ("superior", 2)):
        ax = int(np.argmax(np.abs(D[row])))
        out[name] = (ax, float(np.sign(D[row, ax])))
    if len({v[0] for v in out.values()}) < 3:
        raise InputError(f"the scan's axes are too oblique to find its posterior and superior faces (direction {geometry.direction})")
    return out


@dataclass
class BreathingCycles:
    """Per-cycle breathing parameters (drawn once per series)."""

    period_s: list
    si_mm: list
    ap_mm: list
    baseline_mm: list

    @classmethod
    def draw(cls, rng, duration_s: float) -> "BreathingCycles":
        p, si, ap, base, t = [], [], [], [], 0.0
        while t <= duration_s + 5.0 or len(p) < 2:
            p.append(float(rng.uniform(3.5, 5.0)))
            si.append(float(rng.uniform(8.0, 20.0)))
            ap.append(float(rng.uniform(2.0, 5.0)))
            base.append(0.0 if not base else float(rng.uniform(-1.5, 1.5)))
            t += p[-1]
        return cls(p, si, ap, base)

    def at(self, t: float) -> tuple[float, float]:
        """(inferior mm, anterior mm) of the diaphragm side at time ``t`` (s)."""
        start = 0.0
        for c, T in enumerate(self.period_s):
            if t < start + T or c == len(self.period_s) - 1:
                u = (t - start) / T
                w = math.sin(math.pi * min(u, 1.0)) ** 4
                nxt = self.baseline_mm[c + 1] if c + 1 < len(self.baseline_mm) else self.baseline_mm[c]
                base = self.baseline_mm[c] + (nxt - self.baseline_mm[c]) * min(u, 1.0)
                return self.si_mm[c] * w + base, self.ap_mm[c] * w
            start += T
        return 0.0, 0.0


def _principal_axis(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt[0]


def draw_loads(mesh: BoxMesh, cfg: TruthConfig) -> dict:
    """The parameters of every load of ``cfg.loads`` for this mesh, drawn from ``cfg.seed``."""
    rng = np.random.default_rng([cfg.seed, 202])
    duration = max(cfg.frames - 1, 1) / cfg.fps
    out: dict = {}
    if "breathing" in cfg.loads:
        out["breathing"] = asdict(BreathingCycles.draw(rng, duration))
    if "drift" in cfg.loads:
        out["drift"] = {"rate_mm_s": float(rng.uniform(0.05, 0.2))}
    if "filling" in cfg.loads:
        out["filling"] = {"volume_gain": float(rng.uniform(0.05, 0.15)), "duration_s": duration}
    pts = mesh.sample_local_mm().reshape(-1, 3)
    pt = mesh.point_tissue.ravel()
    if "push" in cfg.loads:
        organ = "duodenum" if np.any(pt == _T["duodenum"]) else "stomach"
        pan = pts[pt == _T["pancreas"]]
        nb = pts[pt == _T[organ]]
        if len(nb) == 0:
            raise InputError("the push load needs a duodenum or a stomach in the label map")
        # the neighbour's points closest to the pancreas: their centroid is the bolus's centre
        from scipy.spatial import cKDTree

        d, _ = cKDTree(pan[:: max(1, len(pan) // 20000)]).query(nb)
        centre = nb[d <= np.percentile(d, 5)].mean(0)
        out["push"] = {"organ": organ, "centre_mm": mesh.local_to_world(centre[None])[0].tolist(),
                       "radius_mm": float(rng.uniform(12.0, 20.0)), "eigenstrain": float(rng.uniform(0.3, 0.6)) / 3.0,
                       "duration_s": duration}
    if "peristalsis" in cfg.loads:
        duo = pts[pt == _T["duodenum"]]
        if len(duo) == 0:
            raise InputError("the peristalsis load needs a duodenum in the label map")
        c, axis = _principal_axis(duo)
        s = (duo - c) @ axis
        out["peristalsis"] = {"centre_mm": mesh.local_to_world(c[None])[0].tolist(), "axis": (mesh.geometry.direction_matrix @ axis).tolist(),
                              "start_mm": float(s.min()), "speed_mm_s": float(rng.uniform(5.0, 15.0)),
                              "width_mm": 12.0, "eigenstrain": -float(rng.uniform(0.05, 0.10)) / 3.0}
    return out


def cell_eigenstrain(mesh: BoxMesh, loads: dict, t: float) -> np.ndarray:
    """(n_cells,) isotropic eigenstrain of every cell at time ``t`` (the mean over its sample points)."""
    shape = mesh.keep.shape
    e = np.zeros(int(np.prod(shape)))
    pt = mesh.point_tissue
    if "filling" in loads:
        L = loads["filling"]
        ramp = min(t / L["duration_s"], 1.0) if L["duration_s"] > 0 else 1.0
        e += (np.cbrt(1.0 + L["volume_gain"] * ramp) - 1.0) * mesh.fractions["stomach"].ravel()
    if "push" in loads or "peristalsis" in loads:
        pts = mesh.sample_local_mm()
        if "push" in loads:
            L = loads["push"]
            c = mesh.world_to_local(np.asarray(L["centre_mm"])[None])[0]
            amp = L["eigenstrain"] * (math.sin(math.pi * min(t / L["duration_s"], 1.0)) ** 2 if L["duration_s"] > 0 else 1.0)
            w = np.exp(-0.5 * np.sum((pts - c) ** 2, -1) / L["radius_mm"] ** 2) * (pt == _T[L["organ"]])
            e += amp * w.mean(1)
        if "peristalsis" in loads:
            L = loads["peristalsis"]
            c = mesh.world_to_local(np.asarray(L["centre_mm"])[None])[0]
            axis = mesh.geometry.direction_matrix.T @ np.asarray(L["axis"])
            s = (pts - c) @ axis
            pos = L["start_mm"] + L["speed_mm_s"] * t
            w = np.exp(-0.5 * ((s - pos) / L["width_mm"]) ** 2) * (pt == _T["duodenum"])
            e += L["eigenstrain"] * min(t / 0.5, 1.0) * w.mean(1)  # the band forms over the first 0.5 s
    return e.reshape(shape)


def load_state(loads: dict, t: float) -> dict:
    """What each aperiodic load amounts to at time ``t`` (for a frame's record): the stomach's volume gain, the push's
    eigenstrain at its centre, the peristaltic band's position along the duodenum's axis (mm from its start)."""
    out = {}
    if "filling" in loads:
        L = loads["filling"]
        out["filling_volume_gain"] = L["volume_gain"] * (min(t / L["duration_s"], 1.0) if L["duration_s"] > 0 else 1.0)
    if "push" in loads:
        L = loads["push"]
        out["push_eigenstrain"] = L["eigenstrain"] * (math.sin(math.pi * min(t / L["duration_s"], 1.0)) ** 2 if L["duration_s"] > 0 else 1.0)
    if "peristalsis" in loads:
        L = loads["peristalsis"]
        out["peristalsis_band_mm"] = L["speed_mm_s"] * t
    if "drift" in loads:
        out["drift_mm"] = loads["drift"]["rate_mm_s"] * t
    return out


def diaphragm_displacement(loads: dict, t: float) -> tuple[float, float]:
    """(inferior, anterior) displacement (mm) of the diaphragm side at time ``t``: breathing plus drift."""
    inf, ant = 0.0, 0.0
    if "breathing" in loads:
        b = BreathingCycles(**loads["breathing"])
        inf, ant = b.at(t)
    if "drift" in loads:
        inf += loads["drift"]["rate_mm_s"] * t
    return inf, ant


# ---------------------------------------------------------------------------------------------------------------
# The series
# ---------------------------------------------------------------------------------------------------------------


@dataclass
class TruthSeries:
    """A finite-element truth: one displacement field per frame on the planning grid, and its record."""

    geometry: Geometry
    fields_mm: list  # (z, y, x, 3) float32 per frame, world LPS mm
    record: dict

    def field(self, n: int) -> np.ndarray:
        return self.fields_mm[n]


class AbdomenModel:
    """The meshed abdomen, its stiffness and boundary conditions, built once; :meth:`solve_frame` per frame."""

    def __init__(self, case: Case, preset: str | None, cfg: TruthConfig, materials: dict | None = None):
        t0 = time.perf_counter()
        self.case, self.cfg = case, cfg
        self.mesh = mesh = build_abdomen_mesh(case, preset, cfg, materials)
        K_mu, K_lam, self.g_ref = reference_matrices(mesh.h_mm)
        en = mesh.element_nodes()
        active = np.unique(en)
        self.active = active
        renum = np.full(int(np.prod(mesh.node_shape)), -1, dtype=np.int64)
        renum[active] = np.arange(len(active))
        self.renum = renum
        self.elem = renum[en]  # (n_el, 8) active node ids
        self.edofs = (3 * self.elem[:, :, None] + np.arange(3)[None, None, :]).reshape(len(en), 24)
        keep = mesh.keep.ravel()
        self.mu_e, self.lam_e = mesh.mu_pa.ravel()[keep], mesh.lam_pa.ravel()[keep]
        n_dofs = 3 * len(active)
        K = assemble(self.edofs, self.mu_e, self.lam_e, K_mu, K_lam, n_dofs)
        local = mesh.node_local_mm()[active]
        self.local = local
        # boundary conditions
        axes = anatomical_axes(case.geometry)
        ap_ax, ap_sign = axes["posterior"]
        si_ax, si_sign = axes["superior"]
        lat_ax, _ = axes["lateral"]
        nodes_ijk = np.rint(local / mesh.h_mm).astype(int)
        post_coord = ap_sign * local[:, ap_ax]  # larger: more posterior
        # the most posterior node of each column across the back (same lateral and SI index)
        key = nodes_ijk[:, lat_ax] * (mesh.node_shape[::-1][si_ax] + 1) + nodes_ijk[:, si_ax]
        order = np.lexsort((-post_coord, key))
        first = np.ones(len(order), bool)
        first[1:] = key[order][1:] != key[order][:-1]
        back = np.zeros(len(local), bool)
        back[order[first]] = True
        # each node's distance to its column's back (for the diaphragm's taper)
        uniq, inv = np.unique(key, return_inverse=True)
        back_coord = np.full(len(uniq), -np.inf)
        np.maximum.at(back_coord, inv, post_coord)
        col_back = back_coord[inv] - post_coord
        bone_cells = (mesh.tissue.ravel()[keep] == _T["bone"])
        bone = np.zeros(len(local), bool)
        bone[np.unique(self.elem[bone_cells])] = True
        self.held = back | bone
        top_index = mesh.n_cells[si_ax] if si_sign > 0 else 0
        self.diaphragm = (nodes_ijk[:, si_ax] == top_index) & ~self.held
        tp = cfg.posterior_taper_mm
        x = np.clip(col_back / tp, 0.0, 1.0) if tp > 0 else np.ones(len(local))
        self.taper = x * x * (3 - 2 * x)
        D = case.geometry.direction_matrix
        self.e_inf_local = D.T @ np.array([0.0, 0.0, -1.0])  # world inferior in scan-axis components
        self.e_ant_local = D.T @ np.array([0.0, -1.0, 0.0])
        fixed_nodes = np.nonzero(self.held | self.diaphragm)[0]
        self.fixed_nodes = fixed_nodes
        fixed = (3 * fixed_nodes[:, None] + np.arange(3)[None]).ravel()
        self.solver = ElasticSolver(K, fixed, local, cfg.rtol)
        self.bulk3_e = 3.0 * self.lam_e + 2.0 * self.mu_e  # 3 K
        self.build_s = time.perf_counter() - t0
        self._u = None
        self._grid_map = None  # (fill indices of the unmeshed nodes, voxel coordinates on the node grid): field_on_grid's
        if not self.held.any():
            raise InputError("the finite-element truth holds nothing still (no posterior wall found)")
        if not self.diaphragm.any() and ("breathing" in cfg.loads or "drift" in cfg.loads):
            raise InputError("breathing needs a superior face of tissue; the scan has none above the organs")

    def prescribed(self, inferior_mm: float, anterior_mm: float) -> np.ndarray:
        """The prescribed unknowns (order of ``fixed_nodes`` x 3): held nodes zero, the diaphragm side moved."""
        u = np.zeros((len(self.fixed_nodes), 3))
        dia = self.diaphragm[self.fixed_nodes]
        v = inferior_mm * self.e_inf_local + anterior_mm * self.e_ant_local
        u[dia] = self.taper[self.fixed_nodes][dia, None] * v[None]
        return u.ravel()

    def load_vector(self, eigen_cell: np.ndarray) -> np.ndarray:
        """The nodal loads of cell eigenstrains ``e*`` (isotropic): ``f_e = 3 K_e e*_e g``."""
        e = eigen_cell.ravel()[self.mesh.keep.ravel()]
        f = np.zeros(3 * len(self.active))
        np.add.at(f, self.edofs.ravel(), ((self.bulk3_e * e)[:, None] * self.g_ref[None]).ravel())
        return f

    def solve_frame(self, inferior_mm: float, anterior_mm: float, eigen_cell: np.ndarray) -> tuple[np.ndarray, dict]:
        """Node displacements (n_active, 3) along the scan's axes (mm) and the solve's report."""
        t0 = time.perf_counter()
        u, info = self.solver.solve(self.load_vector(eigen_cell), self.prescribed(inferior_mm, anterior_mm), self._u)
        self._u = u
        info["wall_s"] = time.perf_counter() - t0
        return u.reshape(-1, 3), info

    def strain_p99(self, u_nodes: np.ndarray, tissues=("pancreas", "stomach", "duodenum", "left_kidney")) -> float:
        """99th percentile over the organ cells of the largest absolute principal strain at the cell centre."""
        U = u_nodes[self.elem]  # (n_el, 8, 3)
        h = self.mesh.h_mm
        grad = np.zeros((len(U), 3, 3))
        for d in range(3):
            hi = CORNERS[:, d] == 1
            grad[:, :, d] = (U[:, hi].mean(1) - U[:, ~hi].mean(1)) / h[d]
        eps = 0.5 * (grad + grad.transpose(0, 2, 1))
        sel = np.isin(self.mesh.tissue.ravel()[self.mesh.keep.ravel()], [_T[t] for t in tissues])
        if not sel.any():
            return 0.0
        return float(np.percentile(np.abs(np.linalg.eigvalsh(eps[sel])).max(1), 99))

    def field_on_grid(self, u_nodes: np.ndarray) -> np.ndarray:
        """The displacement (z, y, x, 3) float32, world LPS mm, at the planning scan's voxels: trilinear inside the
        meshed region, the nearest meshed node's value elsewhere."""
        from scipy import ndimage

        mesh = self.mesh
        shape = mesh.node_shape
        g = self.case.geometry
        nz, ny, nx = g.size[::-1]
        if self._grid_map is None:  # the same for every frame: computed once
            have = np.zeros(int(np.prod(shape)), bool)
            have[self.active] = True
            have = have.reshape(shape)
            fill = None if have.all() else ndimage.distance_transform_edt(~have, return_indices=True)[1]
            k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
            ijk = np.stack([i.ravel(), j.ravel(), k.ravel()], 1)
            q = (ijk - mesh.lo_index) * np.asarray(g.spacing_mm) / mesh.h_mm  # node-grid coordinates (i, j, k)
            self._grid_map = (fill, q[:, ::-1].T)
        fill, coords = self._grid_map
        grid = np.zeros((int(np.prod(shape)), 3))
        grid[self.active] = u_nodes @ g.direction_matrix.T  # world components
        grid = grid.reshape(shape + (3,))
        if fill is not None:
            grid = grid[fill[0], fill[1], fill[2]]
        out = np.stack([ndimage.map_coordinates(grid[..., c], coords, order=1, mode="nearest") for c in range(3)], -1)
        return out.reshape(nz, ny, nx, 3).astype(np.float32)


def make_truth(case: Case, preset: str | None, cfg: TruthConfig, progress=None) -> TruthSeries:
    """A finite-element truth series of ``case`` (see the module docstring); ``progress`` gets a line per frame."""
    model = AbdomenModel(case, preset, cfg)
    mesh = model.mesh
    loads = draw_loads(mesh, cfg)
    fields, frames = [], []
    pan = case.labels == case.label_map["pancreas"]
    for n in range(cfg.frames):
        t = n / cfg.fps
        inf, ant = diaphragm_displacement(loads, t)
        eig = cell_eigenstrain(mesh, loads, t)
        u, info = model.solve_frame(inf, ant, eig)
        f = model.field_on_grid(u)
        fields.append(f)
        d = np.linalg.norm(f[pan], axis=1)
        rec = {"frame": n, "time_s": t, "diaphragm_inferior_mm": inf, "diaphragm_anterior_mm": ant,
               "load_state": load_state(loads, t),
               "max_eigenstrain": float(np.abs(eig).max()), "residual": info["residual"], "iterations": info["iterations"],
               "wall_s": info["wall_s"], "strain_p99_organs": model.strain_p99(u),
               "pancreas_mean_mm": float(d.mean()), "pancreas_max_mm": float(d.max()),
               "pancreas_mean_vector_mm": f[pan].mean(0).astype(float).tolist()}
        frames.append(rec)
        if progress:
            progress(f"frame {n}: t {t:.2f} s, diaphragm {inf:.1f} mm inferior, pancreas moved {d.mean():.2f} mm "
                     f"(residual {info['residual']:.1e}, {info['wall_s']:.1f} s)")
    counts = {t: int(((mesh.tissue == _T[t]) & mesh.keep).sum()) for t in TISSUES[1:]}
    corners = mesh.local_to_world(np.array([[0.0, 0.0, 0.0], mesh.h_mm * np.asarray(mesh.n_cells)]))
    record = {
        "made_by": "warpmpm.truth_fem: linear elasticity, trilinear hexahedra (scikit-fem element matrices, selective "
                   f"reduced integration), {model.solver.method}",
        "units": "displacement in mm along world LPS axes (+x left, +y posterior, +z superior), at each planning voxel",
        "config": asdict(cfg) | {"loads": list(cfg.loads)},
        "loads": loads,
        "materials": mesh.materials,
        "mesh": {"cell_mm": mesh.h_mm.tolist(), "n_cells": list(mesh.n_cells), "n_elements": int(mesh.keep.sum()),
                 "n_nodes": int(len(model.active)), "n_unknowns": int(3 * len(model.active)),
                 "held_nodes": int(model.held.sum()), "diaphragm_nodes": int(model.diaphragm.sum()),
                 "box_corners_mm": corners.tolist(), "cells_per_tissue": counts, "build_s": model.build_s},
        "frames": frames,
    }
    return TruthSeries(case.geometry, fields, record)


def write_truth(series: TruthSeries, out_dir: str) -> None:
    """``out_dir/fields/frame_NNNN.nii.gz`` (one per frame, :func:`warpmpm.fields.write_field`) and
    ``out_dir/truth.json``; written in a temporary folder beside it and moved into place, so a failure leaves
    nothing half-written. An existing ``out_dir`` that is not empty is refused."""
    from .fields import write_field

    out_dir = os.path.abspath(out_dir)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise InputError(f"--out {out_dir} is a file; name a new folder")
    if os.path.isdir(out_dir) and os.listdir(out_dir):
        raise InputError(f"--out {out_dir} already holds files; name a new or empty folder (a truth is never mixed with another)")
    parent = os.path.dirname(out_dir)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".truth-", dir=parent)
    try:
        os.makedirs(os.path.join(tmp, "fields"))
        for n, f in enumerate(series.fields_mm):
            write_field(f, series.geometry, os.path.join(tmp, "fields", f"frame_{n:04d}.nii.gz"))
        with open(os.path.join(tmp, "truth.json"), "w") as fh:
            json.dump(series.record, fh, indent=1)
        if os.path.isdir(out_dir):
            os.rmdir(out_dir)
        os.replace(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
