"""The explicit MLS-MPM stepper: :class:`MPMSolver` steps ``state_in -> state_out`` of an :class:`~warpmpm.solvers.grid.MPMModel`
under an external force.

Layout follows the Newton physics engine: ``solver.step(state_in, state_out, control)`` where the
control is the per-particle external (driving) force in newtons.

Public values are physical: positions in mm (world coordinates), time steps in s, stresses in Pa,
densities in kg/m^3. Inside, kernels work in SI with positions relative to the grid origin.

Quasi-static relaxation
-----------------------
The estimate is an equilibrium, not a trajectory: with no body forces the converged positions do
not depend on the densities. ``mass_scaling`` (default on) therefore gives every material a
fictitious density ``rho = (lambda + 2 mu) / c_ref^2`` so that all organs share the wave speed
``c_ref`` of the stiffest organ: the time step stays the one the stiffest organ needs, and the soft
pancreas relaxes ~70x faster in steps than with its real density. Grid velocities are damped by a
factor ``exp(-damping_per_s * dt)`` every step (viscous damping toward rest, which does not change
the equilibrium); the default damping (``damping_factor`` 4 times ``2 pi c_s / L``) was chosen by
measurement to remove the slow swing of the least-damped mode without slowing convergence, at the
paper's stopping rule. A frame that waits for the whole body to settle damps adaptively instead
(``damping_rule``): the rate is made critical for the mode the body is moving in, measured every step
(:func:`warpmpm.solvers.explicit_kernels.stiffness_rayleigh`), which brings the body to rest 2.5-8x sooner.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..errors import InputError, SimulationError
from . import explicit_kernels as kernels
from . import parallel
from .grid import MPMModel, State, cpu_threads

__all__ = ["RAYLEIGH_SLOTS", "MPMSolver"]

#: Slots the adaptive damping's sums are spread over (by particle index): fewer atomics on one address on a GPU.
RAYLEIGH_SLOTS = 64


class MPMSolver:
    """Explicit MLS-MPM time stepper over an :class:`MPMModel`.

    ``adaptive``: whether the velocity damping adapts (:attr:`ExplicitConfig.damping_rule <warpmpm.solvers.config.ExplicitConfig.damping_rule>`); None: only under
    ``"adaptive"`` (an ``"auto"`` rule is resolved by whoever knows the stopping rule, the estimator)."""

    def __init__(self, model: MPMModel, adaptive: bool | None = None):
        self.model = model
        d = model.device
        shape = model.grid_shape
        self.fields = model.n_fields > 1
        stacked = (shape[0] * model.n_fields, shape[1], shape[2])  # the organ fields stacked along x
        #: threads of a split CPU step (:mod:`warpmpm.solvers.parallel`); each scatters into its own copy of the grid's
        #: mass and momentum (the copies stacked along x after the organ fields), which the grid update adds
        self.threads = cpu_threads(model.config, d)
        self._ranges = parallel.split(model.n, self.threads)
        self.threads = len(self._ranges)
        self._node_ranges = parallel.split(shape[0], self.threads)
        #: the grid update visits only the blocks of nodes that hold mass (:func:`warpmpm.solvers.explicit_kernels.grid_update_blocks`;
        #: sticky contact on the CPU; one thread only: on two the dense update is faster, docs/decisions/2026-12-03-solver-defaults.md)
        self._sparse_capable = not self.fields and not str(d).startswith("cuda")
        self._sparse_update = self._sparse_capable and self.threads == 1
        blocks = tuple(-(-n // kernels.BLOCK) for n in shape) if self._sparse_capable else (1, 1, 1)
        self._stamps = wp.zeros(blocks, dtype=int, device=d)
        self._updated = wp.zeros(blocks, dtype=int, device=d)
        self._block_ranges = parallel.split(blocks[0], self.threads)
        self._views = parallel.ChunkViews(self._ranges)
        copies = (stacked[0] * self.threads, stacked[1], stacked[2])
        if self.fields:  # sliding contact: mass and momentum per organ field, and the mass gradient
            self.grid_m = wp.zeros(copies, dtype=float, device=d)
            self.grid_mv = wp.zeros(copies, dtype=wp.vec3, device=d)
        else:
            #: sticky contact: each node's momentum (x, y, z, kg m/s) and mass (w, kg) side by side, so P2G adds both with
            #: one address
            self.grid_mm = wp.zeros(copies, dtype=wp.vec4, device=d)
        #: the nodes' velocities (m/s) in x, y, z (w unused: 16-byte nodes, one aligned load each in G2P)
        self.grid_v = wp.zeros(stacked, dtype=wp.vec4, device=d)
        self.grid_g = wp.zeros(copies, dtype=wp.vec3, device=d) if self.fields else None
        #: the coarse level of the relaxation (:mod:`warpmpm.solvers.rigid_modes`), set by :meth:`set_accelerator`; None: none
        self.accelerator = None
        # the step's force impulse alone (scattered copies and their sum), only while an accelerator is set
        self._grid_f = self._force_sum = wp.zeros((1, 1, 1), dtype=wp.vec3, device=d)
        self.zero_force = wp.zeros(model.n, dtype=wp.vec3, device=d)
        # one status flag per thread (a CPU "atomic" is a plain read-modify-write: two threads must not share one)
        self._status_parts = [wp.array(np.array([0, 2**31 - 1, 2**31 - 1], dtype=np.int32), dtype=int, device=d)
                              for _ in range(self.threads)]
        self.status = self._status_parts[0]
        # velocity damping factor per step, on the device so the adaptive rule can change it inside a captured graph
        self.damping = wp.array([math.exp(-model.damping_per_s * model.dt_s)], dtype=float, device=d)
        self._damping_dt = model.dt_s  # the step length the fixed factor was computed for
        self.adaptive = model.config.explicit.damping_rule == "adaptive" if adaptive is None else bool(adaptive)
        if self.adaptive:
            self._accel_prev = wp.zeros(model.n, dtype=wp.vec3, device=d)
            self._rayleigh = wp.zeros((2, RAYLEIGH_SLOTS), dtype=float, device=d)
            self._rayleigh_memory = wp.zeros(2, dtype=float, device=d)
            #: 1 for the particles whose motion measures the stiffness, 0 for the driven ones (:meth:`set_driven`)
            self.rayleigh_weight = wp.ones(model.n, dtype=float, device=d)
        self.step_count = 0
        ce = model.config.explicit.check_every
        self.check_every = ce if ce is not None else (50 if str(d).startswith("cuda") else 1)
        dx_m = model.dx_mm * 1e-3
        self._dx = dx_m
        self._x_min = 1.0 * dx_m
        self._x_max = wp.vec3(*[(s - 2.0) * dx_m for s in shape])

    @property
    def sparse_update(self) -> bool:
        """Whether the grid update visits only the node blocks that hold mass (:func:`warpmpm.solvers.explicit_kernels.grid_update_blocks`):
        by default on a one-thread CPU step with sticky contact (the solver keeps the blocks' stamps whenever it runs on
        the CPU with sticky contact). It may be set to False (every node, the dense update: the same grid to the bit)
        and back; True is refused where there are no stamps (CUDA, sliding contact)."""
        return self._sparse_update

    @sparse_update.setter
    def sparse_update(self, value: bool) -> None:
        value = bool(value)
        if value and not self._sparse_capable:
            raise InputError("the sparse grid update runs on the CPU with sticky contact only: this solver was built for "
                             f"{'sliding contact' if self.fields else self.model.device}, without the node blocks' stamps")
        if value and not self._sparse_update:
            self._updated.fill_(1)  # the dense steps left no record of which blocks held mass: visit every block once
        self._sparse_update = value

    def set_accelerator(self, accelerator) -> None:
        """Use ``accelerator`` (a :class:`warpmpm.solvers.rigid_modes.RigidModeAccelerator`, or None for none) in every step
        from now on: P2G then also scatters the force impulse apart, and the accelerator adds its coarse velocity
        change after the grid update."""
        d = self.model.device
        self.accelerator = accelerator
        if accelerator is None:
            self._grid_f = self._force_sum = wp.zeros((1, 1, 1), dtype=wp.vec3, device=d)
        elif self._force_sum.shape != self.grid_v.shape:
            self._grid_f = wp.zeros(self.grid_mm.shape, dtype=wp.vec3, device=d)
            self._force_sum = wp.zeros(self.grid_v.shape, dtype=wp.vec3, device=d)

    def _accelerating(self) -> bool:
        return self.accelerator is not None and self.accelerator.active

    def set_driven(self, driven: np.ndarray) -> None:
        """Leave the driven particles out of the adaptive damping's stiffness estimate (their drive is a spring
        of its own, far stiffer than the tissue)."""
        if self.adaptive:
            w = np.ones(self.model.n, dtype=np.float32)
            w[np.asarray(driven, dtype=np.int64)] = 0.0
            self.rayleigh_weight.assign(w)

    def reset_damping(self) -> None:
        """Start the adaptive damping afresh (a new frame): the derived value, no memory of past motion."""
        self.damping.assign(np.array([math.exp(-self.model.damping_per_s * self.model.dt_s)], dtype=np.float32))
        self._damping_dt = self.model.dt_s
        if self.adaptive:
            self._rayleigh.zero_()
            self._rayleigh_memory.zero_()
            self._accel_prev.zero_()

    @property
    def damping_per_s(self) -> float:
        """The velocity damping rate (1/s) the next step applies (reads the device)."""
        return float(-math.log(float(self.damping.numpy()[0])) / self.model.dt_s)

    def step(self, state_in: State, state_out: State, control: wp.array | None = None, dt: float | None = None,
             check: bool = True) -> None:
        """Advance one step from ``state_in`` to ``state_out`` under the external force ``control`` (N).

        ``check=False`` skips the host read-back of the status flag (for graph capture, where no
        read-back may happen; call :meth:`check` after the graph has run)."""
        m = self.model
        dt = m.dt_s if dt is None else dt
        d = m.device
        force = self.zero_force if control is None else control
        if not self.adaptive and dt != self._damping_dt:  # a fixed rate: the factor follows the step's length
            self.damping.assign(np.array([math.exp(-m.damping_per_s * dt)], dtype=np.float32))
            self._damping_dt = dt
        damping = self.damping
        cfg = m.config
        parts = 1 if self.threads == 1 or wp.get_device(d).is_capturing else self.threads
        if parts == 1:
            self._p2g_part(0, state_in.x, state_in.v, state_in.C, state_in.F, force, [m.mass, m.vol0, m.mu, m.lam, m.field], dt)
            self._grid_update(0, 0, damping, 1)
        else:
            n = len(self._ranges)
            x_in, v_in, C_in, F_in, f_in = (self._views(a) for a in (state_in.x, state_in.v, state_in.C, state_in.F, force))
            carry_in = self._views(state_in.x_carry)
            outs = [self._views(a) for a in (state_out.x, state_out.x_carry, state_out.v, state_out.C, state_out.F)]
            pv = [self._views(a) for a in (m.mass, m.vol0, m.mu, m.lam, m.field)]
            parallel.run_together(
                lambda k=k: self._p2g_part(k, x_in[k], v_in[k], C_in[k], F_in[k], f_in[k], [a[k] for a in pv], dt) for k in range(n))
            parallel.run_together(lambda k=k: self._grid_update(k, n, damping, n) for k in range(n))
        if self._accelerating():
            self.accelerator.correct(self._force_sum, damping, self.grid_v)
        if parts == 1:
            self._g2p_part(0, state_in.x, state_in.x_carry, state_in.F, m.field,
                           [state_out.x, state_out.x_carry, state_out.v, state_out.C, state_out.F], dt)
        else:
            parallel.run_together(
                lambda k=k: self._g2p_part(k, x_in[k], carry_in[k], F_in[k], pv[4][k], [a[k] for a in outs], dt) for k in range(n))
        if self.adaptive:
            lo, hi = cfg.explicit.damping_bounds
            wp.launch(kernels.stiffness_rayleigh, m.n, [state_in.v, state_out.v, self._accel_prev, m.mass, self.rayleigh_weight,
                                                        self.damping, dt, self._rayleigh], device=d)
            wp.launch(kernels.adapt_damping, 1, [self._rayleigh, self._rayleigh_memory, 1.0 - 1.0 / cfg.explicit.damping_memory_steps, dt,
                                                 lo * m.damping_per_s, hi * m.damping_per_s, self.damping], device=d)
        self.step_count += 1
        if check and self.check_every and self.step_count % self.check_every == 0:
            self.check()

    def _p2g_part(self, k, x, v, C, F, force, per_particle, dt):
        """P2G of thread ``k``'s particles (the arrays cut to its range; whole for one thread) into grid copy ``k``."""
        m = self.model
        nx = m.grid_shape[0]
        mass, vol0, mu, lam, field = per_particle
        if self.fields:
            wp.launch(kernels.p2g_fields, x.shape[0], [x, v, C, F, force, mass, vol0, mu, lam, field, nx, self._dx, dt,
                                                       k * nx * m.n_fields, self.grid_m, self.grid_mv, self.grid_g], device=m.device)
        else:
            wp.launch(kernels.p2g, x.shape[0], [x, v, C, F, force, mass, vol0, mu, lam, self._dx, dt, k * nx,
                                                int(self._accelerating()), self._stamp(), self.grid_mm, self._grid_f,
                                                self._stamps],
                      device=m.device)

    def _stamp(self) -> int:
        """This step's number as P2G stamps it into the node blocks it scatters into (never 0, the blocks' start; 0
        when the update is dense: no stamps)."""
        return self.step_count % 1_000_000_000 + 1 if self.sparse_update else 0

    def _grid_update(self, k, n, damping, parts):
        """Grid update of thread ``k``'s slab along x (of ``n`` threads; 0 of 1 for all of it), adding ``parts`` copies
        of the scattered sums."""
        m = self.model
        cfg = m.config
        if self.sparse_update:
            lo, hi = self._block_ranges[k] if n > 1 else (0, self._stamps.shape[0])
            wp.launch(kernels.grid_update_blocks, (hi - lo, *self._stamps.shape[1:]),
                      [self.grid_mm, parts, lo, self._stamps, self._stamp(), self._updated, damping, cfg.grid.wall_cells,
                       int(self._accelerating()), self._grid_f, self.grid_v, self._force_sum], device=m.device)
            return
        lo, hi = self._node_ranges[k] if n > 1 else (0, m.grid_shape[0])
        dim = (hi - lo, m.grid_shape[1], m.grid_shape[2])
        if self.fields:
            wp.launch(kernels.grid_update_fields, dim, [self.grid_m, self.grid_mv, self.grid_g, m.n_fields, m.grid_shape[0], parts, lo,
                                                        damping, cfg.grid.wall_cells, cfg.explicit.friction, self.grid_v], device=m.device)
        else:
            wp.launch(kernels.grid_update, dim, [self.grid_mm, parts, lo, damping, cfg.grid.wall_cells,
                                                 int(self._accelerating()), self._grid_f, self.grid_v, self._force_sum],
                      device=m.device)

    def _g2p_part(self, k, x, carry, F, field, outs, dt):
        """G2P of thread ``k``'s particles (arrays cut to its range), flagging into its own status array."""
        m = self.model
        nx = m.grid_shape[0] if self.fields else 0
        x_out, carry_out, v_out, C_out, F_out = outs
        wp.launch(kernels.g2p, x.shape[0], [self.grid_v, field, nx, x, carry, F, self._dx, dt, self._x_min, self._x_max,
                                            self.step_count, self._ranges[k][0], x_out, carry_out, v_out, C_out, F_out,
                                            self._status_parts[k]], device=m.device)

    def check(self) -> None:
        """Raise :class:`SimulationError` when a kernel flagged a non-finite value or a particle leaving the grid."""
        flags = np.stack([a.numpy() for a in self._status_parts]) if len(self._status_parts) > 1 else self.status.numpy()[None]
        code = int(flags[:, 0].max())
        if code == kernels.STATUS_OK:
            return
        bad = flags[flags[:, 0] > 0]
        particle, step = int(bad[:, 1].min()), int(bad[:, 2].min())
        organ = self.model.particles.organs[int(self.model.particles.organ_index[particle])]
        if code == kernels.STATUS_NONFINITE:
            raise SimulationError(
                f"non-finite value (NaN/Inf) at step {step}, particle {particle} ({organ}); the time step "
                f"{self.model.dt_s:.3e} s or the driving gains are too large for this scene"
            )
        raise SimulationError(
            f"particle {particle} ({organ}) tried to leave the simulation grid at step {step}; "
            f"increase GridConfig.margin_mm (now {self.model.config.grid.margin_mm} mm) or check the targets"
        )

    def reset_status(self) -> None:
        for a in self._status_parts:
            a.assign(np.array([0, 2**31 - 1, 2**31 - 1], dtype=np.int32))
