"""The pseudo ground truth of a run: which protocol, which seed, whether its motion stays in the scan,
and the GT of a sub-combination."""

from __future__ import annotations

import os
import time
import zlib
from dataclasses import replace

import numpy as np

from ..errors import InputError
from ..groundtruth import GroundTruth, contact_ground_truth, paper_ground_truth
from ..model import ParticleModel
from .case import PreparedCase
from .config import CaseConfig

__all__ = ["MAX_OUTSIDE_SHARE", "make_ground_truth", "field_ground_truth", "contact_seed",
           "check_inside_imaged_volume", "gt_for_model"]

#: Largest share of the pancreas a ground truth may move out of the imaged volume.
MAX_OUTSIDE_SHARE = 0.2


def make_ground_truth(prep: PreparedCase, cfg: CaseConfig, callback=None) -> GroundTruth:
    """Simulate the GT of ``cfg.protocol`` on the case's full model (every organ present); ``callback`` is
    called every step of the simulation (progress)."""
    if cfg.protocol == "field":
        gt = field_ground_truth(prep, cfg.truth_field)
        check_inside_imaged_volume(prep, gt)
        return gt
    solver = cfg.solver if cfg.gt_contact is None else replace(cfg.solver, explicit=replace(cfg.solver.explicit, contact=cfg.gt_contact))
    if cfg.protocol == "paper":
        return paper_ground_truth(prep.full_model, cfg.deformation, literal=cfg.literal, perturb=cfg.perturb,
                                  seed=cfg.phantom_seed, centre_mm=prep.centre_mm, solver_config=solver, device=cfg.device,
                                  callback=callback)
    gt = contact_ground_truth(prep.full_model, seed=contact_seed(prep, cfg), perturb=cfg.perturb, solver_config=solver,
                              device=cfg.device, callback=callback, wait_settled=cfg.gt_wait_settled,
                              max_steps=cfg.max_steps if cfg.gt_wait_settled else 4000)
    check_inside_imaged_volume(prep, gt)
    return gt


def field_ground_truth(prep: PreparedCase, path: str) -> GroundTruth:
    """The truth of a displacement field on the planning grid (:mod:`warpmpm.fields`): every particle moved by the
    field at its planning position; the captured volume for the registration targets is the planning image warped
    by the field (made once, kept in ``gt.cache``)."""
    from ..fields import read_field, sample_field, warp_volume

    geo = prep.input_geometry
    ox, oy, oz = prep.offset
    nz, ny, nx = prep.case.labels.shape
    organs = np.zeros(tuple(geo.size[::-1]), bool)
    organs[oz:oz + nz, oy:oy + ny, ox:ox + nx] = np.isin(prep.case.labels, [prep.case.label_map[o] for o in prep.full_model.organs])
    t0 = time.perf_counter()
    f = read_field(path, geo, organs)
    model = prep.full_model
    u = sample_field(f, geo, model.positions_mm)
    gt = GroundTruth(model, model.positions_mm + u, "field",
                     params={"truth_field": os.path.abspath(path), "made_by": "a displacement field (see the field's own record)",
                             "pancreas_mean_mm": float(np.linalg.norm(u[model.organ_slice("pancreas")], axis=1).mean())})
    crop = f[oz:oz + nz, oy:oy + ny, ox:ox + nx]
    if prep.case.image is not None:
        gt.cache["volumes"] = (prep.case, (prep.case.image, warp_volume(prep.case.image, crop, prep.case.geometry)))
    gt.wall_s = time.perf_counter() - t0
    record = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(path))), "truth.json")
    if os.path.exists(record):  # a make-truth series: say who made it
        import json

        with open(record) as fh:
            gt.params["made_by"] = json.load(fh).get("made_by", gt.params["made_by"])
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
        corners = geo.index_to_world(np.array([[-0.5 + (geo.size[a] * b[a]) for a in range(3)] for b in np.ndindex(2, 2, 2)]))

        def box(p):
            return "[" + ", ".join(f"{lo:.0f}..{hi:.0f}" for lo, hi in zip(p.min(0), p.max(0))) + "]"

        raise InputError(f"the {gt.protocol} ground truth moves {share:.0%} of the pancreas out of the imaged volume: the "
                         f"pancreas spans {box(gt.model.positions_mm[pan])} mm (x, y, z, world LPS) at planning and "
                         f"{box(gt.positions_mm[pan])} mm moved, the scan {box(corners)} mm; the scan does not cover enough "
                         "around the pancreas for this motion: use a scan that extends further beyond it, or the paper protocol")


def gt_for_model(gt: GroundTruth, model: ParticleModel) -> np.ndarray:
    """GT positions of ``model``'s particles (a sub-combination of the GT model, same order)."""
    keep = np.isin(gt.model.organ_index, [gt.model.organs.index(o) for o in model.organs])
    return gt.positions_mm[keep]
