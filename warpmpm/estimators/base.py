"""The estimator interface (:class:`TrackingEstimator`), what it is given (:class:`FrameObservation`) and gives back
(:class:`FrameEstimate`), and the registry of names (:data:`ESTIMATORS`)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..errors import InputError

__all__ = ["ESTIMATORS", "FrameEstimate", "FrameObservation", "TrackingEstimator", "get_estimator", "register"]


@dataclass
class FrameObservation:
    """What one registered cine frame shows, in the terms every estimator takes.

    Attributes:
        frame: the cine frame (:class:`warpmpm.cine.CineFrame`: its plane, thickness, in-plane axes).
        positions_mm: (N, 3) every particle's estimated position before this frame (mm, world LPS).
        observed_mm: (N, 3) every particle where the frame's registered motion puts it: the in-plane motion of its
            organ where the registration measured the organ on this frame, else the whole slice's; the through-plane
            component kept from ``positions_mm`` (what a plane cannot see).
        on_plane: boolean mask over the estimator's ``driven`` candidates: those within half the slice thickness of
            the frame's plane now.
        measured_organs: the organs whose own motion the frame's registration measured (the others in
            ``observed_mm`` took the whole slice's).
    """

    frame: object
    positions_mm: np.ndarray
    observed_mm: np.ndarray
    on_plane: np.ndarray
    measured_organs: tuple = ()


@dataclass
class FrameEstimate:
    """An estimator's answer for one frame: every particle's position (N, 3, mm) and the ``track.csv`` fields of its
    solve (``solver``, ``steps``, ``linear_iterations``, ``converged``, ``slice_converged``, ``settled``,
    ``body_motion_mm``, ``reason``, ``wall_s``, ``rms_residual_mm``)."""

    positions_mm: np.ndarray
    solve: dict


class TrackingEstimator(ABC):
    """Set up once from the planning model and the series' planes; then :meth:`estimate` once per frame.

    Args:
        model: the planning particle model (:class:`warpmpm.model.ParticleModel`).
        case: the planning case (its image, labels and geometry).
        planes: per plane of the series, its first frame and the indices of the particles that may lie on it.
        driven: every particle that may lie on a plane during the series (the union of the planes' candidates).
        config: the tracker's configuration (:class:`warpmpm.tracker.TrackerConfig`).

    Class attributes: ``name`` (the registry's key), ``uses`` (one line: what it takes from the planes and the model),
    ``measured`` (one line: its measured accuracy and latency, with where it was measured), ``baseline_from_estimate``
    (True: the copy baseline of ``track`` is the frame's motion applied to this estimate; False: the baseline keeps
    positions of its own, for an estimator that leaves the copy).
    """

    name: ClassVar[str] = ""
    uses: ClassVar[str] = ""
    measured: ClassVar[str] = ""
    baseline_from_estimate: ClassVar[bool] = True

    def __init__(self, model, case, planes, driven: np.ndarray, config):
        self.model, self.case, self.planes, self.driven, self.config = model, case, planes, driven, config
        self.setup_s = 0.0
        self._positions = model.positions_mm.copy()

    def positions_mm(self) -> np.ndarray:
        """The current estimate: every particle's position (N, 3), mm, world LPS."""
        return self._positions.copy()

    @abstractmethod
    def estimate(self, obs: FrameObservation) -> FrameEstimate:
        """Every particle's position after the frame ``obs``."""

    def summary(self) -> str:
        """What ``track`` prints after the set-up (empty when there is nothing to say)."""
        return ""


#: name -> estimator class (``warpmpm estimators`` lists them)
ESTIMATORS: dict[str, type[TrackingEstimator]] = {}


def register(cls: type[TrackingEstimator]) -> type[TrackingEstimator]:
    """Class decorator: add an estimator to :data:`ESTIMATORS` under its ``name``."""
    if not cls.name or cls.name in ESTIMATORS:
        raise ValueError(f"estimator name {cls.name!r} is empty or taken")
    ESTIMATORS[cls.name] = cls
    return cls


def get_estimator(name: str) -> type[TrackingEstimator]:
    """The estimator class registered as ``name``; :class:`InputError` naming the registered ones otherwise."""
    if name not in ESTIMATORS:
        raise InputError(f"estimator {name!r} is not one of {', '.join(ESTIMATORS)} (`warpmpm estimators` lists them)")
    return ESTIMATORS[name]
