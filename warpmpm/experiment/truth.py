"""The pseudo ground truth of a run: which protocol, which seed, and the GT of a sub-combination."""

from __future__ import annotations

import numpy as np

from ..groundtruth import GroundTruth, contact_ground_truth, paper_ground_truth
from ..model import ParticleModel
from .case import PreparedCase
from .config import CaseConfig


def make_ground_truth(prep: PreparedCase, cfg: CaseConfig) -> GroundTruth:
    """Simulate the GT of ``cfg.protocol`` on the case's full model (every organ present)."""
    if cfg.protocol == "paper":
        return paper_ground_truth(prep.full_model, cfg.deformation, literal=cfg.literal, perturb=cfg.perturb,
                                  seed=cfg.phantom_seed, centre_mm=prep.centre_mm, solver_config=cfg.solver, device=cfg.device)
    return contact_ground_truth(prep.full_model, seed=cfg.phantom_seed + 31 * cfg.deformation, perturb=cfg.perturb,
                                solver_config=cfg.solver, device=cfg.device)


def gt_for_model(gt: GroundTruth, model: ParticleModel) -> np.ndarray:
    """GT positions of ``model``'s particles (a sub-combination of the GT model, same order)."""
    keep = np.isin(gt.model.organ_index, [gt.model.organs.index(o) for o in model.organs])
    return gt.positions_mm[keep]
