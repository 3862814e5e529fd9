"""The pseudo ground truth of a run: which protocol, which seed, whether its motion stays in the scan,
and the GT of a sub-combination."""

from __future__ import annotations

import zlib
from dataclasses import replace

import numpy as np

from ..errors import InputError
from ..groundtruth import GroundTruth, contact_ground_truth, paper_ground_truth
from ..model import ParticleModel
from .case import PreparedCase
from .config import CaseConfig

#: Largest share of the pancreas a ground truth may move out of the imaged volume.
MAX_OUTSIDE_SHARE = 0.2


def make_ground_truth(prep: PreparedCase, cfg: CaseConfig, callback=None) -> GroundTruth:
    """Simulate the GT of ``cfg.protocol`` on the case's full model (every organ present); ``callback`` is
    called every step of the simulation (progress)."""
    solver = cfg.solver if cfg.gt_contact is None else replace(cfg.solver, contact=cfg.gt_contact)
    if cfg.protocol == "paper":
        return paper_ground_truth(prep.full_model, cfg.deformation, literal=cfg.literal, perturb=cfg.perturb,
                                  seed=cfg.phantom_seed, centre_mm=prep.centre_mm, solver_config=solver, device=cfg.device,
                                  callback=callback)
    gt = contact_ground_truth(prep.full_model, seed=contact_seed(prep, cfg), perturb=cfg.perturb, solver_config=solver,
                              device=cfg.device, callback=callback, wait_settled=cfg.gt_wait_settled,
                              max_steps=cfg.max_steps if cfg.gt_wait_settled else 4000)
    check_inside_imaged_volume(prep, gt)
    return gt


def contact_seed(prep: PreparedCase, cfg: CaseConfig) -> int:
    """The contact scenario's seed, from the case (its name), the phantom seed and the scenario number:
    scenario 3 differs from case to case (before, every real case got the same 6 scenarios)."""
    return zlib.crc32(prep.case.name.encode()) % 100_000 + cfg.phantom_seed + 31 * cfg.deformation


def check_inside_imaged_volume(prep: PreparedCase, gt: GroundTruth) -> None:
    """:class:`InputError` when the GT moves more than :data:`MAX_OUTSIDE_SHARE` of the pancreas out of the
    scan: the protocol's motion is not plausible for the imaged region (a scan cut close to the pancreas)."""
    geo = prep.input_geometry
    pan = gt.model.organ_slice("pancreas")
    ijk = geo.world_to_index(gt.positions_mm[pan])
    outside = np.any((ijk < -0.5) | (ijk > np.asarray(geo.size) - 0.5), axis=1)
    share = float(outside.mean())
    if share > MAX_OUTSIDE_SHARE:
        ext0 = np.ptp(gt.model.positions_mm[pan], axis=0).round(0).tolist()
        ext = np.ptp(gt.positions_mm[pan], axis=0).round(0).tolist()
        raise InputError(f"the {gt.protocol} ground truth moves {share:.0%} of the pancreas out of the imaged volume "
                         f"(its extent goes from {ext0} to {ext} mm): the scan does not cover enough around the pancreas "
                         "for this motion; use a scan that extends further beyond it, or the paper protocol")


def gt_for_model(gt: GroundTruth, model: ParticleModel) -> np.ndarray:
    """GT positions of ``model``'s particles (a sub-combination of the GT model, same order)."""
    keep = np.isin(gt.model.organ_index, [gt.model.organs.index(o) for o in model.organs])
    return gt.positions_mm[keep]
