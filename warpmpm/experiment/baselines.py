"""The baselines scored beside every estimate.

- ``initial``: no motion (the planning positions).
- ``propagate``: the first driving slice's in-plane motion applied to every particle (what copying the
  slice's motion to the whole volume gives; nearly exact under the paper protocol, whose GT applies
  one 2D affine to every slice). With organ-aware registration targets each organ takes its own motion
  on the slice (the same information as the estimate), and ``propagate_affine`` is the whole slice's; beside
  the ``gt`` / ``gt-inplane`` ceilings each organ takes its in-plane affine fitted to its true motion on the
  slice (a perfect organ-aware registration's). With several planes (registered, ``gt`` or ``gt-inplane``),
  ``propagate_planes`` moves every particle by all planes' motions combined (each plane's in-plane components,
  averaged where planes share a direction): the estimate's whole information.
- ``volume_registration``: 3D affine registration of the planning volume to the GT volume (the
  paper's elastix comparison; it needs the whole 3D volume at time t, which a cine MR does not give).
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from ..groundtruth import GroundTruth
from ..model import ParticleModel
from ..registration import register_volumes_affine
from ..slices import DrivingSlice, InPlaneAffine, in_plane_axes
from ..targets import field_motion
from .capture import planning_and_gt_volumes
from .case import PreparedCase

__all__ = ["propagate", "UNCERTAIN_MM", "volume_registration"]


def propagate(model: ParticleModel, s: DrivingSlice, affine: InPlaneAffine, centre_mm: np.ndarray,
              organ_affines: dict | None = None, field=None, organ_fields: dict | None = None) -> np.ndarray:
    """Every particle moved by the slice's in-plane motion (mm), extruded along the slice normal; with
    ``organ_affines`` (organ-aware registration) each organ's particles take their organ's motion on the
    slice, the organs absent from it the whole slice's: the same information the estimate is driven with.
    With ``organ_fields`` (organ -> deformable motion) an organ's particles take the motion of their point of
    the slice in their organ's field."""
    e_u, e_v = in_plane_axes(model, s.orientation)
    if field is not None:  # a deformable slice motion: every particle takes the motion of its point of the slice
        return field_motion(field, model.positions_mm, e_u, e_v, centre_mm)
    out = affine.apply(model.positions_mm, e_u, e_v, centre_mm)
    for organ, aff in (organ_affines or {}).items():
        sel = model.organ_slice(organ)
        out[sel] = aff.apply(model.positions_mm[sel], e_u, e_v, centre_mm)
    for organ, f in (organ_fields or {}).items():
        sel = model.organ_slice(organ)
        out[sel] = field_motion(f, model.positions_mm[sel], e_u, e_v, centre_mm)
    return out


#: Two volume registrations of one case that disagree by more than this (mm, mean over the model's
#: particles) mark the baseline as uncertain in the table.
UNCERTAIN_MM = 2.0


def volume_registration(prep: PreparedCase, gt: GroundTruth, model: ParticleModel) -> tuple[np.ndarray, dict]:
    """Positions (mm) of ``model``'s particles moved by the 3D affine registered from the planning to the
    GT volume, and what happened (``wall_s``, ``fallback_to_identity``, ``disagreement_mm``, ``uncertain``).

    The result is the paper's elastix set-up: both volumes masked to the organs in use (planning contour on
    the planning image, GT contour on the GT image), the metric over the dilated GT region. That set-up
    fails silently on the paper's expansions (CT sample, deformations 2, 4, 6, 8: 5.8-8.4 mm against
    0.6-0.9 on the others), and no image metric tells the failures apart (measured: choosing by the fit of
    either preparation picks the wrong one). So a second registration of the unmasked volumes, the metric
    over the same region, checks it: when the two disagree by more than :data:`UNCERTAIN_MM` on the
    model's particles, the row is marked uncertain (the CT's expansions disagree by 7.8-11.3 mm, its other
    deformations by 1.5-2.1).
    """
    case = prep.case
    values = {o: case.label_map[o] for o in gt.model.organs}
    planning, target = planning_and_gt_volumes(case, gt)
    use = [values[o] for o in model.organs]
    gt_mask = np.isin(gt.label_map(values), use)
    m_img = case.geometry.apply_to(sitk.GetImageFromArray(gt_mask.astype(np.uint8)))
    mask = sitk.GetArrayFromImage(sitk.BinaryDilate(m_img, [3, 3, 1])).astype(bool)
    reg = register_volumes_affine(np.where(np.isin(case.labels, use), planning, 0.0), np.where(gt_mask, target, 0.0),
                                  case.geometry, mask=mask)
    check = register_volumes_affine(planning, target, case.geometry, mask=mask)
    moved = reg.apply(model.positions_mm)
    disagreement = float(np.linalg.norm(moved - check.apply(model.positions_mm), axis=1).mean())
    return moved, {"wall_s": reg.wall_s, "fallback_to_identity": reg.fallback, "disagreement_mm": disagreement,
                   "uncertain": bool(disagreement > UNCERTAIN_MM)}
