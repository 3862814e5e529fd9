"""A run's driving targets from its ground truth: the ``--targets`` kinds of :class:`CaseConfig`.

- ``affine``: one in-plane affine per slice, as a registration would measure it: the paper's known
  ``A`` for axial slices under the paper protocol, else the least-squares fit of the slice particles'
  GT motion (:meth:`~warpmpm.slices.InPlaneAffine.fit`).
- ``gt``: the slice particles' GT 3D positions (through-plane motion included; an upper bound).
- ``registration``: register each planning slice with the slice captured from the GT-warped image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..groundtruth import GroundTruth, paper_affine
from ..model import ParticleModel
from ..slices import DrivingSlice, InPlaneAffine, driven_indices, in_plane_axes
from ..targets import affine_targets, registration_targets, truth_targets
from .capture import planning_and_gt_volumes
from .case import PreparedCase
from .config import CaseConfig


@dataclass
class RunTargets:
    """Driven particle indices, their targets (mm), the slice motion used and the registration's report.

    Attributes:
        idx: (n_driven,) sorted particle indices. targets_mm: (n_driven, 3).
        affines: the in-plane motion of each slice (fitted, known or registered; what ``propagate`` applies).
        registration: the registration's own error and time when ``targets="registration"``, else None.
    """

    idx: np.ndarray
    targets_mm: np.ndarray
    affines: list[InPlaneAffine]
    registration: dict | None = None


def slice_affines(prep: PreparedCase, model: ParticleModel, gt_pos: np.ndarray, slices: list[DrivingSlice],
                  cfg: CaseConfig) -> list[InPlaneAffine]:
    """The in-plane affine of every driving slice: the paper's known A for axial slices under the paper
    protocol, else the least-squares fit of the slice particles' GT motion."""
    out = []
    for s in slices:
        if cfg.protocol == "paper" and s.orientation == "axial":
            out.append(InPlaneAffine(paper_affine(cfg.deformation, cfg.literal)))
        else:
            idx = driven_indices(model, [s])
            e_u, e_v = in_plane_axes(model, s.orientation)
            out.append(InPlaneAffine.fit(model.positions_mm[idx], gt_pos[idx], e_u, e_v, prep.centre_mm))
    return out


def run_targets(prep: PreparedCase, gt: GroundTruth, model: ParticleModel, gt_pos: np.ndarray, slices: list[DrivingSlice],
                cfg: CaseConfig) -> RunTargets:
    """The targets of ``cfg.targets`` for ``model`` driven from ``slices``."""
    if cfg.targets == "affine":
        affines = slice_affines(prep, model, gt_pos, slices, cfg)
        idx, targets = affine_targets(model, model.positions_mm, slices, affines, prep.centre_mm)
        return RunTargets(idx, targets, affines)
    if cfg.targets == "gt":
        idx, targets = truth_targets(model, slices, gt_pos)
        return RunTargets(idx, targets, slice_affines(prep, model, gt_pos, slices, cfg))
    case = prep.case
    planning, warped = planning_and_gt_volumes(case, gt)
    values = {o: case.label_map[o] for o in gt.model.organs}
    idx, targets, info = registration_targets(model, slices, planning, warped, case.labels, case.geometry, values,
                                              prep.centre_mm, truth_mm=gt_pos)
    registered = info.pop("affines")
    info.pop("slices")
    return RunTargets(idx, targets, registered, info)
