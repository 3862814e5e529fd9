"""``copy``: what the planes show, copied; no physics."""

from __future__ import annotations

import time

from .base import FrameEstimate, FrameObservation, TrackingEstimator, register

__all__ = ["CopyEstimator"]


@register
class CopyEstimator(TrackingEstimator):
    """Each particle moved by the in-plane motion its organ shows on the frame (an organ the frame's registration did not
    measure: by the whole slice's motion), through-plane motion as the last estimate had it. The estimate is the
    ``propagate`` baseline of the tracker itself: on the finite-element series measured the slice-driven MPM ended
    exactly here on every organ (``benchmarks/track_fem.py``), so the copy gives its accuracy without its solve."""

    name = "copy"
    uses = "each organ's registered in-plane motion on the frame (an organ not measured: the whole slice's); no physics"
    measured = ("the tracker's estimate on every finite-element series measured (benchmarks/track_fem.py: the "
                "slice-driven MPM ends on it on every organ); no solve: registration and rendering only")

    def estimate(self, obs: FrameObservation) -> FrameEstimate:
        t0 = time.perf_counter()
        self._positions = obs.observed_mm.copy()
        solve = dict(solver="copy", steps=0, linear_iterations=0, converged=True, slice_converged=True, settled=True,
                     body_motion_mm=0.0, reason="the planes' observed motion, copied", wall_s=time.perf_counter() - t0,
                     rms_residual_mm=0.0)
        return FrameEstimate(self._positions.copy(), solve)
