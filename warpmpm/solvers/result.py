"""What one frame did: :class:`DriveResult`, returned by every frame solver (:mod:`warpmpm.solvers.frame`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .drive import Gains

__all__ = ["DriveResult"]


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
    acceleration ran (:attr:`AccelerationConfig.mode <warpmpm.solvers.config.AccelerationConfig.mode>`): ``"none"``, ``"from step N"`` (once the slice had
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
