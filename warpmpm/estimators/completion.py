"""``completion``: the whole abdomen's elastic equilibrium completes what the planes show."""

from __future__ import annotations

import time

import numpy as np

from ..solvers.completion import CompletionModel, ReducedCompletion
from .base import FrameEstimate, FrameObservation, TrackingEstimator, register

__all__ = ["CompletionTracking"]


@register
class CompletionTracking(TrackingEstimator):
    """The equilibrium of the whole abdomen (organs, the tissue around them, the held spine;
    :mod:`warpmpm.solvers.completion`) driven by the observed motion decides the organs farther than ``reach_mm`` from
    every plane; the others keep the copy. Its response to each seen organ's affine motion is solved once for the
    series' plane set (:class:`~warpmpm.solvers.completion.ReducedCompletion`), so a frame is a small fit and a matrix
    product. The copy baseline keeps its own positions (the estimate leaves the copy off the planes)."""

    name = "completion"
    uses = "the whole abdomen's elastic equilibrium (organs, tissue, held spine) driven by the planes' observed motion"
    measured = ("beats the copy on an organ no plane reaches in 1 of 4 finite-element series, worse in 3 "
                "(benchmarks/track_fem.py); set-up 43-93 s, a frame milliseconds after it")
    baseline_from_estimate = False

    def __init__(self, model, case, planes, driven, config):
        super().__init__(model, case, planes, driven, config)
        t0 = time.perf_counter()
        idx = [on for _, on in planes]
        axes = [np.broadcast_to(f.projector, (len(on), 3, 3)) for f, on in planes]
        cm = CompletionModel(case, config.preset, model, config.completion, device=config.solver.device)
        self.reduced = ReducedCompletion(cm, np.concatenate(idx), np.concatenate(axes))
        self.setup_s = time.perf_counter() - t0

    def summary(self) -> str:
        return (f"completion: the abdomen's response to each seen organ's motion solved once in {self.setup_s:.1f} s "
                f"({self.reduced.R.shape[-1]} responses, {self.reduced.cm.summary()['unknowns']:,} unknowns)")

    def estimate(self, obs: FrameObservation) -> FrameEstimate:
        # the observation: every particle of a seen organ where the planes' motion puts it, combined over the planes
        # (this frame's in-plane directions, the others' from the estimate, which keeps them exactly)
        res = self.reduced.complete(obs.observed_mm[self.reduced.idx], obs.observed_mm)
        self._positions = res.positions_mm
        solve = dict(solver="completion", steps=0, linear_iterations=0, converged=True, slice_converged=True, settled=True,
                     body_motion_mm=0.0, reason=f"equilibrium of the observed motion ({res.info['responses']} precomputed responses)",
                     wall_s=res.wall_s, rms_residual_mm=float("nan"))
        return FrameEstimate(res.positions_mm, solve)
