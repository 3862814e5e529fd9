"""``slice-driven``: the seed's method (Hara et al.): the multi-organ MPM driven at the particles on the frame's plane."""

from __future__ import annotations

import numpy as np

from ..driving import ConvergenceConfig, SliceDrivenEstimator
from .base import FrameEstimate, FrameObservation, TrackingEstimator, register

__all__ = ["SliceDrivenTracking"]


@register
class SliceDrivenTracking(TrackingEstimator):
    """The seed's slice-driven MPM: from the previous frame's state, predicted by the frame's observed motion
    (``TrackerConfig.predict``), to a new equilibrium driven at the particles on the frame's plane
    (:class:`warpmpm.driving.SliceDrivenEstimator`; ``solver``, ``max_steps``, ``wait_settled`` set it)."""

    name = "slice-driven"
    uses = "the seed's multi-organ MPM driven at the particles on the frame's plane (Hara et al.)"
    measured = ("equals the copy on every organ of the finite-element series (benchmarks/track_fem.py) for 0.02-0.05 s "
                "a frame more; kept to reproduce the paper")

    def __init__(self, model, case, planes, driven, config):
        super().__init__(model, case, planes, driven, config)
        reach = [model.positions_mm + s * config.margin_mm * np.eye(3)[k] for k in range(3) for s in (-0.5, 0.5)]
        self.mpm = SliceDrivenEstimator(model, driven=driven, solver_config=config.solver, extra_points_mm=np.vstack(reach),
                                        convergence=ConvergenceConfig(max_steps=config.max_steps, wait_settled=config.wait_settled))

    def positions_mm(self) -> np.ndarray:
        return self.mpm.positions_mm()

    def estimate(self, obs: FrameObservation) -> FrameEstimate:
        x, on = obs.positions_mm, obs.on_plane
        targets = x[self.driven].copy()  # the particles on the plane now pulled where the frame's motion puts them
        axes = np.zeros((len(self.driven), 3, 3))
        targets[on] = obs.observed_mm[self.driven[on]]
        axes[on] = obs.frame.projector
        if self.config.predict:
            self.mpm.move_to(obs.observed_mm)
        res = self.mpm.estimate(targets, axes=axes)
        solve = dict(solver=res.method, steps=res.steps, linear_iterations=res.linear_iterations,
                     converged=bool(res.converged and res.settled), slice_converged=res.converged, settled=res.settled,
                     body_motion_mm=res.body_motion_mm, reason=res.reason, wall_s=res.wall_s, rms_residual_mm=res.final_rms_mm)
        return FrameEstimate(res.positions_mm, solve)
