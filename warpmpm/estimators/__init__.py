"""What decides the 3D motion of a tracked frame from what its plane shows: the estimators, behind one interface.

An estimator is set up once from the planning model and the series' planes, then called once per frame with the
frame's observation (:class:`FrameObservation`: where the registered in-plane motion of each organ puts every
particle) and returns every particle's position (:class:`FrameEstimate`). The registry :data:`ESTIMATORS` maps each
name to its class; ``warpmpm estimators`` lists them with what each uses and what it measured. Adding one is a module
in this package with a class decorated by :func:`register` (and its import below).

    from warpmpm.estimators import ESTIMATORS, TrackingEstimator, register
"""

from .base import ESTIMATORS, FrameEstimate, FrameObservation, TrackingEstimator, get_estimator, register
from . import copying, slice_driven, completion  # noqa: F401,E402,I001 - each registers its estimator (in this order)

__all__ = ["ESTIMATORS", "FrameEstimate", "FrameObservation", "TrackingEstimator", "get_estimator", "register"]
