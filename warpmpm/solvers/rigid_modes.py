"""Rigid-mode acceleration of the explicit relaxation: a two-level mass matrix for stiff organs on a soft one.

Why. Mass scaling (:attr:`ExplicitConfig.mass_scaling <warpmpm.solvers.config.ExplicitConfig.mass_scaling>`) gives every
material the stiffest one's wave speed, so the time step is that of the softest: each organ's density becomes
proportional to its modulus. The duodenum (2,900x the pancreas's shear modulus) then weighs 2,900x the pancreas per
volume, and its motions on the soft pancreas, held by a few driven particles, are the slowest modes of the scene by
far (on the resolution-3 phantom the slowest swings at ``omega dt`` 0.009, 13x below the slowest deformation of the
body ``pi c / L``): a frame needs thousands of steps to settle, and the settled rule can be fooled by a motion too
slow to register (docs/decisions/2026-12-03-solver-defaults.md).

What. The grid update's velocity change ``dv = M^-1 f dt`` becomes ::

    dv = (M^-1 + Z B Z^T) f dt

with ``Z`` the six rigid motions (three translations, three rotations about the group's centre divided by its radius
of gyration ``L_g``; or twelve affine ones) of every *group* of particles on the grid nodes, each weighed by the
group's share of the node's mass, and ``B = Phi diag(beta_j - 1) Phi^T`` from the coarse eigenproblem ::

    E Phi = M_c Phi diag(omega_j^2),   E = Z^T K Z,   M_c = Z^T M Z,   Phi^T M_c Phi = I

(``K``: the small-strain stiffness of the particles on the grid plus the drive's spring, the operator of
:mod:`warpmpm.solvers.quasistatic`; ``M``: the nodal masses), ``beta_j = omega_t^2 / omega_j^2`` for the modes slower than the
target ``omega_t`` and 1 for the others. Coarse mode ``j`` then accelerates as if its mass were ``1 / beta_j`` of what
it is: it swings at ``omega_t`` instead of ``omega_j``, and the adaptive damping (:attr:`ExplicitConfig.damping_rule
<warpmpm.solvers.config.ExplicitConfig.damping_rule>`) brings it to rest with the rest of the body. A group is a cube of about
``aggregate_mm`` of one organ (:func:`aggregate_groups`): with whole organs as groups a stiff organ's bending is still
slow; with 25 mm cubes the default phantom settles in 1,700 steps instead of 4,700, and in 1,100 when each cube
moves with its 12 affine motions (:attr:`AccelerationConfig.basis <warpmpm.solvers.config.AccelerationConfig.basis>`;
but more work a step, so about the same time a frame: not the default; docs/decisions/2026-12-03-solver-defaults.md).

What it does not change. The equilibrium: where the force vanishes, so does the correction (it preconditions the
relaxation, it is not physics). Stability: the eigenvalues of the preconditioned stiffness ``(M^-1 + Z B Z^T) K``
exceed those of ``M^-1 K`` by at most ``max_j (beta_j - 1) omega_j^2 <= omega_t^2`` (Weyl's inequality), so with
``omega_t dt`` far below the explicit limit 2 the step stays stable at the same time step. ``f`` is the step's own
force impulse (stress and drive), scattered apart from the momentum by :func:`warpmpm.solvers.explicit_kernels.p2g`; ``E`` and ``M_c``
are assembled particle by particle from the same stencils (:meth:`RigidModeAccelerator.build`), so restriction,
prolongation and coarse matrix are one consistent ``Z``.

When. :class:`warpmpm.driving.SliceDrivenEstimator` builds the coarse level once the driven slice has arrived (the
residual rule that ends a frame by default has held) and runs it until the body has settled: while the drive still
saturates, a boosted mode would be thrown by it. A scene whose slowest coarse mode is within 10x of the body's pace gets none
(:data:`MIN_BOOST`; no extra work a step). A guard on the device (:func:`coarse_guard`) switches it off for the rest of the frame when its
velocity change grows like an instability; this happened under the paper protocol's 12 mm slice motion on the
default phantom, where the coarse matrices were right (checked against finite differences of the nonlinear force)
but the coarse level still grew 1.3-2x a step after ~200 steps: a coupling with the fine modes of a strongly deformed
body that the linear bound above does not cover. The frame then goes on without it (``DriveResult.acceleration`` and a
warning say so).

Sticky contact only (one grid velocity field), like the quasi-static solver.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..errors import InputError
from . import parallel
from .coarse_space import AGGREGATE_MM, NODE_GROUPS, CoarseSpace, aggregate_groups, basis
from .config import RIGID_MODE_BASES
from .grid import MPMModel, State, cpu_threads
from .rigid_modes_kernels import (SLOTS, coarse_expand, coarse_guard, coarse_project, energy_blocks, prolong_velocity,
                                  reduce_slots, restrict_force)

__all__ = ["RigidModeAccelerator", "TARGET_FACTOR", "MAX_BOOST", "MIN_BOOST", "GUARD_GROWTH", "GUARD_STEPS"]

#: the target frequency of the coarse modes, ``omega_t = TARGET_FACTOR * pi c / L`` (c: the scaled wave speed the time
#: step uses; L: the scene's largest extent): the slowest deformation of the body, so a coarse mode is brought up to the
#: body's own pace (measured with whole organs as groups on the resolution-3 phantom: 2 and 4 gave 1,300 steps against
#: 1,500; a target from the shear wave speed instead, 25 mm cubes: 3,100 steps against 800)
TARGET_FACTOR = 1.0

#: the largest boost of a coarse mode (a mode with no stiffness at all, a group nothing holds, would get an infinite
#: one; its force is zero, so the cap only keeps rounding noise from being amplified without bound)
MAX_BOOST = 1.0e4

#: the coarse level runs only when its slowest mode needs at least this boost (is 10x slower than the body's slowest
#: deformation): the stiff-inclusion case it is for. A soft block alone has coarse modes needing at most ~40 and gained
#: no steps from them (FEM blocks, settled: 400-700 steps either way, at 1.3-1.5x the time).
MIN_BOOST = 100.0

#: the guard against an unstable coarse level: the coarse velocity change growing by more than ``GUARD_GROWTH`` a step
#: for ``GUARD_STEPS`` steps in a row switches the correction off for the rest of the frame. A boosted mode swings at
#: ``omega_t`` (``omega_t dt`` 0.04 on the default phantom), so its force changes by a few % a step; 20 % a step for 6
#: steps is an instability (the paper protocol's 12 mm slice motion on the default phantom: docs/decisions/2026-12-03-solver-defaults.md).
GUARD_GROWTH = 1.2
GUARD_STEPS = 6



class RigidModeAccelerator:
    """The coarse level of the relaxation (module docstring) for one :class:`MPMModel`; :meth:`build` it for a
    frame's drive, then :meth:`correct` adds its velocity change in every step (:meth:`MPMSolver.step
    <warpmpm.solvers.explicit.MPMSolver.step>` calls it between the grid update and G2P).

    ``modes``: ``"rigid"`` (6 a group) or ``"affine"`` (12); ``aggregate_mm``: the cubes organs are cut into (None:
    whole organs); ``target_factor``: :data:`TARGET_FACTOR`.

    Attributes after :meth:`build`: ``frequencies_per_s`` (the coarse modes' own ``omega_j``), ``boosts``
    (``beta_j``), ``mode_shapes`` (``Phi``: their coefficients on the groups' motions, ``Phi^T M_c Phi = I``),
    ``coarse`` (what :meth:`coarse_matrices` returned for the build), ``target_per_s`` (``omega_t``); :meth:`switched_off_after` (the guard, :data:`GUARD_GROWTH`); ``layout`` (increases whenever the device arrays were re-allocated:
    a captured graph that launched the old ones must be captured again)."""

    def __init__(self, model: MPMModel, target_factor: float = TARGET_FACTOR, modes: str = "rigid",
                 aggregate_mm: float | None = AGGREGATE_MM):
        if model.n_fields > 1:
            raise InputError("the rigid-mode acceleration handles sticky contact only (one grid field); use "
                             "ExplicitConfig(contact='sticky') or turn it off (AccelerationConfig(mode='off'))")
        if not (isinstance(target_factor, (int, float)) and math.isfinite(target_factor) and target_factor > 0):
            raise InputError(f"rigid-mode target factor must be a finite number > 0, got {target_factor!r}")
        if modes not in RIGID_MODE_BASES:
            raise InputError(f"rigid-mode acceleration modes must be one of {', '.join(RIGID_MODE_BASES)}, got {modes!r}")
        self.model = model
        #: the group of each particle whose motions form the coarse space
        self.groups = aggregate_groups(model.particles, aggregate_mm)
        #: the coarse space: the groups' rigid or affine motions on the grid (shared with the quasi-static solver)
        self.space = CoarseSpace(model, self.groups, modes)
        self.n_groups = self.space.n_groups
        self.affine = self.space.affine
        self.stride = self.space.stride
        self.target_factor = float(target_factor)
        size_m = float(np.max(np.ptp(model.particles.positions_mm, axis=0))) * 1e-3
        #: the coarse modes' target frequency (rad/s): the slowest deformation of the body, ``pi c / L``
        self.target_per_s = self.target_factor * math.pi * model.wave_speed_m_s / max(size_m, 10 * model.dx_mm * 1e-3)
        self.frequencies_per_s = np.zeros(0)
        self.boosts = np.zeros(0)
        self.mode_shapes = np.zeros((0, 0))
        self.coarse: dict = {}
        self.layout = 0
        self._capacity = 0
        self._built = False
        self._active = False
        d = model.device
        k = self.stride * self.n_groups
        #: CPU threads the coarse kernels split over (those of the solver's step)
        self.threads = cpu_threads(model.config, d)
        self.n_boosted = 0
        self._W = wp.zeros((k, k), dtype=float, device=d)  # the boosted modes' shapes, first n_boosted columns
        self._WT = wp.zeros((k, k), dtype=float, device=d)  # the same, as rows
        self._boost = wp.zeros(k, dtype=float, device=d)  # their beta - 1
        self._h = wp.zeros(k, dtype=float, device=d)
        self._slots = wp.zeros((k, SLOTS * self.threads), dtype=float, device=d)
        self._g = wp.zeros(k, dtype=float, device=d)
        self._y = wp.zeros(k, dtype=float, device=d)
        self._centre = wp.zeros(self.n_groups, dtype=wp.vec3, device=d)
        self._inv_len = wp.zeros(self.n_groups, dtype=float, device=d)
        self._dx = model.dx_mm * 1e-3
        self._guard = wp.zeros(5, dtype=float, device=d)

    @property
    def built(self) -> bool:
        return self._built

    @property
    def active(self) -> bool:
        """Built, with a coarse mode that needs at least :data:`MIN_BOOST` (otherwise the scene's coarse modes keep up
        with the body well enough, and its steps skip the force scatter and the coarse kernels)."""
        return self._built and self._active

    def coarse_matrices(self, state: State, driven: np.ndarray, axes: np.ndarray, spring_per_s2: float) -> dict:
        """The coarse space at ``state``: the node table (active nodes, their groups and shares), the groups' centres and
        radii, and the matrices ``E = Z^T K Z`` (N/m) and ``M_c = Z^T M Z`` (kg) over the groups' modes (``stride``
        per group, in group order). ``spring_per_s2``: the drive's spring per kg of each driven particle (the PD
        drive's ``Kp``) along ``axes`` (n_driven, 3, 3) of the ``driven`` particles."""
        m = self.model
        dx = self._dx
        G, S = self.n_groups, self.stride
        K = G * S
        nn = int(np.prod(m.grid_shape))
        mass = m.mass_kg.astype(np.float64)
        n = m.n
        t = self.space.table(state.x)
        nodes, node_pos, group_of, share = t["nodes"], t["node_pos"], t["group_of"], t["share"]
        node_group, node_share, node_mass, Xn = t["node_group"], t["node_share"], t["node_mass"], t["Xn"]
        centre, radius, flat, w, r = t["centre"], t["radius"], t["flat"], t["w"], t["r"]
        na = nodes.size
        a_c, A_c = basis(self.affine)
        # M_c: per (node, group) the mode values Z = s (a + A y); pairs of groups at a node
        y_ng = (Xn[node_pos] - centre[group_of]) / radius[group_of, None]
        Zv = share[:, None, None] * (a_c[None] + np.einsum("cij,nj->nci", A_c, y_ng))  # (entries, S, 3)
        Mc = self._pair_sum(node_pos, group_of, Zv, Zv, node_mass[node_pos], K)
        # E: per (particle, group) the moments of the group's share over the particle's stencil
        pos_of_node = np.full(nn, -1, dtype=np.int64)
        pos_of_node[nodes] = np.arange(na)
        npos = pos_of_node[flat]  # (n, 27)
        rows_p, rows_k, rows_q = [], [], []
        for q in range(NODE_GROUPS):
            s_q = node_share[npos, q]
            p_i, k_i = np.nonzero(s_q > 0)
            rows_p.append(p_i)
            rows_k.append(k_i)
            rows_q.append(np.full(p_i.size, q))
        rp, rk, rq = (np.concatenate(v) for v in (rows_p, rows_k, rows_q))
        na_i = npos[rp, rk]
        g_r = node_group[na_i, rq].astype(np.int64)
        s_r = node_share[na_i, rq] * w[rp, rk]
        y_r = (Xn[na_i] - centre[g_r]) / radius[g_r, None]
        off = r[rp, rk]
        pkey, pinv = np.unique(rp * G + g_r, return_inverse=True)
        pinv = pinv.ravel()
        ne = pkey.size

        def moment(vals):
            return np.bincount(pinv, weights=vals, minlength=ne)

        n0 = moment(s_r)
        n1 = np.stack([moment(s_r * y_r[:, c]) for c in range(3)], axis=1)
        m0 = np.stack([moment(s_r * off[:, c]) for c in range(3)], axis=1)
        m1 = np.stack([np.stack([moment(s_r * y_r[:, i] * off[:, j]) for j in range(3)], axis=1) for i in range(3)], axis=1)
        u = a_c[None] * n0[:, None, None] + np.einsum("cij,ej->eci", A_c, n1)  # (ne, S, 3)
        c4 = 4.0 / dx**2
        Gm = c4 * (a_c[None, :, :, None] * m0[:, None, None, :] + np.matmul(A_c[None], m1[:, None]))  # (ne, S, 3, 3)
        p_e = pkey // G
        g_e = pkey % G
        vol = m.vol0.numpy().astype(np.float64)[p_e]
        mu = m.mu.numpy().astype(np.float64)[p_e]
        lam = m.lam.numpy().astype(np.float64)[p_e]
        pen = np.zeros(n)
        P = np.zeros((n, 3, 3))
        driven = np.asarray(driven, dtype=np.int64)
        pen[driven] = spring_per_s2 * mass[driven]
        P[driven] = np.asarray(axes, dtype=np.float64)
        # E = sum_p Q_p^T Q_p with Q_p (10 rows a particle) the square root of its energy: strain components weighed
        # by sqrt(2 mu V) (diagonal) and sqrt(4 mu V) (off-diagonal, counted twice), the trace by sqrt(lambda V), the
        # driven directions by sqrt(spring) (a projector P: (P u).(P u) = u.P u)
        eps = 0.5 * (Gm + np.swapaxes(Gm, 2, 3))
        sd = np.sqrt(2.0 * mu * vol)[:, None]
        so = np.sqrt(4.0 * mu * vol)[:, None]
        Q = np.empty((ne, 10, S))
        Q[:, 0], Q[:, 1], Q[:, 2] = sd * eps[:, :, 0, 0], sd * eps[:, :, 1, 1], sd * eps[:, :, 2, 2]
        Q[:, 3], Q[:, 4], Q[:, 5] = so * eps[:, :, 0, 1], so * eps[:, :, 0, 2], so * eps[:, :, 1, 2]
        Q[:, 6] = np.sqrt(lam * vol)[:, None] * np.trace(Gm, axis1=2, axis2=3)
        Q[:, 7:10] = np.sqrt(pen[p_e])[:, None, None] * np.einsum("eab,ecb->eac", P[p_e], u)
        order = np.argsort(p_e, kind="stable")
        p_sorted = p_e[order]
        starts = np.r_[0, np.flatnonzero(np.diff(p_sorted)) + 1]
        cnt = np.diff(np.r_[starts, p_sorted.size])
        E = self._sum_energy_blocks(Q, order, starts, cnt, g_e, K)
        E = 0.5 * (E + E.T)
        return {"nodes": nodes, "node_group": node_group, "node_share": node_share, "centre": centre, "radius": radius,
                "E": E, "Mc": Mc, "node_mass": node_mass}

    def _sum_energy_blocks(self, Q: np.ndarray, order: np.ndarray, starts: np.ndarray, counts: np.ndarray, group: np.ndarray,
                           K: int) -> np.ndarray:
        """``E = sum_p Q_p^T Q_p`` (K, K) from the (particle, group) entries' energy rows ``Q`` (entries, 10, stride),
        the entries sorted by particle and, within one, by group (``order``), each particle's first sorted entry and
        count: :func:`energy_blocks` over the particles, split over the solver's CPU threads (a copy each, summed;
        float64). Replaces a batched NumPy product per particle: 2.1 -> 1.2 s (rigid) and 3.5 -> 2.6 s (affine) on the
        default phantom, same matrix within 5e-15."""
        d = self.model.device
        parts = parallel.split(starts.size, cpu_threads(self.model.config, d))
        Qw = wp.array(np.ascontiguousarray(Q), dtype=wp.float64, device=d)
        ow = wp.array(order.astype(np.int32), dtype=int, device=d)
        sw = wp.array(starts.astype(np.int32), dtype=int, device=d)
        cw = wp.array(counts.astype(np.int32), dtype=int, device=d)
        gw = wp.array(group.astype(np.int32), dtype=int, device=d)
        outs = [wp.zeros((K, K), dtype=wp.float64, device=d) for _ in parts]
        parallel.run_together(
            lambda k=k, lo=lo, hi=hi: wp.launch(energy_blocks, hi - lo, [sw, cw, ow, gw, Qw, self.stride, lo, outs[k]], device=d)
            for k, (lo, hi) in enumerate(parts))
        U = outs[0].numpy()
        for o in outs[1:]:
            U = U + o.numpy()
        E = U + U.T
        S = self.stride
        for g in range(K // S):  # the diagonal blocks (a group with itself) were added whole, once
            E[g * S:(g + 1) * S, g * S:(g + 1) * S] -= U[g * S:(g + 1) * S, g * S:(g + 1) * S]
        return E

    @staticmethod
    def _pair_sum(node_pos, group_of, Za, Zb, weight, K):
        """``sum over nodes of weight * Za(g1)^T Zb(g2)`` for every pair of groups at a node, as a (K, K) matrix."""
        S = Za.shape[1]
        order = np.argsort(node_pos, kind="stable")
        ns = node_pos[order]
        starts = np.r_[0, np.flatnonzero(np.diff(ns)) + 1]
        cnt = np.diff(np.r_[starts, ns.size])
        idx_all, val_all = [], []
        ar = np.arange(S)
        for c in np.unique(cnt):
            ent = order[starts[cnt == c][:, None] + np.arange(c)[None]]
            for i1 in range(c):
                for i2 in range(c):
                    ea, eb = ent[:, i1], ent[:, i2]
                    val = weight[ea, None, None] * (Za[ea] @ np.swapaxes(Zb[eb], 1, 2))
                    idx_all.append((((group_of[ea] * S)[:, None, None] + ar[None, :, None]) * K + (group_of[eb] * S)[:, None, None]
                                    + ar[None, None, :]).ravel())
                    val_all.append(val.ravel())
        out = np.bincount(np.concatenate(idx_all), weights=np.concatenate(val_all), minlength=K * K)
        out = out.reshape(K, K)
        return 0.5 * (out + out.T)

    def build(self, state: State, driven: np.ndarray, axes: np.ndarray, spring_per_s2: float) -> None:
        """The coarse space and its boost for the particles at ``state`` under the frame's drive (see
        :meth:`coarse_matrices`), uploaded for :meth:`correct`."""
        c = self.coarse_matrices(state, driven, axes, spring_per_s2)
        E, Mc = c["E"], c["Mc"]
        S, G = self.stride, self.n_groups
        K = S * G
        # E phi = omega^2 Mc phi through the Cholesky factor of Mc (positive definite: every group has mass on its nodes)
        Lc = np.linalg.cholesky(Mc)
        Li = np.linalg.inv(Lc)
        w2, V = np.linalg.eigh(Li @ E @ Li.T)
        Phi = Li.T @ V
        w2 = np.maximum(w2, 0.0)
        target2 = self.target_per_s**2
        boosts = np.where(w2 < target2, np.minimum(target2 / np.maximum(w2, 1e-300), MAX_BOOST), 1.0)
        boosted = np.flatnonzero(boosts > 1.0)
        self.frequencies_per_s = np.sqrt(w2)
        self.boosts = boosts
        self.mode_shapes = Phi
        self.coarse = c
        self._active = bool(boosts.max() >= MIN_BOOST)
        d = self.model.device
        na = c["nodes"].size
        if na > self._capacity:  # room for the table to grow by a fifth before the arrays (and a graph) change
            self._capacity = int(math.ceil(na * 1.2))
            self._nodes = wp.zeros(self._capacity, dtype=int, device=d)
            self._node_group = wp.zeros((self._capacity, NODE_GROUPS), dtype=int, device=d)
            self._node_share = wp.zeros((self._capacity, NODE_GROUPS), dtype=float, device=d)
            self.layout += 1
        pad = self._capacity - na
        self._nodes.assign(np.r_[c["nodes"], np.zeros(pad, dtype=np.int64)].astype(np.int32))
        self._node_group.assign(np.r_[c["node_group"], np.zeros((pad, NODE_GROUPS), dtype=np.int32)])
        self._node_share.assign(np.r_[c["node_share"], np.zeros((pad, NODE_GROUPS))].astype(np.float32))
        self._centre.assign(c["centre"].astype(np.float32))
        self._inv_len.assign((1.0 / c["radius"]).astype(np.float32))
        # B = Phi_b diag(beta_b - 1) Phi_b^T over the boosted modes only: two thin products a step instead of a dense
        # K x K one (66 of 516 modes boosted on the default phantom, 206 of 1,032 with affine motions)
        self.n_boosted = int(boosted.size)
        W = np.zeros((K, K), dtype=np.float32)
        W[:, :boosted.size] = Phi[:, boosted]
        beta1 = np.zeros(K, dtype=np.float32)
        beta1[:boosted.size] = boosts[boosted] - 1.0
        self._W.assign(W)
        self._WT.assign(np.ascontiguousarray(W.T))
        self._boost.assign(beta1)
        # each thread's nodes, boosted modes and coarse rows for :meth:`correct` (fixed until the next build)
        self._ranges = tuple(parallel.split(n, self.threads) for n in (self._capacity, self.n_boosted, K))
        self._slots.zero_()
        self._guard.assign(np.array([0.0, 0.0, 1.0, -1.0, 0.0]))
        self._built = True

    def suspend(self) -> None:
        """Stop correcting until the next :meth:`build` (a new frame starts without the coarse level)."""
        self._active = False

    def correct(self, force_sum: wp.array, damping: wp.array, grid_v: wp.array) -> None:
        """Add ``damping Z B Z^T f`` to the grid velocities (``force_sum``: the step's nodal force impulse, N s). On the
        CPU the restriction, the two thin products and the prolongation are each split over :attr:`threads` (disjoint
        nodes, rows or modes; the restriction into a band of slots per thread); one launch each on CUDA or while a
        graph is captured."""
        if not self.active:
            return
        d = self.model.device
        a = int(self.affine)
        k = self._g.shape[0]
        nb = self.n_boosted
        whole = wp.get_device(d).is_capturing  # a captured graph must hold whole-array launches
        nodes, modes, rows = ([(0, self._capacity)], [(0, nb)], [(0, k)]) if whole else self._ranges

        def split(ranges, launch):
            parallel.run_together(lambda t=t, lo=lo, hi=hi: launch(t, lo, hi) for t, (lo, hi) in enumerate(ranges))

        split(nodes, lambda t, lo, hi: wp.launch(
            restrict_force, hi - lo, [self._nodes, self._node_group, self._node_share, self._centre, self._inv_len, force_sum,
                                      self._dx, a, lo, t * SLOTS, self._slots], device=d))
        wp.launch(reduce_slots, k, [self._slots, self._g], device=d)
        split(modes, lambda t, lo, hi: wp.launch(coarse_project, hi - lo, [self._WT, self._boost, self._g, lo, self._h], device=d))
        split(rows, lambda t, lo, hi: wp.launch(coarse_expand, hi - lo, [self._W, self._h, nb, lo, self._y], device=d))
        wp.launch(coarse_guard, 1, [self._y, self._guard, GUARD_GROWTH, float(GUARD_STEPS)], device=d)
        split(nodes, lambda t, lo, hi: wp.launch(
            prolong_velocity, hi - lo, [self._nodes, self._node_group, self._node_share, self._centre, self._inv_len, self._y,
                                        damping, self._dx, a, self._guard, lo, grid_v], device=d))

    def switched_off_after(self) -> int | None:
        """Steps since :meth:`build` after which the guard switched the correction off (reads the device); None: it did
        not."""
        g = self._guard.numpy()
        return None if g[2] > 0.0 or not self._built else int(g[3])
