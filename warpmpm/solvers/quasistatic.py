"""A quasi-static solve of the MPM equilibrium: Newton iterations on the grid, each a matrix-free
preconditioned conjugate-gradient solve (implicit MPM with an infinite time step).

The estimate of a frame is an equilibrium, not a trajectory. The explicit solver reaches it by dynamic
relaxation, which needs thousands of steps before a whole abdomen stops moving (~8,000 on the phantom);
this module finds it directly. The unknown is a displacement ``u_i`` of every grid node the particles
touch; a particle moves by ``sum_i w_ip u_i`` and its deformation gradient becomes
``F_p <- (I + G_p u) F_p`` with the MLS-MPM gradient ``G_p u = 4/dx^2 sum_i w_ip u_i (x_i - x_p)^T`` that
the explicit step uses for its affine velocity (so the two solvers share their discrete physics). Newton
iteration k solves ::

    (K + k_reg M) du = f_int(F) + f_drive        then moves the particles by du

where

* ``f_int,i = -sum_p w_ip 4/dx^2 V0_p tau_p (x_i - x_p)`` is the explicit step's internal force, with the
  fixed-corotated Kirchhoff stress ``tau`` of the current ``F`` (the exact nonlinear residual, so the answer is
  the nonlinear equilibrium);
* ``K = G^T C G`` the small-strain stiffness (``C``: the isotropic elasticity tensor of each particle's Lame
  parameters): the Hessian at rest, symmetric positive semi-definite, applied particle by particle
  (:func:`apply_stiffness`), never assembled;
* the drive is a spring ``k_p |P_p (x_p - t_p)|^2 / 2`` on every driven particle (``P_p`` the projector of the
  directions the slice drives, ``k_p = penalty * (lambda + 2 mu) V0 4/dx^2``): by default the spring of the explicit
  settled mode's PD drive, so both solvers seek the same equilibrium; with ``exact_drive`` an augmented-Lagrangian
  multiplier, updated after every iteration, takes the driven particles exactly onto their targets;
* ``k_reg M`` a mass-proportional regularisation (an implicit pseudo-time step, Levenberg-Marquardt): a node at a
  stencil's fringe and a part of the body that nothing holds (an organ touching nothing) stay where they are
  instead of making the system singular; it slows the softest modes and never moves the equilibrium.

The conjugate gradient is this module's own (Warp's ``warp.optim.linear.cg`` spent ~76 ms an iteration on the CPU
around a 0.2 ms operator on a 1,100-particle block, in launches and host round trips); every scalar of its recurrence
stays on the device, in float64. Its preconditioner has two levels: Jacobi (the diagonal of ``K``) plus a coarse
correction over each organ's six rigid motions (``QuasiStaticConfig.coarse_modes``), whose 6 x organs matrix
``Z^T A Z`` is built when a Newton iteration's solve has not converged after ``COARSE_AFTER`` Jacobi iterations (one
operator application a mode; a frame that starts near its equilibrium never needs it). The coarse level carries
what Jacobi cannot: stiff organs swinging on the soft pancreas (on the phantom after the slice has arrived,
30-100 CG iterations a Newton step instead of the 300-iteration cap).

A Newton step is cut so that no particle moves more than ``max_move_cells`` or deforms more than
``max_strain_step``; the regularisation adapts (Levenberg-Marquardt: a quarter after a full step, four times after
a cut one). A frame has settled when an iteration moves no particle by more than ``settle_mm`` and the decay of
the moves says no more than that is to come (with ``exact_drive`` also: the driven particles within
``drive_tol_mm`` of their targets, RMS).

Only sticky contact (one grid velocity field) is solved this way; sliding contact is refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..errors import InputError, SimulationError
from . import explicit_kernels as kernels
from . import parallel
from .coarse_space import CoarseSpace
from .coarse_space_kernels import prolong_nodes, restrict_nodes
from .config import QuasiStaticConfig
from .grid import MPMModel, State, cpu_threads
from .quasistatic_kernels import (DOT_SLOTS, RZ, RZ_LAST, RZ_NEXT, add_copies, apply_stiffness, cg_advance,
                                  cg_direction, cg_dot, cg_next, cg_reduce, cg_start, coarse_solve, finish_matvec,
                                  internal_and_drive_forces, inverse_diagonal, move_particles, update_multipliers)

__all__ = ["QuasiStaticConfig", "QuasiStaticResult", "QuasiStaticSolver"]

#: range of the adaptive regularisation, as multiples of ``QuasiStaticConfig.regularization``
REG_RANGE = (1e-2, 1e2)

#: Jacobi-only conjugate-gradient iterations before the coarse level is built (``coarse_modes="rigid"``)
COARSE_AFTER = 20

#: conjugate-gradient iterations between two host reads of the residual
CG_CHECK_EVERY = 10


@dataclass
class QuasiStaticResult:
    """What one quasi-static solve did: Newton iterations, conjugate-gradient iterations in all, the largest
    particle move of the last iteration and the driven RMS residual (mm) after each iteration."""

    newton_iterations: int
    cg_iterations: int
    settled: bool
    max_move_mm: float
    rms_history_mm: list = field(default_factory=list)
    move_history_mm: list = field(default_factory=list)


def grid_view(nodes: wp.array, ny: int, nz: int) -> wp.array:
    """A flat node array (index :func:`node_index`) as the (nx, ny, nz) array it is laid out as: a view, no copy (the
    gathers read nodes by their three indices, :func:`warpmpm.solvers.explicit_kernels.gather_velocity`)."""
    return nodes.reshape((nodes.shape[0] // (ny * nz), ny, nz))


class QuasiStaticSolver:
    """Newton / conjugate-gradient equilibrium of an :class:`MPMModel` under a slice drive (module docstring).

    ``solve(state, driven, targets_mm, axes)`` moves ``state`` (positions and deformation gradients) to the
    equilibrium in place; velocities stay zero."""

    def __init__(self, model: MPMModel, config: QuasiStaticConfig | None = None):
        if model.n_fields > 1:
            raise InputError("the quasi-static solver handles sticky contact only (one grid field); use "
                             "ExplicitConfig(contact='sticky') or the explicit solver for sliding contact")
        self.model = model
        self.config = config or QuasiStaticConfig()
        d = model.device
        nx, ny, nz = model.grid_shape
        self.n_nodes = nx * ny * nz
        self._ny, self._nz = ny, nz
        self._dx = model.dx_mm * 1e-3
        nn, n = self.n_nodes, model.n
        #: threads of the particle kernels of an iteration (the explicit step's, :func:`warpmpm.solvers.grid.cpu_threads`); a
        #: split kernel scatters into a copy of its node arrays per thread, a split move flags its own status
        self.threads = cpu_threads(model.config, d)
        self._ranges = parallel.split(n, self.threads)
        self.threads = len(self._ranges)
        self._views = parallel.ChunkViews(self._ranges)
        copies = nn * self.threads
        self._force_copies = wp.zeros(copies, dtype=wp.vec3, device=d)
        self._diag_copies = wp.zeros(copies, dtype=wp.vec3, device=d)
        self._mass_copies = wp.zeros(copies, dtype=float, device=d)
        self.force, self.diag, self.node_mass = (a[:nn] for a in (self._force_copies, self._diag_copies, self._mass_copies))
        self.inv_diag = wp.zeros(nn, dtype=wp.vec3, device=d)
        # regularisation k_reg M: at a node full of particles it is ``regularization`` times their stiffness scale
        # (M 4 c^2 / dx^2 ~ (lambda + 2 mu) V 4 / dx^2 under mass scaling); at a stencil's fringe, where a node carries
        # little weight, it dominates (mass ~ w, stiffness ~ w^2), so such nodes cannot swing far
        self._k_reg = self.config.regularization * 4.0 * model.wave_speed_m_s**2 / self._dx**2
        self.du = wp.zeros(nn, dtype=wp.vec3, device=d)
        self._r = wp.zeros(nn, dtype=wp.vec3, device=d)
        self._z = wp.zeros(nn, dtype=wp.vec3, device=d)
        self._p = wp.zeros(nn, dtype=wp.vec3, device=d)
        self._Ap_copies = wp.zeros(nn * self.threads, dtype=wp.vec3, device=d)
        self._Ap = self._Ap_copies[:nn]
        self._du3, self._p3, self._r3, self._Ap3 = (grid_view(a, ny, nz) for a in (self.du, self._p, self._r, self._Ap_copies))
        self._scalars = wp.zeros(6, dtype=wp.float64, device=d)
        self._partial = wp.zeros((6, DOT_SLOTS), dtype=wp.float64, device=d)
        self.pen_k = wp.zeros(n, dtype=float, device=d)
        self.pen_P = wp.zeros(n, dtype=wp.mat33, device=d)
        self.target = wp.zeros(n, dtype=wp.vec3, device=d)
        self.multiplier = wp.zeros(n, dtype=wp.vec3, device=d)
        self.move = wp.zeros(n, dtype=float, device=d)
        self.strain = wp.zeros(n, dtype=float, device=d)
        self._err2 = wp.zeros(1, dtype=float, device=d)
        self._status_parts = [wp.array(np.array([0, 2**31 - 1], dtype=np.int32), dtype=int, device=d) for _ in range(self.threads)]
        self.status = self._status_parts[0]
        self._x_min = 1.0 * self._dx
        self._x_max = wp.vec3(*[(s - 2.0) * self._dx for s in model.grid_shape])
        lam = model.particles.per_particle("lam_pa")
        mu = model.particles.per_particle("mu_pa")
        self._stiffness = (lam + 2 * mu) * model.particles.volume_mm3 * 1e-9 * 4.0 / self._dx**2  # N/m per particle
        self._state = None
        #: the coarse space of the two-level preconditioner: each organ's rigid motions
        self.coarse_space = CoarseSpace(model, np.unique(model.particles.organ_index, return_inverse=True)[1].ravel(), "rigid")
        self._coarse = None

    def _conjugate_gradient(self, state: State, k_reg: float, max_iterations: int) -> tuple[int, bool]:
        """Solve ``(K + k_reg M) du = force`` by preconditioned CG (``du`` starts at zero): the iterations it took and
        whether it reached ``cg_tolerance``.

        Every scalar of the recurrence stays on the device (each kernel reads ``alpha`` and ``beta`` from it); the
        host reads the residual every ``CG_CHECK_EVERY`` iterations only."""
        m, cfg, d, nn = self.model, self.config, self.model.device, self.n_nodes
        sc, part = self._scalars, self._partial
        sc.zero_()
        part.zero_()
        na = self._active.shape[0]
        wp.launch(cg_start, na, [self._active, self.force, self.inv_diag, self.du, self._r, self._z, self._p, part], device=d)
        coarse = self._coarse is not None
        if coarse:
            part.zero_()
            self._coarse_correct()
            wp.launch(cg_dot, na, [self._active, self._r, self._z, self._p, RZ, 1, part], device=d)
        wp.launch(cg_reduce, 1, [part, sc], device=d)
        rz0 = float(sc.numpy()[RZ])
        if rz0 == 0.0:
            return 0, True
        # the residual in the preconditioner's norm (r . D^-1 r): each node's force weighed by its stiffness, so the
        # soft pancreas is solved as well as the ~3000x stiffer organs beside it (the plain norm is theirs alone)
        goal = cfg.cg_tolerance**2 * rz0
        sc.assign(np.array([rz0, 0.0, 0.0, 0.0, 0.0, rz0], dtype=np.float64))
        it = 0
        done = False
        while it < max_iterations:
            for _ in range(CG_CHECK_EVERY):
                self._product(state, self._p, self._p3, k_reg, part)
                wp.launch(cg_reduce, 1, [part, sc], device=d)
                wp.launch(cg_advance, na, [self._active, self.inv_diag, self._p, self._Ap, self.du, self._r, self._z, int(not coarse), sc,
                                           part],
                          device=d)
                if coarse:
                    self._coarse_correct()
                    wp.launch(cg_dot, na, [self._active, self._r, self._z, self._p, RZ_NEXT, 0, part], device=d)
                wp.launch(cg_reduce, 1, [part, sc], device=d)
                wp.launch(cg_direction, na, [self._active, self._z, self._p, sc], device=d)
                wp.launch(cg_next, 1, [sc], device=d)
                it += 1
            rz = float(sc.numpy()[RZ_LAST])
            if not math.isfinite(rz):
                raise SimulationError("quasi-static solve: the conjugate-gradient residual became non-finite")
            if rz <= goal:
                done = True
                break
        return it, done

    def _forces(self, state: State) -> None:
        """:func:`internal_and_drive_forces` into ``force``, ``diag`` and ``node_mass``, the particles split over
        :attr:`threads` (each thread's share into its own copy of the three, added by :func:`add_copies`)."""
        m, d = self.model, self.model.device
        for a in (self.force, self.diag, self.node_mass):  # the other copies were cleared when last added
            a.zero_()
        per_particle = (state.x, state.F, m.vol0, m.mu, m.lam, self.pen_k, self.pen_P, self.target, self.multiplier, m.mass)
        outs = (self._force_copies, self._diag_copies, self._mass_copies)
        if self.threads == 1:
            wp.launch(internal_and_drive_forces, m.n, [*per_particle, self._dx, self._ny, self._nz, 0, *outs], device=d)
            return
        views = [self._views(a) for a in per_particle]
        parallel.run_together(
            lambda k=k: wp.launch(internal_and_drive_forces, views[0][k].shape[0],
                                  [*(v[k] for v in views), self._dx, self._ny, self._nz, k * self.n_nodes, *outs], device=d)
            for k in range(self.threads))
        wp.launch(add_copies, self.n_nodes, [*outs, self.threads], device=d)

    def _find_active(self) -> None:
        """The nodes the particles touch (``node_mass > 0`` after :meth:`_forces`), ascending, for the conjugate
        gradient's node kernels: 7-11 % of the grid on the FEM benchmark's blocks and the default phantom. ``du`` is
        cleared everywhere (a node the body has left keeps no displacement)."""
        nodes = np.flatnonzero(self.node_mass.numpy() > 0.0).astype(np.int32)
        self._active = wp.array(nodes, dtype=int, device=self.model.device)
        self.du.zero_()

    def _product(self, state: State, v: wp.array, v3: wp.array, k_reg: float, part: wp.array) -> None:
        """``_Ap <- A v`` (:func:`apply_stiffness` then :func:`finish_matvec`; ``v3``: ``v`` as :func:`grid_view`), the
        particles split over :attr:`threads` (each thread's share scattered into its own copy of ``_Ap``)."""
        m, d = self.model, self.model.device
        self._Ap.zero_()  # the other copies were cleared when last added
        if self.threads == 1:
            wp.launch(apply_stiffness, m.n, [state.x, m.vol0, m.mu, m.lam, self.pen_k, self.pen_P, self._dx, self._ny, self._nz, v3, 0,
                                             self._Ap3], device=d)
        else:
            nx = m.grid_shape[0]
            x, vol0, mu, lam, pk, pP = (self._views(a) for a in (state.x, m.vol0, m.mu, m.lam, self.pen_k, self.pen_P))
            parallel.run_together(
                lambda k=k: wp.launch(apply_stiffness, x[k].shape[0], [x[k], vol0[k], mu[k], lam[k], pk[k], pP[k], self._dx, self._ny,
                                                                      self._nz, v3, k * nx, self._Ap3], device=d)
                for k in range(self.threads))
        wp.launch(finish_matvec, self._active.shape[0], [self._active, self._Ap_copies, self.threads, v, self.node_mass, k_reg, part], device=d)

    def _move(self, state: State, scale: float, apply: int) -> None:
        """:func:`move_particles` by ``scale du``, the particles split over :attr:`threads` (each flags its own status)."""
        d = self.model.device
        args = (self._dx, self._ny, self._nz, self._x_min, self._x_max)
        if self.threads == 1:
            wp.launch(move_particles, self.model.n, [self._du3, scale, apply, *args, state.x, state.F, self.move, self.strain, 0,
                                                     self.status], device=d)
            return
        x, F, mv, st = (self._views(a) for a in (state.x, state.F, self.move, self.strain))
        parallel.run_together(
            lambda k=k: wp.launch(move_particles, x[k].shape[0], [self._du3, scale, apply, *args, x[k], F[k], mv[k], st[k],
                                                                  self._ranges[k][0], self._status_parts[k]], device=d)
            for k in range(self.threads))

    def _coarse_correct(self) -> None:
        """``z += Z E^-1 Z^T r`` (device only; the coarse space's restriction and prolongation)."""
        d, c = self.model.device, self._coarse
        self._coarse_t.zero_()
        na = c["nodes"].shape[0]
        args = [c["nodes"], c["node_group"], c["node_share"], c["centre"], c["inv_len"]]
        geom = [self._ny, self._nz, self._dx, 0]
        wp.launch(restrict_nodes, na, args + [self._r] + geom + [self._coarse_t], device=d)
        wp.launch(coarse_solve, self.coarse_space.size, [self._coarse_E_inv, self._coarse_t, self._coarse_y], device=d)
        wp.launch(prolong_nodes, na, args + [self._coarse_y] + geom + [self._z], device=d)

    def _build_coarse(self, state: State, k_reg: float) -> None:
        """The coarse space of the two-level preconditioner (:class:`~warpmpm.solvers.coarse_space.CoarseSpace`): each
        organ's rigid motions (3 translations, 3 rotations about its centre) on the nodes its particles touch, weighed by
        its share of each node's mass; and the coarse matrix ``E = Z^T A Z`` (one matrix-vector product per mode),
        inverted on the host in float64."""
        d, nn = self.model.device, self.n_nodes
        table = self.coarse_space.table(state.x)
        nodes = table["nodes"]
        Z = self.coarse_space.dense_modes(table).astype(np.float32)  # (n_active, k, 3)
        k = Z.shape[1]
        AZ = np.empty_like(Z, dtype=np.float64)
        v = self._r  # scratch: the CG that follows starts by overwriting r; the products' sums (partial) are cleared there too
        part = self._partial
        for j in range(k):
            col = np.zeros((nn, 3), dtype=np.float32)
            col[nodes] = Z[:, j]
            v.assign(col)
            self._product(state, v, self._r3, k_reg, part)
            AZ[:, j] = self._Ap.numpy()[nodes]
        E = np.einsum("ajc,alc->jl", Z.astype(np.float64), AZ)
        E = 0.5 * (E + E.T)
        self._coarse = self.coarse_space.device_table(table)
        self._coarse_E_inv = wp.array(np.linalg.pinv(E, rcond=1e-10), dtype=wp.float64, device=d)
        self._coarse_t = wp.zeros(k, dtype=wp.float64, device=d)
        self._coarse_y = wp.zeros(k, dtype=wp.float64, device=d)

    def set_drive(self, driven: np.ndarray, targets_mm: np.ndarray, axes: np.ndarray) -> None:
        """The driven particles, their targets (world mm) and the projectors of the directions each is driven along."""
        m, n = self.model, self.model.n
        driven = np.asarray(driven, dtype=np.int64)
        k = np.zeros(n, dtype=np.float32)
        k[driven] = self.config.penalty * self._stiffness[driven]
        P = np.zeros((n, 3, 3), dtype=np.float32)
        P[driven] = axes
        t = np.zeros((n, 3), dtype=np.float32)
        t[driven] = m.to_local_m(targets_mm)
        self.pen_k.assign(k)
        self.pen_P.assign(P)
        self.target.assign(t)
        self.multiplier.zero_()
        self._driven = driven
        self._driven_wp = wp.array(driven.astype(np.int32), dtype=int, device=m.device)

    def solve(self, state: State, max_iterations: int | None = None, stop_at_cg_cap: bool = False,
              max_cg_iterations: int | None = None) -> QuasiStaticResult:
        """Newton iterations from ``state`` until it has settled (or ``max_iterations``, default
        ``max_newton_iterations``); in place. ``stop_at_cg_cap``: also stop (not settled) after the first iteration
        whose linear solve ran into its cap (``max_cg_iterations``, default the config's): ``SolverConfig(method="auto")``
        then goes on explicitly."""
        cfg, m, d = self.config, self.model, self.model.device
        self._state = state
        for a in (self._force_copies, self._diag_copies, self._mass_copies, self._Ap_copies):  # whatever an interrupted
            a.zero_()  # solve left in the extra copies (each scatter clears only the first, add_copies the others)
        state.v.zero_()
        state.C.zero_()
        state.x_carry.zero_()
        nd = len(self._driven)
        rms_hist, move_hist = [], []
        cg_total = 0
        settled = False
        max_step = cfg.max_move_cells * self._dx
        reg = 1.0  # the regularisation, a multiple of the configured one
        it = 0
        capped = False
        for it in range(1, (cfg.max_newton_iterations if max_iterations is None else int(max_iterations)) + 1):
            self._forces(state)
            self._find_active()
            k_reg = self._k_reg * reg
            wp.launch(inverse_diagonal, self._active.shape[0], [self._active, self.diag, self.node_mass, k_reg, self.inv_diag], device=d)
            # Jacobi alone first: a frame that starts near its equilibrium (a predicted tracker frame) is solved before
            # the coarse level would have been built (one operator application per mode)
            self._coarse = None
            cap = cfg.max_cg_iterations if max_cg_iterations is None else int(max_cg_iterations)
            n_cg, done = self._conjugate_gradient(state, k_reg, min(COARSE_AFTER, cap) if cfg.coarse_modes == "rigid" else cap)
            if not done and cfg.coarse_modes == "rigid" and cap > COARSE_AFTER:
                self._build_coarse(state, k_reg)
                more, done = self._conjugate_gradient(state, k_reg, cap if max_cg_iterations is None else cap - COARSE_AFTER)
                n_cg += more
            capped = not done
            cg_total += n_cg
            # the step's longest particle move (nodes at a stencil's fringe may move far: they carry almost no weight)
            self._move(state, 1.0, 0)
            longest = float(self.move.numpy().max())
            steepest = float(self.strain.numpy().max())
            if not math.isfinite(longest):
                raise SimulationError(f"quasi-static iteration {it}: the linear solve gave a non-finite displacement; "
                                      "the scene may have a collapsed element (det F <= 0)")
            scale = min(1.0, max_step / max(longest, 1e-30), cfg.max_strain_step / max(steepest, 1e-30))
            # Levenberg-Marquardt: a full step trusts the stiffness more (less regularisation), a cut one less
            reg = max(reg / 4.0, REG_RANGE[0]) if scale == 1.0 else min(reg * 4.0, REG_RANGE[1])
            self._move(state, scale, 1)
            self._check()
            self._err2.zero_()
            wp.launch(update_multipliers, nd, [self._driven_wp, state.x, self.pen_k, self.pen_P, self.target, self.multiplier,
                                               int(cfg.exact_drive), self._err2], device=d)
            rms = math.sqrt(float(self._err2.numpy()[0]) / max(nd, 1)) * 1e3
            moved = float(self.move.numpy().max()) * 1e3
            rms_hist.append(rms)
            move_hist.append(moved)
            previous = move_hist[-2] if len(move_hist) > 1 else float("inf")
            ratio = moved / previous if previous > 0 else 0.0
            remaining = moved * ratio / (1.0 - ratio) if ratio < 1.0 else float("inf")
            if moved < cfg.settle_mm and remaining < cfg.settle_mm and (rms < cfg.drive_tol_mm or not cfg.exact_drive):
                settled = True
                break
            if stop_at_cg_cap and capped:
                break
        self._state = None
        return QuasiStaticResult(it, cg_total, settled, move_hist[-1] if move_hist else 0.0, rms_hist, move_hist)

    def _check(self) -> None:
        flags = np.stack([a.numpy() for a in self._status_parts])
        code = int(flags[:, 0].max())
        if code == kernels.STATUS_OK:
            return
        particle = int(flags[flags[:, 0] > 0, 1].min())
        for a in self._status_parts:
            a.assign(np.array([0, 2**31 - 1], dtype=np.int32))
        organ = self.model.particles.organs[int(self.model.particles.organ_index[particle])]
        if code == kernels.STATUS_NONFINITE:
            raise SimulationError(f"quasi-static solve: non-finite position or deformation at particle {particle} ({organ})")
        raise SimulationError(f"quasi-static solve: particle {particle} ({organ}) would leave the simulation grid; increase "
                              f"GridConfig.margin_mm (now {self.model.config.grid.margin_mm} mm) or check the targets")
