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

import time
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from ..groundtruth import GroundTruth
from ..images import Geometry
from ..model import ParticleModel
from ..slices import copy_organ_motion, DrivingSlice, InPlaneAffine, in_plane_axes
from ..targets import field_motion
from .capture import planning_and_gt_volumes
from .case import PreparedCase

__all__ = ["propagate", "UNCERTAIN_MM", "VolumeRegistration", "register_volumes_affine", "volume_registration"]


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
    organ_of = np.asarray(model.organs)[model.organ_index]
    out = copy_organ_motion(model.positions_mm, organ_of, e_u, e_v, centre_mm, affine, organ_affines)
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


@dataclass
class VolumeRegistration:
    """3D affine mapping planning points to GT points: ``y = M x + b`` (mm)."""

    matrix: np.ndarray
    offset_mm: np.ndarray
    wall_s: float
    metric: float
    fallback: bool = False

    def apply(self, points_mm: np.ndarray) -> np.ndarray:
        return np.asarray(points_mm) @ self.matrix.T + self.offset_mm


def register_volumes_affine(planning: np.ndarray, target: np.ndarray, geometry: Geometry, *, mask: np.ndarray | None = None,
                            iterations: int = 200, levels: tuple[int, ...] = (4, 2, 1)) -> VolumeRegistration:
    """3D affine registration of the planning volume onto the target (GT) volume.

    Both arrays are (z, y, x) on ``geometry``; ``mask`` (target grid, boolean) restricts the metric
    (mean squares: the two volumes share a modality). Returns the planning->target point mapping.
    """
    fixed = geometry.apply_to(sitk.GetImageFromArray(target.astype(np.float32)))
    moving = geometry.apply_to(sitk.GetImageFromArray(planning.astype(np.float32)))
    reg = sitk.ImageRegistrationMethod()
    reg.SetMetricAsMeanSquares()
    reg.SetMetricSamplingStrategy(reg.NONE)
    if mask is not None:
        reg.SetMetricFixedMask(geometry.apply_to(sitk.GetImageFromArray(mask.astype(np.uint8))))
    tx = sitk.AffineTransform(3)
    if mask is not None and mask.any():
        kk, jj, ii = np.nonzero(mask)
        centre = geometry.index_to_world(np.array([[ii.mean(), jj.mean(), kk.mean()]]))[0]
    else:
        centre = geometry.center_mm()
    tx.SetCenter(centre.tolist())
    reg.SetInitialTransform(tx, inPlace=True)
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetOptimizerAsRegularStepGradientDescent(learningRate=2.0, minStep=1e-4, numberOfIterations=iterations,
                                                 relaxationFactor=0.6)
    reg.SetOptimizerScalesFromPhysicalShift()
    reg.SetShrinkFactorsPerLevel(list(levels))
    reg.SetSmoothingSigmasPerLevel([max(0.0, f / 2.0) for f in levels])
    reg.SmoothingSigmasAreSpecifiedInPhysicalUnitsOff()
    t0 = time.perf_counter()
    reg.Execute(fixed, moving)
    wall = time.perf_counter() - t0
    # tx maps target points to planning points: x = M (y - c) + c + tr. Invert: y = M^-1 (x - c - tr) + c.
    M = np.asarray(tx.GetMatrix()).reshape(3, 3)
    tr = np.asarray(tx.GetTranslation())
    c = np.asarray(tx.GetCenter())
    # The metric at the result, at full resolution; a result worse than no motion (a diverged
    # optimisation) is replaced by the identity and flagged.
    check = sitk.ImageRegistrationMethod()
    check.SetMetricAsMeanSquares()
    if mask is not None:
        check.SetMetricFixedMask(geometry.apply_to(sitk.GetImageFromArray(mask.astype(np.uint8))))
    check.SetInitialTransform(tx)
    check.SetInterpolator(sitk.sitkLinear)
    final_metric = check.MetricEvaluate(fixed, moving)
    identity = sitk.ImageRegistrationMethod()
    identity.SetMetricAsMeanSquares()
    if mask is not None:
        identity.SetMetricFixedMask(geometry.apply_to(sitk.GetImageFromArray(mask.astype(np.uint8))))
    identity.SetInitialTransform(sitk.AffineTransform(3))
    identity.SetInterpolator(sitk.sitkLinear)
    identity_metric = identity.MetricEvaluate(fixed, moving)
    # A diverged optimisation maps the organs off the image, where ITK drops the samples and the
    # metric of the few left is misleadingly small: require most mask points to land inside.
    kk, jj, ii = np.nonzero(mask) if mask is not None else np.nonzero(np.ones(target.shape, dtype=bool))
    pts = geometry.index_to_world(np.stack([ii, jj, kk], axis=1)[:: max(1, len(ii) // 20000)])
    mapped = geometry.world_to_index((pts - c) @ M.T + c + tr)
    inside = float(np.mean(np.all((mapped >= -0.5) & (mapped <= np.asarray(geometry.size) - 0.5), axis=1)))
    ok = (np.all(np.isfinite(M)) and np.all(np.isfinite(tr)) and abs(np.linalg.det(M)) > 1e-3
          and final_metric <= identity_metric and inside >= 0.8)
    if not ok:
        return VolumeRegistration(np.eye(3), np.zeros(3), wall, float(identity_metric), fallback=True)
    Minv = np.linalg.inv(M)
    return VolumeRegistration(Minv, c - Minv @ (c + tr), wall, float(final_metric))
