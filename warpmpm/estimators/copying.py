"""``copy``: what the planes show, copied; no physics."""

from __future__ import annotations

import time

import numpy as np

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

    def __init__(self, model, case, planes, driven, config):
        super().__init__(model, case, planes, driven, config)
        self.organ_of = np.asarray(model.organs)[model.organ_index]
        self.centroid = {o: model.positions_mm[self.organ_of == o].mean(0) for o in model.organs}

    def estimate(self, obs: FrameObservation) -> FrameEstimate:
        t0 = time.perf_counter()
        out = obs.observed_mm.copy()
        rule = getattr(self.config, "unseen", "whole-slice")
        measured = [o for o in obs.measured_organs if o in self.centroid]
        unmeasured = [o for o in self.centroid if o not in measured]
        if rule != "whole-slice" and unmeasured:
            d = obs.observed_mm - obs.positions_mm  # this frame's in-plane motion of every particle
            mean = {o: d[self.organ_of == o].mean(0) for o in measured}
            for o in unmeasured:
                sel = self.organ_of == o
                if rule == "none" or not measured:
                    shift = np.zeros(3)
                elif rule == "global":
                    shift = d[np.isin(self.organ_of, measured)].mean(0)
                else:  # nearest measured organ, by the planning centroids
                    shift = mean[min(measured, key=lambda m: float(np.linalg.norm(self.centroid[m] - self.centroid[o])))]
                out[sel] = obs.positions_mm[sel] + shift
        self._positions = out
        solve = dict(solver="copy", steps=0, linear_iterations=0, converged=True, slice_converged=True, settled=True,
                     body_motion_mm=0.0, reason="the planes' observed motion, copied", wall_s=time.perf_counter() - t0,
                     rms_residual_mm=0.0)
        return FrameEstimate(self._positions.copy(), solve)
