"""What a run reports while it runs: the :class:`Recorder` interface and its do-nothing default.

The experiment layer calls a recorder at fixed points of a run; a viewer implements it (the Rerun
recorder is :class:`viewer.recording.RerunRecorder`). The library never imports a viewer:
the caller hands one in, so the package has no cycle through it and runs without it.

Order of calls in one run: :meth:`~Recorder.begin`, :meth:`~Recorder.log_slices`,
:meth:`~Recorder.on_step` every step, :meth:`~Recorder.log_result`, then :meth:`~Recorder.close`
(``ok=False`` when the run failed or was interrupted: a file recorder then leaves nothing behind).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

__all__ = ["Recorder", "NullRecorder"]

if TYPE_CHECKING:
    from .images import Case
    from .model import ParticleModel
    from .slices import DrivingSlice


class Recorder(Protocol):
    """A sink for one run's model, slices, per-step residuals and final result."""

    def begin(self, model: "ParticleModel", gt_positions_mm: np.ndarray | None = None) -> None:
        """The run's particle model at planning state and, when known, the GT positions (same order)."""

    def log_slices(self, slices: list["DrivingSlice"], driven: np.ndarray, targets_mm: np.ndarray,
                   case: "Case | None" = None, centre_mm: np.ndarray | None = None) -> None:
        """The driving slices, the driven particle indices and their targets (mm); ``case`` and
        ``centre_mm`` give the slice images when the case has an intensity image."""

    def on_step(self, estimator, step: int, rel_residual: float, rms_mm: float) -> None:
        """Called after every solver step of the estimate (``estimator.positions_mm()`` reads the state)."""

    def log_result(self, positions_mm: np.ndarray, steps: int, summary: dict, table: str) -> None:
        """The final positions, the step count, the run's JSON summary and its table (Markdown)."""

    def close(self, ok: bool = True) -> None:
        """Finish; with ``ok=False`` (a failed or interrupted run) discard what was written."""


class NullRecorder:
    """Records nothing (the default)."""

    def begin(self, model, gt_positions_mm=None) -> None:
        pass

    def log_slices(self, slices, driven, targets_mm, case=None, centre_mm=None) -> None:
        pass

    def on_step(self, estimator, step, rel_residual, rms_mm) -> None:
        pass

    def log_result(self, positions_mm, steps, summary, table) -> None:
        pass

    def close(self, ok: bool = True) -> None:
        pass
