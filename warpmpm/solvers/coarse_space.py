"""One coarse space for every solver that needs one: groups of particles (whole organs, or organs cut into cubes), each
moving with its rigid (6) or affine (12) motions about its centre, on the grid nodes its particles touch, each weighed by
the group's share of the node's mass.

The quasi-static solver's two-level preconditioner uses it with whole organs and rigid motions
(:mod:`warpmpm.solvers.quasistatic`); the rigid-mode acceleration of the explicit relaxation with 25 mm cubes, rigid or
affine (:mod:`warpmpm.solvers.rigid_modes`). Both read the particles' stencils from the kernels' own B-spline
(:func:`~warpmpm.solvers.coarse_space_kernels.particle_stencils`), build the same node table (:meth:`CoarseSpace.table`)
and restrict and prolong with the same mode functions (:mod:`warpmpm.solvers.coarse_space_kernels`).

Mode ``c`` of group ``g`` at node ``x_i``: ``s_ig (a_c + A_c y)`` with ``y = (x_i - centre_g) / L_g`` (``L_g`` the
group's radius of gyration over its nodes, at least a cell), ``s_ig`` the group's share of the node's mass, and
``(a_c, A_c)`` from :func:`basis`.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..errors import InputError
from ..model import ParticleModel
from .coarse_space_kernels import particle_stencils
from .config import RIGID_MODE_AGGREGATE_MM, RIGID_MODE_BASES
from .grid import MPMModel

__all__ = ["AGGREGATE_MM", "MIN_GROUP_PARTICLES", "NODE_GROUPS", "aggregate_groups", "basis", "stencils", "CoarseSpace"]

#: edge of the cubes each organ is cut into for the rigid-mode acceleration (mm): :data:`RIGID_MODE_AGGREGATE_MM`
AGGREGATE_MM = RIGID_MODE_AGGREGATE_MM

#: fewest particles a cube keeps as a group of its own (fewer: merged into the nearest kept cube of its organ)
MIN_GROUP_PARTICLES = 50

#: groups a node holds at most (the largest shares kept)
NODE_GROUPS = 8


def aggregate_groups(particles: ParticleModel, size_mm: float | None = AGGREGATE_MM) -> np.ndarray:
    """A group index per particle: each organ cut into cubes of ``size_mm`` (from its own bounding box), a cube with
    fewer than :data:`MIN_GROUP_PARTICLES` particles merged into the nearest kept cube of the same organ (by centroid);
    ``size_mm`` None: one group per organ."""
    if size_mm is not None and not (isinstance(size_mm, (int, float)) and math.isfinite(size_mm) and size_mm > 0):
        raise InputError(f"aggregate size must be a finite number of mm > 0 (or None: whole organs), got {size_mm!r}")
    groups = np.zeros(particles.n, dtype=np.int32)
    nxt = 0
    for o in range(len(particles.organs)):
        idx = np.nonzero(particles.organ_index == o)[0]
        if idx.size == 0:
            continue
        if size_mm is None:
            groups[idx] = nxt
            nxt += 1
            continue
        x = particles.positions_mm[idx]
        cube = np.floor((x - x.min(0)) / size_mm).astype(np.int64)
        _, label = np.unique(cube, axis=0, return_inverse=True)
        label = label.ravel()
        count = np.bincount(label)
        kept = np.nonzero(count >= MIN_GROUP_PARTICLES)[0]
        if kept.size == 0:
            kept = np.array([int(np.argmax(count))])
        centres = np.stack([x[label == c].mean(0) for c in kept])
        own = np.full(count.size, -1)
        own[kept] = np.arange(kept.size)
        mine = own[label]
        lone = mine < 0
        if lone.any():
            mine[lone] = np.argmin(((x[lone, None, :] - centres[None]) ** 2).sum(2), axis=1)
        groups[idx] = nxt + mine
        nxt += kept.size
    return groups


def basis(affine: bool) -> tuple[np.ndarray, np.ndarray]:
    """``(a, A)`` of the coarse modes of one group, mode ``c`` at ``y = (x - centre) / L`` being ``a_c + A_c y``:
    translations ``e_k``, then rotations ``e_k x y`` (rigid) or the affine ``e_k y_l`` (the same modes as
    :func:`~warpmpm.solvers.coarse_space_kernels.mode_vector`)."""
    S = 12 if affine else 6
    a = np.zeros((S, 3))
    A = np.zeros((S, 3, 3))
    for k in range(3):
        a[k, k] = 1.0
        e = np.eye(3)[k]
        if affine:
            for l in range(3):
                A[3 + 3 * k + l, k, l] = 1.0
        else:
            A[3 + k] = np.cross(e, np.eye(3))  # (e_k x y) = A y: column l is e_k x e_l
            A[3 + k] = A[3 + k].T
    return a, A


def stencils(x: wp.array, dx_m: float, grid_shape, device) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each particle's 27 stencil nodes (flat index, int64), weights (float64) and offsets ``x_i - x_p`` (m, float64),
    from the kernels' own stencil (``x``: grid-local positions, m)."""
    n = x.shape[0]
    flat = wp.zeros((n, 27), dtype=int, device=device)
    w = wp.zeros((n, 27), dtype=float, device=device)
    r = wp.zeros((n, 27), dtype=wp.vec3, device=device)
    wp.launch(particle_stencils, n, [x, float(dx_m), int(grid_shape[1]), int(grid_shape[2]), flat, w, r], device=device)
    return flat.numpy().astype(np.int64), w.numpy().astype(np.float64), r.numpy().astype(np.float64)


class CoarseSpace:
    """The groups' motions on the grid of one :class:`MPMModel`: ``groups`` a group index per particle (e.g.
    :func:`aggregate_groups`), ``modes`` ``"rigid"`` (6 a group) or ``"affine"`` (12)."""

    def __init__(self, model: MPMModel, groups: np.ndarray, modes: str = "rigid"):
        if modes not in RIGID_MODE_BASES:
            raise InputError(f"coarse-space modes must be one of {', '.join(RIGID_MODE_BASES)}, got {modes!r}")
        self.model = model
        self.groups = np.asarray(groups, dtype=np.int64)
        self.n_groups = int(self.groups.max()) + 1
        self.affine = modes == "affine"
        self.stride = 12 if self.affine else 6
        #: coarse unknowns: stride x groups
        self.size = self.stride * self.n_groups
        self.dx_m = model.dx_mm * 1e-3

    def table(self, x: wp.array) -> dict:
        """The node table at particle positions ``x`` (grid-local m): ``nodes`` (flat indices of the active nodes),
        ``node_group`` / ``node_share`` (each node's :data:`NODE_GROUPS` largest group shares, the wall layer's nodes
        none), ``node_mass`` (kg), ``centre`` and ``radius`` (m) of each group over its nodes; with the entries it was
        built from (``node_pos``, ``group_of``, ``share``: one a (node, group) pair; ``Xn``: the active nodes'
        positions) and the particles' stencils (``flat``, ``w``, ``r``)."""
        m = self.model
        G, dx = self.n_groups, self.dx_m
        mass = m.mass_kg.astype(np.float64)
        flat, w, r = stencils(x, dx, m.grid_shape, m.device)
        key = (flat * G + self.groups[:, None]).ravel()
        uk, inv = np.unique(key, return_inverse=True)
        gm = np.bincount(inv.ravel(), weights=(w * mass[:, None]).ravel())
        node_of, group_of = uk // G, (uk % G).astype(np.int64)
        nodes, node_pos = np.unique(node_of, return_inverse=True)
        node_pos = node_pos.ravel()
        node_mass = np.bincount(node_pos, weights=gm)
        share = gm / node_mass[node_pos]
        ijk = np.stack([nodes // (m.grid_shape[1] * m.grid_shape[2]), (nodes // m.grid_shape[2]) % m.grid_shape[1],
                        nodes % m.grid_shape[2]], axis=1)
        wall = m.config.grid.wall_cells
        inside = np.all((ijk >= wall) & (ijk < np.asarray(m.grid_shape) - wall), axis=1)
        share[~inside[node_pos]] = 0.0
        # keep the NODE_GROUPS largest shares of each node
        order = np.lexsort((-share, node_pos))
        rank = np.empty_like(order)
        first = np.r_[0, np.flatnonzero(np.diff(node_pos[order])) + 1]
        counts = np.diff(np.r_[first, order.size])
        rank[order] = np.arange(order.size) - np.repeat(first, counts)
        share[rank >= NODE_GROUPS] = 0.0
        na = nodes.size
        node_group = np.zeros((na, NODE_GROUPS), dtype=np.int32)
        node_share = np.zeros((na, NODE_GROUPS), dtype=np.float64)
        sel = rank < NODE_GROUPS
        node_group[node_pos[sel], rank[sel]] = group_of[sel]
        node_share[node_pos[sel], rank[sel]] = share[sel]
        Xn = ijk * dx
        # each group's centre and radius of gyration over the nodes it has a share of
        wsum = np.bincount(group_of, weights=share, minlength=G)
        if np.any(wsum <= 0):
            raise InputError("coarse space: a group of particles has no grid node of its own (all in the wall layer?); "
                             "increase GridConfig.margin_mm or turn the coarse level off")
        centre = np.stack([np.bincount(group_of, weights=share * Xn[node_pos, c], minlength=G) for c in range(3)], axis=1) / wsum[:, None]
        d2 = ((Xn[node_pos] - centre[group_of]) ** 2).sum(1)
        radius = np.maximum(np.sqrt(np.bincount(group_of, weights=share * d2, minlength=G) / wsum), dx)
        return {"nodes": nodes, "node_group": node_group, "node_share": node_share, "node_mass": node_mass, "centre": centre,
                "radius": radius, "node_pos": node_pos, "group_of": group_of, "share": share, "Xn": Xn, "flat": flat, "w": w,
                "r": r}

    def dense_modes(self, table: dict) -> np.ndarray:
        """``Z`` (active nodes, :attr:`size`, 3): every mode's vector at every active node of ``table``."""
        a_c, A_c = basis(self.affine)
        nodes, S = table["nodes"], self.stride
        Z = np.zeros((nodes.size, self.size, 3))
        rows = np.arange(nodes.size)
        for q in range(NODE_GROUPS):
            s, g = table["node_share"][:, q], table["node_group"][:, q]
            y = (table["Xn"] - table["centre"][g]) / table["radius"][g, None]
            vals = s[:, None, None] * (a_c[None] + np.einsum("cij,nj->nci", A_c, y))
            for j in range(S):  # a node holds each group once: the (row, column) pairs of one q are distinct
                Z[rows, g * S + j] += vals[:, j]
        return Z

    def device_table(self, table: dict, capacity: int | None = None) -> dict:
        """The table's arrays on the model's device for the restriction and prolongation kernels: ``nodes``,
        ``node_group``, ``node_share``, ``centre``, ``inv_len`` (padded with empty nodes to ``capacity``)."""
        d = self.model.device
        na = table["nodes"].size
        pad = (capacity or na) - na
        return {"nodes": wp.array(np.r_[table["nodes"], np.zeros(pad, dtype=np.int64)].astype(np.int32), dtype=int, device=d),
                "node_group": wp.array(np.r_[table["node_group"], np.zeros((pad, NODE_GROUPS), dtype=np.int32)], dtype=int, device=d),
                "node_share": wp.array(np.r_[table["node_share"], np.zeros((pad, NODE_GROUPS))].astype(np.float32), dtype=float, device=d),
                "centre": wp.array(table["centre"].astype(np.float32), dtype=wp.vec3, device=d),
                "inv_len": wp.array((1.0 / table["radius"]).astype(np.float32), dtype=float, device=d)}
