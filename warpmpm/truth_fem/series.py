"""A finite-element truth series: :class:`AbdomenModel` solves each frame's equilibrium, :func:`make_truth` makes
the series and :func:`write_truth` writes it (fields, ``truth.json``)."""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass

import numpy as np

from ..anatomy import TISSUES
from ..anatomy import TISSUE_CODE as _T
from ..errors import InputError, strict_json
from ..images import Case, Geometry
from .config import TruthConfig
from .elements import CORNERS, ElasticSolver, assemble, reference_matrices
from .mesh import build_abdomen_mesh
from .loads import anatomical_axes, cell_eigenstrain, diaphragm_displacement, draw_loads, load_state

__all__ = ["TruthSeries", "AbdomenModel", "make_truth", "write_truth", "write_truth_files"]


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
        self.diaphragm_from = "the box's superior face"
        if not self.diaphragm.any() and ("breathing" in cfg.loads or "drift" in cfg.loads):
            # no tissue reaches the box's superior face (a scan cut just above the organs): the body's own superior
            # surface is moved instead, the most superior node of each superior-inferior column
            sup = si_sign * local[:, si_ax]
            col = nodes_ijk[:, lat_ax] * (mesh.node_shape[::-1][ap_ax] + 1) + nodes_ijk[:, ap_ax]
            order = np.lexsort((-sup, col))
            top = np.ones(len(order), bool)
            top[1:] = col[order][1:] != col[order][:-1]
            self.diaphragm = np.zeros(len(local), bool)
            self.diaphragm[order[top]] = True
            self.diaphragm &= ~self.held
            self.diaphragm_from = "the body's superior surface (no tissue reaches the scan's top above the organs)"
            import warnings

            from ..errors import InputWarning

            warnings.warn("breathing: the scan has no tissue at its top above the organs; the diaphragm's motion is put on "
                          "the body's own superior surface instead (the truth is less like a breathing abdomen there)",
                          InputWarning, stacklevel=2)
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
                 "held_nodes": int(model.held.sum()), "diaphragm_nodes": int(model.diaphragm.sum()), "diaphragm_from": model.diaphragm_from,
                 "box_corners_mm": corners.tolist(), "cells_per_tissue": counts, "build_s": model.build_s},
        "frames": frames,
    }
    return TruthSeries(case.geometry, fields, record)


def write_truth_files(series: TruthSeries, folder: str) -> None:
    """``folder/fields/frame_NNNN.nii.gz`` (one per frame, :func:`warpmpm.fields.write_field`) and
    ``folder/truth.json``, into an existing (working) folder."""
    from ..fields import write_field

    os.makedirs(os.path.join(folder, "fields"))
    for n, f in enumerate(series.fields_mm):
        write_field(f, series.geometry, os.path.join(folder, "fields", f"frame_{n:04d}.nii.gz"))
    with open(os.path.join(folder, "truth.json"), "w") as fh:
        json.dump(strict_json(series.record), fh, indent=1, allow_nan=False)


def write_truth(series: TruthSeries, out_dir: str) -> None:
    """:func:`write_truth_files` into ``out_dir`` through :class:`warpmpm.output_folder.OutputFolder`: written in a
    working folder beside it and moved into place, so a failure leaves nothing half-written; an existing ``out_dir``
    that is not empty is refused (a truth is never mixed with another), and so is a second writer."""
    from ..output_folder import OutputFolder

    with OutputFolder(out_dir, kind="truth", make_parent=True) as work:
        write_truth_files(series, work)
