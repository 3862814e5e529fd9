"""Slice-driven estimation: driving slices, targets, the PID driving force and convergence.

A frame's estimate drives the particles lying on one or more 2D slices toward their targets with
a PID force while the whole multi-organ MPM model evolves; the converged positions are the 3D
estimate. A frame starts from the previous frame's converged state (a cine stream is followed
frame after frame); the PID integral restarts every frame.

PID force (per driven particle i, acceleration form, physical units)::

    e_i = x_i^target - x_i                       (m)
    a_i = Kp e_i - Kd v_i + Ki sum(e_i dt)       (m/s^2;  Kp in 1/s^2, Kd in 1/s, Ki in 1/s^3)
    f_i = m_i clamp(a_i, max_accel)              (N)

Anti-windup: the integral stops growing while the command is clamped, and its own action never exceeds
the clamp. Without it, the part of the error the grid cannot remove (driven particles closer than a cell
pulled apart) was integrated for as long as the frame ran, up to 21x the clamp in 3,000 steps.

Writing the force as mass times a controlled acceleration makes one set of gains work for the
soft pancreas and the stiff duodenum alike (their masses differ by ~1500x under mass scaling).
``-Kd v`` is the derivative of the error for a target at rest, without the kick a finite
difference gives when the target jumps. The default gains derive from the solver's time step
(``omega = omega_dt / dt``, ``Kp = omega^2``, ``Kd = 2 zeta omega``, ``Ki = ki_ratio omega^3``) so
they stay stable for any scene, and are reported in physical units in every result.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from .errors import InputError, SimulationError
from .model import ParticleModel
from .slices import DrivingSlice, driven_indices
from .quasistatic import QuasiStaticSolver
from .rigid_modes import GUARD_GROWTH, GUARD_STEPS, RigidModeAccelerator
from .solver import MPMModel, MPMSolver, SolverConfig

__all__ = ["ConvergenceConfig", "ConvergenceMonitor", "Gains", "DriveConfig", "pid_force", "DriveResult",
           "SliceDrivenEstimator"]

# forward kernels only, no adjoints to compile (why: warpmpm.kernels)
wp.set_module_options({"enable_backward": False})


# --------------------------------------------------------------------------------------------
# Convergence
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ConvergenceConfig:
    """Stopping rules (METHOD.md): relative residual under ``th_v`` for ``th_s`` consecutive steps,
    or unchanged at ``th_d`` decimals for ``th_s`` consecutive steps; at most ``max_steps``.

    The paper uses TH_D = 4; the default here is 3: with the solver's default damping the estimate has
    settled when the residual stops changing in its third decimal, and TH_D = 4 spends 1.8x the steps
    for 0.02 mm (phantom, 8 deformations; benchmarks/studies/convergence_curves.py). ``ConvergenceConfig.paper()`` gives
    the paper's values.

    Those rules watch only the driven particles. Two more checks say what the stop means:
    a frame that stops by stagnation with its driven RMS residual above ``stall_mm`` is *stalled* (it
    settled far from its targets: an unreachable target, a collapsed element), not converged; and the
    whole model's motion is measured every ``th_s`` steps (the 99th percentile of the particles'
    displacement over the last ``th_s`` steps): below ``settle_mm`` the body has *settled*.
    With ``wait_settled`` a frame runs on until the body has settled too: the *settled mode*, in which the
    estimator also damps adaptively (:attr:`SolverConfig.damping_rule` ``"auto"``) and drives without the
    integral term (:attr:`DriveConfig.ki_ratio` None); the mode the FEM reference checks (docs/performance.md).
    """

    th_v: float = 0.0015
    """Relative residual threshold (TH_V)."""
    th_s: int = 100
    """Consecutive steps a rule must hold (TH_S); also the window of the body-motion check."""
    th_d: int = 3
    """Decimals at which the residual must stop changing (TH_D; the paper's 4 with :meth:`paper`)."""
    max_steps: int = 6000
    """Steps before a frame is reported not converged."""
    min_steps: int = 0
    """Steps before any rule may stop a frame."""
    stall_mm: float | None = None
    """Driven RMS residual (mm) above which a stagnated frame is ``stalled``; None: a quarter of the grid cell."""
    settle_mm: float = 0.05
    """The body has settled when the 99th-percentile particle moved less than this (mm) in the last ``th_s``
    steps and the motion still to come, extrapolated from the last two windows, is below it too."""
    wait_settled: bool = False
    """Keep stepping after the residual rule until the body has settled (or ``max_steps``)."""

    def __post_init__(self):
        for name in ("th_s", "th_d", "max_steps", "min_steps"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < (0 if name == "min_steps" else 1):
                raise InputError(f"ConvergenceConfig.{name} must be a positive integer, got {v!r}")
        for name in ("th_v", "settle_mm") + (("stall_mm",) if self.stall_mm is not None else ()):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"ConvergenceConfig.{name} must be a finite number > 0, got {v!r}")

    @classmethod
    def paper(cls) -> "ConvergenceConfig":
        """The paper's stopping rule (TH_V 0.0015, TH_S 100, TH_D 4)."""
        return cls(th_d=4)


class ConvergenceMonitor:
    """Feeds on the relative residual (and the RMS residual in mm) of every step, and on the body's
    motion every ``th_s`` steps, and says when to stop.

    ``reason``: ``"threshold"`` (TH_V) or ``"stagnation"`` (TH_D): converged; ``"stalled"``: stagnated
    with the RMS residual above ``stall_mm``; ``"max_steps"``.
    """

    def __init__(self, config: ConvergenceConfig | None = None, stall_mm: float = float("inf")):
        self.config = config or ConvergenceConfig()
        self.stall_mm = self.config.stall_mm if self.config.stall_mm is not None else stall_mm
        self.below = 0
        self.same = 0
        self.previous: float | None = None
        self.steps = 0
        self.reason: str | None = None
        self.body_motion_mm: float = float("nan")
        self._previous_motion_mm: float = float("nan")
        #: the residual rule has held once (where the default rule stops): the driven slice has arrived
        self.arrived = False

    @property
    def settled(self) -> bool:
        """The body moved less than ``settle_mm`` in the last window, and the motion still to come,
        extrapolated from how fast the window motion decays, is below ``settle_mm`` too (a slow creep
        that moves little per window but far in total is not settled)."""
        return self.body_motion_mm < self.config.settle_mm and self.remaining_mm < self.config.settle_mm

    @property
    def remaining_mm(self) -> float:
        """Motion still to come if the window motion keeps decaying geometrically: ``d r / (1 - r)``,
        ``r`` the ratio of the last two windows' motion (infinite when it does not decay)."""
        d, prev = self.body_motion_mm, self._previous_motion_mm
        if d == 0.0:
            return 0.0  # nothing moved in the last window (a frame that starts in equilibrium)
        if not (math.isfinite(d) and math.isfinite(prev)) or prev <= 0:
            return float("inf")
        r = d / prev
        return d * r / (1.0 - r) if r < 1.0 else (0.0 if d == 0 else float("inf"))

    def observe_body(self, motion_mm: float) -> None:
        """The 99th-percentile particle displacement (mm) over the last ``th_s`` steps."""
        self._previous_motion_mm = self.body_motion_mm
        self.body_motion_mm = float(motion_mm)

    def update(self, residual: float, rms_mm: float = 0.0) -> bool:
        c = self.config
        self.steps += 1
        if not math.isfinite(residual):
            raise SimulationError(f"non-finite residual at step {self.steps}: the simulation diverged")
        self.below = self.below + 1 if residual < c.th_v else 0
        rounded = round(residual, c.th_d)
        self.same = self.same + 1 if (self.previous is not None and rounded == self.previous) else 0
        self.previous = rounded
        self.reason = None
        if self.steps < c.min_steps:
            return False
        if self.below >= c.th_s:
            self.reason = "threshold"
        elif self.same >= c.th_s:
            self.reason = "stagnation" if rms_mm <= self.stall_mm else "stalled"
        if self.reason is not None:
            self.arrived = True
        if self.reason is not None and c.wait_settled and not self.settled:
            self.reason = None  # the driven slice has converged; the body has not settled yet
        if self.reason is None and self.steps >= c.max_steps:
            self.reason = "max_steps"
        return self.reason is not None

    @property
    def converged(self) -> bool:
        return self.reason in ("threshold", "stagnation")


# --------------------------------------------------------------------------------------------
# PID drive
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Gains:
    """Resolved PID gains in physical units (acceleration form, see module docstring)."""

    kp_per_s2: float
    """Proportional gain (1/s^2)."""
    kd_per_s: float
    """Derivative (velocity) gain (1/s)."""
    ki_per_s3: float
    """Integral gain (1/s^3)."""
    max_accel_m_s2: float
    """Clamp of the commanded acceleration magnitude (m/s^2)."""

    def to_json(self) -> dict:
        return {"kp_per_s2": self.kp_per_s2, "kd_per_s": self.kd_per_s, "ki_per_s3": self.ki_per_s3,
                "max_accel_m_s2": self.max_accel_m_s2}


@dataclass(frozen=True)
class DriveConfig:
    """PID gains (acceleration form, see module docstring) and clamp.

    Attributes:
        kp_per_s2, kd_per_s, ki_per_s3: explicit gains; None derives them from the time step.
        omega_dt: drive frequency times the time step for the derived gains (stability needs << 1).
        zeta: damping ratio of the derived derivative gain.
        ki_ratio: derived ``Ki = ki_ratio * omega^3``; None: 0.02 for a frame that stops on the driven slice,
            0 (a PD drive) for one that waits for the body to settle. The integral pushes every driven particle
            exactly onto its target, which the grid can give a single particle layer only by stretching the
            layers beside it (they share its grid nodes): against the FEM, the settled error of a scaled slice
            is 17 % with the integral and 9 % without, and with it the body creeps for as long as it runs
            (17 -> 20 % by 6,000 steps; without it 9.3 % from step 400 to 6,000). Stopping on the slice, the
            integral gets the slice to its targets sooner (phantom, paper protocol 3.0 against 3.2 mm).
        max_accel_m_s2: clamp of the commanded acceleration magnitude; None: ``0.05 * dx / dt^2``
            (at most 5% of a cell per step squared).
    """

    kp_per_s2: float | None = None
    kd_per_s: float | None = None
    ki_per_s3: float | None = None
    omega_dt: float = 0.3
    zeta: float = 1.0
    ki_ratio: float | None = None
    max_accel_m_s2: float | None = None

    def resolve(self, dt_s: float, dx_mm: float, settle: bool = False) -> Gains:
        """Gains in physical units for the time step and cell; ``settle``: the frame waits for the body."""
        for name in ("kp_per_s2", "kd_per_s", "ki_per_s3", "max_accel_m_s2"):
            value = getattr(self, name)
            if value is not None and (not math.isfinite(value) or value < 0):
                raise InputError(f"driving gain {name} must be a finite number >= 0, got {value}")
        ki_ratio = (0.0 if settle else 0.02) if self.ki_ratio is None else self.ki_ratio
        if not (0 < self.omega_dt < 1) or self.zeta < 0 or not (math.isfinite(ki_ratio) and ki_ratio >= 0):
            raise InputError("drive omega_dt must be in (0, 1); zeta and ki_ratio must be >= 0")
        w = self.omega_dt / dt_s
        kp = w * w if self.kp_per_s2 is None else self.kp_per_s2
        kd = 2 * self.zeta * w if self.kd_per_s is None else self.kd_per_s
        ki = ki_ratio * w**3 if self.ki_per_s3 is None else self.ki_per_s3
        amax = 0.05 * dx_mm * 1e-3 / dt_s**2 if self.max_accel_m_s2 is None else self.max_accel_m_s2
        if kp * dt_s * dt_s > 0.25 or kd * dt_s > 1.0:
            raise InputError(
                f"driving gains too large for the time step {dt_s:.3e} s: need Kp dt^2 <= 0.25 and Kd dt <= 1 "
                f"(Kp <= {0.25 / dt_s**2:.3e} 1/s^2, Kd <= {1 / dt_s:.3e} 1/s)"
            )
        return Gains(kp, kd, ki, amax)


@wp.kernel
def pid_force(
    driven: wp.array(dtype=int),
    target: wp.array(dtype=wp.vec3),
    axes: wp.array(dtype=wp.mat33),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    integral: wp.array(dtype=wp.vec3),
    bias: wp.array(dtype=wp.vec3),
    centre: wp.vec3,
    kp: float,
    kd: float,
    ki: float,
    max_accel: float,
    dt: float,
    f_ext: wp.array(dtype=wp.vec3),
    sums: wp.array(dtype=float, ndim=2),
    row: int,
):
    """PID force on driven particle ``driven[j]`` toward ``target[j]`` along the directions ``axes[j]`` drives
    (a projector: the identity pins all three components, a slice plane's projector only the in-plane
    ones); accumulates the residual sums ``sums[row] = [sum |e|^2, sum |target - centre|^2]`` over the
    driven directions (one row per step, read back in batches)."""
    j = wp.tid()
    p = driven[j]
    P = axes[j]
    e = P * (target[j] - x[p])
    acc_i = integral[j] + e * dt
    # anti-windup: the integral action alone never exceeds the clamp
    if ki > 0.0 and wp.length(ki * acc_i) > max_accel:
        acc_i = acc_i * (max_accel / (ki * wp.length(acc_i)))
    a = P * (bias[j] + kp * e - kd * v[p] + ki * acc_i)  # nothing along the directions this frame does not drive
    n = wp.length(a)
    if n > max_accel:
        a = a * (max_accel / n)
        acc_i = integral[j]  # anti-windup: no integration while the command is saturated
    integral[j] = acc_i
    f_ext[p] = mass[p] * a
    r = P * (target[j] - centre)
    wp.atomic_add(sums, row, 0, wp.dot(e, e))
    wp.atomic_add(sums, row, 1, wp.dot(r, r))


@dataclass
class DriveResult:
    """One frame's estimate.

    Attributes: positions_mm (N, 3) final world positions; steps; wall_s; residual_history
    (relative residual per step); rms_history_mm; converged; reason (which rule stopped it:
    threshold, stagnation, stalled, max_steps); final_rel_residual; final_rms_mm; gains (resolved,
    physical units); settled and body_motion_mm (the 99th-percentile particle displacement over the
    last TH_S steps: whether the whole model had stopped moving, not only the driven slice);
    min_det_f (the smallest volume ratio det F of any particle: near 0 or below, an element collapsed);
    method (``SolverConfig.method``). With the quasi-static method, ``steps`` counts Newton iterations,
    ``linear_iterations`` their conjugate-gradient iterations (each costs about half an explicit step), the residual
    histories have one entry per Newton iteration, ``reason`` is ``"settled"`` or ``"max_iterations"`` and
    ``body_motion_mm`` is the largest particle move of the last iteration. ``acceleration``: whether the rigid-mode
    acceleration ran (:attr:`SolverConfig.rigid_mode_acceleration`): ``"none"``, ``"from step N"`` (once the slice had
    arrived), with ``", switched off at step M"`` when its guard found it unstable.
    """

    positions_mm: np.ndarray
    steps: int
    wall_s: float
    residual_history: np.ndarray
    rms_history_mm: np.ndarray
    converged: bool
    reason: str
    gains: Gains | None = None
    settled: bool = False
    body_motion_mm: float = float("nan")
    min_det_f: float = float("nan")
    method: str = "explicit"
    linear_iterations: int = 0
    acceleration: str = "none"

    @property
    def final_rel_residual(self) -> float:
        return float(self.residual_history[-1]) if len(self.residual_history) else float("nan")

    @property
    def final_rms_mm(self) -> float:
        return float(self.rms_history_mm[-1]) if len(self.rms_history_mm) else float("nan")


class SliceDrivenEstimator:
    """Owns the solver and the current state; estimates frame after frame.

    Example::

        est = SliceDrivenEstimator(model, [DrivingSlice("axial", 20)])
        idx, targets = affine_targets(model, est.positions_mm(), est.slices, [InPlaneAffine(A, t)])  # warpmpm.targets
        result = est.estimate(targets)          # frame 1
        result2 = est.estimate(next_targets)    # frame 2 starts from frame 1's state

    GPU path: the residual sums of each step are accumulated on the device and read back every
    ``sync_every`` steps (default 1 on the CPU, 50 on CUDA), and with ``use_graph`` (default on CUDA)
    a batch of ``sync_every`` steps is captured once with ``wp.ScopedCapture`` and replayed with
    ``wp.capture_launch``: one host call and one read-back per batch. A frame then runs whole batches,
    so it may take up to ``sync_every - 1`` steps past the stopping rule (``DriveResult.steps`` counts
    them). The captured path gives the same numbers as the eager one (tested on the CPU, where Warp
    replays a captured launch list).
    """

    def __init__(self, model: ParticleModel, slices: list[DrivingSlice] | None = None, *,
                 driven: np.ndarray | None = None, solver_config: SolverConfig | None = None,
                 drive_config: DriveConfig | None = None, convergence: ConvergenceConfig | None = None,
                 extra_points_mm: np.ndarray | None = None, callback=None, sync_every: int | None = None,
                 use_graph: bool | None = None):
        if slices is None and driven is None:
            raise InputError("give driving slices or explicit driven particle indices")
        self.particles = model
        self.slices = list(slices) if slices else []
        self.driven = driven_indices(model, self.slices) if driven is None else np.asarray(driven, dtype=np.int64)
        if self.driven.size == 0:
            raise InputError("no particle to drive: the driving slices hold none of this model's particles"
                             + (f" (particle sampling step {model.sampling_step} leaves none on them)" if model.sampling_step > 1 else ""))
        if self.driven.min() < 0 or self.driven.max() >= model.n:
            raise InputError("driven particle indices outside the model")
        self.convergence = convergence or ConvergenceConfig()
        settle = self.convergence.wait_settled
        self.mpm = MPMModel(model, solver_config, extra_points_mm)
        rule = self.mpm.config.damping_rule
        # the "auto" damping and the default integral follow the stopping rule given here (not a per-frame override)
        self.solver = MPMSolver(self.mpm, adaptive=rule == "adaptive" or (rule == "auto" and settle))
        self.solver.set_driven(self.driven)
        #: the Newton / conjugate-gradient solver of ``SolverConfig(method="quasistatic" | "auto")``; None: explicit steps
        self.quasistatic = (QuasiStaticSolver(self.mpm, self.mpm.config.quasistatic)
                            if self.mpm.config.method in ("quasistatic", "auto") else None)
        self.drive_config = drive_config or DriveConfig()
        self.gains = self.drive_config.resolve(self.mpm.dt_s, self.mpm.dx_mm, settle=settle)
        #: the coarse level of the explicit relaxation (:attr:`SolverConfig.rigid_mode_acceleration`); None: none
        acc = self.mpm.config.rigid_mode_acceleration
        self.accelerator = None
        if self.mpm.config.method != "quasistatic" and (acc == "on" or (acc == "auto" and settle and self.mpm.n_fields == 1)):
            self.accelerator = RigidModeAccelerator(self.mpm, aggregate_mm=self.mpm.config.rigid_mode_aggregate_mm,
                                                    modes=self.mpm.config.rigid_mode_basis)
            self.solver.set_accelerator(self.accelerator)
        d = self.mpm.device
        self.state = self.mpm.state()
        self._other = self.mpm.state()
        nd = len(self.driven)
        self._driven_wp = wp.array(self.driven.astype(np.int32), dtype=int, device=d)
        self._target = wp.zeros(nd, dtype=wp.vec3, device=d)
        self._axes = wp.array(np.tile(np.eye(3, dtype=np.float32), (nd, 1, 1)), dtype=wp.mat33, device=d)
        self._integral = wp.zeros(nd, dtype=wp.vec3, device=d)
        self._bias = wp.zeros(nd, dtype=wp.vec3, device=d)
        self._force = wp.zeros(model.n, dtype=wp.vec3, device=d)
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
        self._centre = wp.vec3(*self.mpm.to_local_m(model.center_mm()[None, :])[0])
        self.callback = callback
        self.frames = 0

    def positions_mm(self) -> np.ndarray:
        return self.state.positions_mm()

    def driven_axes(self) -> np.ndarray:
        """(n_driven, 3, 3) the projector of each driven particle's drive (the identity: pinned; the plane's in-plane
        projector: in-plane driving), as the last :meth:`estimate` set it (a copy)."""
        return self._axes.numpy().copy()

    def _inside_grid(self, points_mm: np.ndarray) -> bool:
        """Whether every point lies where a particle's stencil stays clear of the grid's wall layer."""
        lo = self.mpm.origin_mm + (self.mpm.config.wall_cells + 1) * self.mpm.dx_mm
        hi = self.mpm.origin_mm + (np.asarray(self.mpm.grid_shape) - self.mpm.config.wall_cells - 2) * self.mpm.dx_mm
        return not (np.any(points_mm < lo) or np.any(points_mm > hi))

    def move_to(self, positions_mm: np.ndarray) -> None:
        """Place every particle at ``positions_mm`` (N, 3), at rest, keeping its deformation gradient: a
        kinematic prediction the next :meth:`estimate` corrects (the tracker's predictor). The move itself
        stores no strain, so it must be a motion the tissue makes without deforming (per-organ translation,
        rotation), or the physics will not see it."""
        positions_mm = np.asarray(positions_mm, dtype=np.float64)
        if positions_mm.shape != (self.particles.n, 3) or not np.all(np.isfinite(positions_mm)):
            raise InputError(f"predicted positions must be finite with shape ({self.particles.n}, 3), got {positions_mm.shape}")
        if not self._inside_grid(positions_mm):
            raise InputError("predicted positions lie outside the simulation grid; build the estimator with a larger reach")
        self.state.x.assign(self.mpm.to_local_m(positions_mm))
        self.state.x_carry.zero_()
        self.state.v.zero_()
        self.state.C.zero_()

    def _steps_run(self, n_residuals: int) -> int:
        """Steps actually run: whole batches of ``sync_every`` steps."""
        k = self.sync_every
        return -(-n_residuals // k) * k

    def driven_positions_mm(self) -> np.ndarray:
        return self.positions_mm()[self.driven]

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
        estimator: every array it touches is preallocated and updated in place between frames (targets,
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

    def estimate(self, targets_mm: np.ndarray, convergence: ConvergenceConfig | None = None, carry_force: bool = True,
                 axes: np.ndarray | None = None) -> DriveResult:
        """Drive the driven particles to ``targets_mm`` (n_driven, 3) until convergence; one frame.

        ``axes`` (n_driven, 3, 3): per driven particle, the projector onto the directions that are driven
        (:func:`warpmpm.targets.plane_projector`: a slice drives its in-plane components and leaves the
        through-plane one to the physics); None drives all three components (the default).

        The PID integral restarts at zero every frame. With ``carry_force`` (default) the integral
        action that held the previous frame's equilibrium is kept as a constant feed-forward term,
        so a frame that differs little from the last starts almost in balance instead of springing
        back while the integral rebuilds (measured: fewer steps per frame in a stream).
        """
        targets_mm = np.asarray(targets_mm, dtype=np.float64)
        if targets_mm.shape != (len(self.driven), 3):
            raise InputError(f"targets must have shape ({len(self.driven)}, 3) for the driven particles, got {targets_mm.shape}")
        if not np.all(np.isfinite(targets_mm)):
            raise InputError("targets hold a non-finite value")
        if not self._inside_grid(targets_mm):
            raise InputError("targets lie outside the simulation grid; build the estimator with extra_points_mm covering them "
                             f"or a larger SolverConfig.margin_mm (now {self.mpm.config.margin_mm} mm)")
        nd = len(self.driven)
        if axes is None:
            axes = np.tile(np.eye(3), (nd, 1, 1))
        axes = np.asarray(axes, dtype=np.float64)
        if axes.shape != (nd, 3, 3) or not np.all(np.isfinite(axes)):
            raise InputError(f"driven axes must be finite projectors of shape ({nd}, 3, 3), got {axes.shape}")
        self._axes.assign(axes.astype(np.float32))
        trial = None
        if self.mpm.config.method == "quasistatic":
            return self._estimate_quasistatic(targets_mm, axes)
        if self.mpm.config.method == "auto":
            trial = self._estimate_quasistatic(targets_mm, axes, trial=True)
            if trial.converged:
                return trial
        conv = ConvergenceMonitor(convergence or self.convergence, stall_mm=0.25 * self.mpm.dx_mm)
        window = conv.config.th_s
        last_x = self.state.x.numpy().copy()  # on the CPU .numpy() is a view of the live buffer
        self._target.assign(self.mpm.to_local_m(targets_mm))
        if carry_force and self.frames > 0:
            self._bias.assign(self._bias.numpy() + self.gains.ki_per_s3 * self._integral.numpy())
        else:
            self._bias.zero_()
        self._integral.zero_()
        self._force.zero_()
        self.solver.reset_damping()
        g = self.gains
        accelerating = False
        switched_off = None
        if self.accelerator is not None and self.accelerator.active:  # a new frame starts without it (below)
            self.accelerator.suspend()
            self._graph = None
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
                    self.callback(self, step, rel, rms_hist[-1])
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
                # before, where the drive still saturates (chosen when the paper protocol's 12 mm slice motion threw
                # the stomach off the grid from step 0; it still grew unstable later from here, which the guard now
                # catches; on the hanging FEM blocks starting here costs 100-300 steps against starting at step 0)
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
        acceleration = "none"
        if accelerating:
            if switched_off is None and self.accelerator.active:
                switched_off = self.accelerator.switched_off_after()
            acceleration = (f"from step {accel_from}" if self.accelerator.active or switched_off is not None
                            else "none (no coarse mode slower than the body)")
            off = switched_off
            if off is not None:
                acceleration += f", switched off at step {accel_from + off}"
                warnings.warn(f"the rigid-mode acceleration switched itself off at step {accel_from + off} (its coarse motion "
                              f"grew by more than {round(100 * (GUARD_GROWTH - 1))} % a step for {GUARD_STEPS} steps: unstable "
                              "here); the frame went on without it", RuntimeWarning, stacklevel=2)
        # on a GPU the loop runs whole batches of sync_every steps: report the steps actually run
        det = np.linalg.det(self.state.F.numpy().astype(np.float64))
        min_det, collapsed = float(det.min()), float(np.mean(det < 0.1))
        result = DriveResult(self.positions_mm(), self._steps_run(len(rel_hist)), wall, np.asarray(rel_hist), np.asarray(rms_hist),
                             conv.converged, conv.reason, g, conv.settled, conv.body_motion_mm, min_det, acceleration=acceleration)
        if trial is not None:  # "auto": the quasi-static iterations that came first are part of the frame
            result.method, result.linear_iterations = "quasistatic+explicit", trial.linear_iterations
            result.wall_s += trial.wall_s
        if conv.reason == "stalled":
            warnings.warn(f"estimate stalled: it stopped changing {rms_hist[-1]:.2f} mm (RMS) from its targets after {conv.steps} "
                          f"steps, more than {conv.stall_mm:.2f} mm; the targets may be unreachable"
                          + (f" ({collapsed:.1%} of the particles collapsed to det F < 0.1)" if collapsed > 0.005 else ""),
                          RuntimeWarning, stacklevel=2)
        elif not result.converged:
            warnings.warn(f"estimate did not converge in {conv.steps} steps (relative residual {rel:.2e}, "
                          f"RMS {rms_hist[-1]:.3f} mm)", RuntimeWarning, stacklevel=2)
        elif collapsed > 0.005:
            warnings.warn(f"estimate converged but {collapsed:.1%} of the particles collapsed (det F < 0.1, smallest "
                          f"{min_det:.3f}): the targets compress or fold the tissue beyond what the material model holds",
                          RuntimeWarning, stacklevel=2)
        return result

    def _estimate_quasistatic(self, targets_mm: np.ndarray, axes: np.ndarray, trial: bool = False) -> DriveResult:
        """One frame by the quasi-static solver (:mod:`warpmpm.quasistatic`): the settled equilibrium under the
        drive's spring; the ConvergenceConfig's rules do not apply (the solver stops when an iteration moves no
        particle by more than ``QuasiStaticConfig.settle_mm``). ``trial`` (``method="auto"``): at most
        ``auto_newton_iterations``, stopping at a capped linear solve, and no warning when it has not settled (the
        explicit steps go on from there)."""
        nd = len(self.driven)
        t0 = time.perf_counter()
        self.quasistatic.set_drive(self.driven, targets_mm, axes)
        qc = self.quasistatic.config
        res = self.quasistatic.solve(self.state, max_iterations=qc.auto_newton_iterations if trial else None, stop_at_cg_cap=trial,
                                     max_cg_iterations=qc.auto_max_cg_iterations if trial else None)
        wall = time.perf_counter() - t0
        if res.settled:  # the PID's integral and feed-forward belong to an explicit frame's equilibrium; none holds this one
            self._integral.zero_()
            self._bias.zero_()
        reach = np.einsum("nij,nj->ni", axes, targets_mm - self.particles.center_mm())
        scale = math.sqrt(max(float(np.sum(reach**2)), 1e-30) / nd)
        rms = np.asarray(res.rms_history_mm, dtype=np.float64)
        rel = rms / scale
        if self.callback is not None:
            for k in range(len(rms)):
                self.callback(self, k + 1, float(rel[k]), float(rms[k]))
        if trial and not res.settled:
            return DriveResult(self.positions_mm(), res.newton_iterations, wall, rel, rms, False, "max_iterations", None, False,
                               res.max_move_mm, float("nan"), method="quasistatic", linear_iterations=res.cg_iterations)
        self.frames += 1
        det = np.linalg.det(self.state.F.numpy().astype(np.float64))
        result = DriveResult(self.positions_mm(), res.newton_iterations, wall, rel, rms, res.settled,
                             "settled" if res.settled else "max_iterations", None, res.settled, res.max_move_mm, float(det.min()),
                             method="quasistatic", linear_iterations=res.cg_iterations)
        if not res.settled:
            warnings.warn(f"quasi-static estimate did not settle in {res.newton_iterations} Newton iterations (the last moved a "
                          f"particle {res.max_move_mm:.3f} mm; QuasiStaticConfig.settle_mm {self.quasistatic.config.settle_mm} mm)",
                          RuntimeWarning, stacklevel=3)
        return result
