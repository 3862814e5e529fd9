"""The abdomen's box mesh: organs and the tissue around them inside the body outline, cell materials drawn from
the published ranges, the anchors (vertebrae) and the couch."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..anatomy import TISSUE_RANGES, TISSUES, tissue_map
from ..anatomy import TISSUE_CODE as _T
from ..errors import InputError
from ..images import ORGANS, Case, Geometry
from .config import TruthConfig
from .elements import CORNERS

__all__ = ["BoxMesh", "draw_materials", "build_abdomen_mesh"]


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
