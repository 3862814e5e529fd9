"""The explicit relaxation: a frame by explicit MLS-MPM steps (:class:`~warpmpm.solvers.explicit.MPMSolver`) under the
PID drive (:mod:`warpmpm.solvers.drive`), stopped by :class:`~warpmpm.solvers.convergence.ConvergenceMonitor`, with
the rigid-mode acceleration (:mod:`warpmpm.solvers.rigid_modes`) in the settled mode.

A frame starts from the previous frame's state (a cine stream is followed frame after frame); the PID integral restarts
every frame, and the integral action that held the previous frame is carried over as a feed-forward term.

GPU path: the residual sums of each step are accumulated on the device and read back every ``sync_every`` steps
(default 1 on the CPU, 50 on CUDA), and with ``use_graph`` (default on CUDA) a batch of ``sync_every`` steps is captured
once with ``wp.ScopedCapture`` and replayed with ``wp.capture_launch``: one host call and one read-back per batch. A
frame then runs whole batches, so it may take up to ``sync_every - 1`` steps past the stopping rule
(``DriveResult.steps`` counts them). The captured path gives the same numbers as the eager one (tested on the CPU, where
Warp replays a captured launch list).
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np
import warp as wp

from ..errors import InputError, SimulationError
from ..model import ParticleModel
from .convergence import ConvergenceConfig, ConvergenceMonitor
from .drive import DriveConfig, pid_force
from .explicit import MPMSolver
from .grid import MPMModel
from .result import DriveResult
from .rigid_modes import GUARD_GROWTH, GUARD_STEPS, RigidModeAccelerator

__all__ = ["ExplicitRelaxation"]


class ExplicitRelaxation:
    """The explicit frame solver (:class:`~warpmpm.solvers.frame.FrameSolver`) of one :class:`MPMModel`: owns the
    stepper, the pair of states it swaps, the PID drive's memory, the rigid-mode accelerator and the captured graph.

    ``callback(step, rel, rms_mm)`` is called after every step (and every quasi-static iteration)."""

    def __init__(self, mpm: MPMModel, particles: ParticleModel, driven: np.ndarray, convergence: ConvergenceConfig,
                 drive_config: DriveConfig, callback=None, sync_every: int | None = None, use_graph: bool | None = None):
        self.mpm = mpm
        self.particles = particles
        self.driven = driven
        self.convergence = convergence
        settle = convergence.wait_settled
        rule = mpm.config.explicit.damping_rule
        # the "auto" damping and the default integral follow the stopping rule given here (not a per-frame override)
        self.solver = MPMSolver(mpm, adaptive=rule == "adaptive" or (rule == "auto" and settle))
        self.solver.set_driven(driven)
        self.drive_config = drive_config
        self.gains = drive_config.resolve(mpm.dt_s, mpm.dx_mm, settle=settle)
        #: the coarse level of the relaxation (:attr:`AccelerationConfig.mode <warpmpm.solvers.config.AccelerationConfig.mode>`); None: none
        acc = mpm.config.acceleration.mode
        self.accelerator = None
        if mpm.config.method != "quasistatic" and (acc == "on" or (acc == "auto" and settle and mpm.n_fields == 1)):
            self.accelerator = RigidModeAccelerator(mpm, aggregate_mm=mpm.config.acceleration.aggregate_mm,
                                                    modes=mpm.config.acceleration.basis)
            self.solver.set_accelerator(self.accelerator)
        d = mpm.device
        self.state = mpm.state()
        self._other = mpm.state()
        nd = len(driven)
        self._driven_wp = wp.array(driven.astype(np.int32), dtype=int, device=d)
        self._target = wp.zeros(nd, dtype=wp.vec3, device=d)
        self._axes = wp.array(np.tile(np.eye(3, dtype=np.float32), (nd, 1, 1)), dtype=wp.mat33, device=d)
        self._integral = wp.zeros(nd, dtype=wp.vec3, device=d)
        self._bias = wp.zeros(nd, dtype=wp.vec3, device=d)
        self._force = wp.zeros(particles.n, dtype=wp.vec3, device=d)
        # residual sums of the steps since the last read-back: read every ``sync_every`` steps so a GPU
        # run does not synchronise with the host every step (every step on the CPU, where it is free)
        cuda = str(d).startswith("cuda")
        self.use_graph = cuda if use_graph is None else bool(use_graph)
        if sync_every is not None and int(sync_every) < 1:
            raise InputError(f"sync_every must be >= 1, got {sync_every}")
        k = (50 if cuda else 1) if sync_every is None else int(sync_every)
        if self.use_graph:
            k = max(2, k + (k % 2))  # the captured batch swaps the two states k times: k even ends where it began
        self.sync_every = k
        self._sums = wp.zeros((self.sync_every, 2), dtype=float, device=d)
        self._graph = None
        self._centre = wp.vec3(*mpm.to_local_m(particles.center_mm()[None, :])[0])
        self.callback = callback
        #: frames solved so far (by this relaxation or a quasi-static frame on its state)
        self.frames = 0

    def positions_mm(self) -> np.ndarray:
        return self.state.positions_mm()

    def set_axes(self, axes: np.ndarray) -> None:
        """The projector of each driven particle's drive (n_driven, 3, 3) for the next frames."""
        self._axes.assign(axes.astype(np.float32))

    def driven_axes(self) -> np.ndarray:
        return self._axes.numpy().copy()

    def clear_drive_memory(self) -> None:
        """Forget the PID's integral and feed-forward (a frame settled by another solver holds its own equilibrium)."""
        self._integral.zero_()
        self._bias.zero_()

    def _steps_run(self, n_residuals: int) -> int:
        """Steps actually run: whole batches of ``sync_every`` steps."""
        k = self.sync_every
        return -(-n_residuals // k) * k

    def _launch_batch(self, check: bool) -> None:
        """Enqueue ``sync_every`` steps: PID force, then one solver step, swapping the two states."""
        g, dt, d, nd = self.gains, self.mpm.dt_s, self.mpm.device, len(self.driven)
        self._sums.zero_()
        for row in range(self.sync_every):
            wp.launch(pid_force, nd, [self._driven_wp, self._target, self._axes, self.state.x, self.state.v, self.mpm.mass, self._integral,
                                      self._bias, self._centre, g.kp_per_s2, g.kd_per_s, g.ki_per_s3,
                                      g.max_accel_m_s2, dt, self._force, self._sums, row], device=d)
            self.solver.step(self.state, self._other, self._force, check=check)
            self.state, self._other = self._other, self.state

    def _run_batch(self) -> None:
        """Run one batch of ``sync_every`` steps, eagerly or as a replay of a captured graph.

        The graph (CUDA graph on a GPU, Warp's replayed launch list on the CPU) is captured once per
        relaxation: every array it touches is preallocated and updated in place between frames (targets,
        bias, integral), so it stays valid frame after frame with no per-step allocation or launch
        from Python. The NaN / out-of-grid flag is read after each batch."""
        if not self.use_graph:
            self._launch_batch(check=True)
            return
        if self._graph is None:
            first = self.solver.step_count
            with wp.ScopedCapture(device=self.mpm.device) as capture:
                self._launch_batch(check=False)
            self._graph = capture.graph
            self.solver.step_count = first
        wp.capture_launch(self._graph)
        self.solver.step_count += self.sync_every
        try:
            self.solver.check()
        except SimulationError as exc:
            raise SimulationError(f"{exc} (graph replay: the step is counted within a batch of {self.sync_every}; "
                                  f"this batch ended at step {self.solver.step_count})") from None

    def _start_frame(self, targets_mm: np.ndarray, carry_force: bool) -> None:
        """Targets in, the PID's memory restarted (the last frame's holding force kept as feed-forward with
        ``carry_force``), the damping reset and the accelerator suspended until the slice has arrived."""
        self._target.assign(self.mpm.to_local_m(targets_mm))
        if carry_force and self.frames > 0:
            self._bias.assign(self._bias.numpy() + self.gains.ki_per_s3 * self._integral.numpy())
        else:
            self._bias.zero_()
        self._integral.zero_()
        self._force.zero_()
        self.solver.reset_damping()
        if self.accelerator is not None and self.accelerator.active:  # a new frame starts without it
            self.accelerator.suspend()
            self._graph = None

    def solve(self, targets_mm: np.ndarray, axes: np.ndarray, convergence: ConvergenceConfig | None = None,
              carry_force: bool = True, trial: DriveResult | None = None) -> DriveResult:
        """One frame (:class:`~warpmpm.solvers.frame.FrameSolver`); ``trial``: the quasi-static iterations that came
        first (``method="auto"``), added to the result."""
        conv = ConvergenceMonitor(convergence or self.convergence, stall_mm=0.25 * self.mpm.dx_mm)
        window = conv.config.th_s
        nd = len(self.driven)
        last_x = self.state.x.numpy().copy()  # on the CPU .numpy() is a view of the live buffer
        self._start_frame(targets_mm, carry_force)
        g = self.gains
        accelerating = False
        switched_off = None
        rel_hist, rms_hist = [], []
        t0 = time.perf_counter()
        done = False
        step = 0
        while not done:
            self._run_batch()
            if (step + self.sync_every) // window != step // window:  # the body's motion over the last window
                x = self.state.x.numpy().copy()
                conv.observe_body(float(np.percentile(np.linalg.norm(x - last_x, axis=1), 99)) * 1e3)
                last_x = x
            sums = self._sums.numpy()
            for e2, r2 in sums:
                step += 1
                rel = math.sqrt(e2 / max(r2, 1e-30))
                rel_hist.append(rel)
                rms_hist.append(math.sqrt(e2 / nd) * 1e3)
                if self.callback is not None:
                    self.callback(step, rel, rms_hist[-1])
                if conv.update(rel, rms_hist[-1]):
                    done = True
                    break
            if accelerating and self.accelerator.active and switched_off is None:
                switched_off = self.accelerator.switched_off_after()
                if switched_off is not None:  # the guard turned the correction off: stop scattering the force for it too
                    self.accelerator.suspend()
                    self._graph = None
            if self.accelerator is not None and not accelerating and conv.arrived and not done:
                # the slice has arrived: from here the body settles, and its slow coarse modes are accelerated. Not
                # before, where the drive still saturates (docs/decisions/2026-12-03-solver-defaults.md)
                layout = self.accelerator.layout
                self.accelerator.build(self.state, self.driven, axes, g.kp_per_s2)
                accelerating = True
                accel_from = step
                if self.accelerator.layout != layout or self.accelerator.active:
                    self._graph = None  # the captured launches point at the old arrays, or do not run the coarse level
        self.solver.check()
        wall = time.perf_counter() - t0
        self._force.zero_()
        self.frames += 1
        acceleration = self._acceleration_report(accelerating, switched_off, accel_from if accelerating else 0)
        # on a GPU the loop runs whole batches of sync_every steps: report the steps actually run
        det = np.linalg.det(self.state.F.numpy().astype(np.float64))
        min_det, collapsed = float(det.min()), float(np.mean(det < 0.1))
        result = DriveResult(self.positions_mm(), self._steps_run(len(rel_hist)), wall, np.asarray(rel_hist), np.asarray(rms_hist),
                             conv.converged, conv.reason, g, conv.settled, conv.body_motion_mm, min_det, acceleration=acceleration)
        if trial is not None:  # "auto": the quasi-static iterations that came first are part of the frame
            result.method, result.linear_iterations = "quasistatic+explicit", trial.linear_iterations
            result.wall_s += trial.wall_s
        self._warn(conv, result, rel, rms_hist, collapsed, min_det)
        return result

    def _acceleration_report(self, accelerating: bool, switched_off: int | None, accel_from: int) -> str:
        """``DriveResult.acceleration``, with a warning when the guard switched the coarse level off."""
        if not accelerating:
            return "none"
        if switched_off is None and self.accelerator.active:
            switched_off = self.accelerator.switched_off_after()
        acceleration = (f"from step {accel_from}" if self.accelerator.active or switched_off is not None
                        else "none (no coarse mode slower than the body)")
        if switched_off is not None:
            acceleration += f", switched off at step {accel_from + switched_off}"
            warnings.warn(f"the rigid-mode acceleration switched itself off at step {accel_from + switched_off} (its coarse "
                          f"motion grew by more than {round(100 * (GUARD_GROWTH - 1))} % a step for {GUARD_STEPS} steps: "
                          "unstable here); the frame went on without it", RuntimeWarning, stacklevel=4)
        return acceleration

    @staticmethod
    def _warn(conv: ConvergenceMonitor, result: DriveResult, rel: float, rms_hist: list, collapsed: float, min_det: float) -> None:
        """One warning line for a frame that stalled, did not converge or collapsed tissue."""
        if conv.reason == "stalled":
            warnings.warn(f"estimate stalled: it stopped changing {rms_hist[-1]:.2f} mm (RMS) from its targets after {conv.steps} "
                          f"steps, more than {conv.stall_mm:.2f} mm; the targets may be unreachable"
                          + (f" ({collapsed:.1%} of the particles collapsed to det F < 0.1)" if collapsed > 0.005 else ""),
                          RuntimeWarning, stacklevel=4)
        elif not result.converged:
            warnings.warn(f"estimate did not converge in {conv.steps} steps (relative residual {rel:.2e}, "
                          f"RMS {rms_hist[-1]:.3f} mm)", RuntimeWarning, stacklevel=4)
        elif collapsed > 0.005:
            warnings.warn(f"estimate converged but {collapsed:.1%} of the particles collapsed (det F < 0.1, smallest "
                          f"{min_det:.3f}): the targets compress or fold the tissue beyond what the material model holds",
                          RuntimeWarning, stacklevel=4)
