"""When a frame of the explicit relaxation stops: :class:`ConvergenceConfig` (the paper's residual rules, and the
settled mode that waits for the whole body) and :class:`ConvergenceMonitor`, which reads every step's residual and the
body's motion and says when to stop, and why."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import InputError, SimulationError

__all__ = ["ConvergenceConfig", "ConvergenceMonitor"]


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
    estimator also damps adaptively (:attr:`ExplicitConfig.damping_rule <warpmpm.solvers.config.ExplicitConfig.damping_rule>` ``"auto"``) and drives without the
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
