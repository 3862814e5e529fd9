"""The planning image as a particle state shows it.

A state of the particle model (positions, mm) moves the planning image: each voxel takes the intensity
found where the tissue now at it came from. The backward displacement ``planning - now`` is scattered from
the particles at their current positions and filled by normalised Gaussian smoothing at two scales:
``sigma_mm`` near the organs, blended into a ``far_sigma_mm`` extrapolation elsewhere, so the tissue around
the organs moves with them instead of tearing at their boundaries (the paper deforms whole slices); beyond the
extrapolation's reach (where its weights are lost in the filter's error) the tissue takes the particles' mean
displacement.

:func:`warp_volume` warps the whole volume (the ground truths' captured images). :func:`render_plane` renders
only what a cine frame images: the field is built on the slab of the planning grid around the frame's plane
(its thickness plus three ``sigma_mm``), and the image is sampled on the frame's pixels, averaged over the
slice thickness (a box slice profile, by the midpoint rule on sub-planes no further apart than the
planning grid's spacing along the normal: exactly the box over the voxels when the thickness is a whole number
of voxels, as the synthetic cine frames are made, :func:`warpmpm.experiment.cine_series.slab_average`). The cine tracker registers each frame against its current estimate
rendered so (:class:`~warpmpm.tracker.TrackerConfig`): the frame's registration then measures only what the
estimate still misses, not the motion since an earlier frame, so registration errors do not accumulate
frame after frame, and motion through the plane that another plane has measured is in the reference.
"""

from __future__ import annotations

import math

import numpy as np
import SimpleITK as sitk

from .errors import InputError
from .images import Case, Geometry
from .model import ParticleModel, voxelize


def _check_sigmas(sigma_mm: float, far_sigma_mm: float) -> None:
    for name, v in (("sigma_mm", sigma_mm), ("far_sigma_mm", far_sigma_mm)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise InputError(f"rendering: {name} must be a positive number of mm, got {v!r}")


def backward_displacement(geometry: Geometry, planning_mm: np.ndarray, positions_mm: np.ndarray, sigma_mm: float = 4.0,
                          far_sigma_mm: float = 25.0) -> sitk.Image:
    """The backward displacement field (mm, ``planning - now``) on ``geometry`` (a vector image), from particles
    that moved from ``planning_mm`` to ``positions_mm`` (N, 3); particles outside the grid are left out (module
    docstring for the fill)."""
    _check_sigmas(sigma_mm, far_sigma_mm)
    u = np.asarray(positions_mm, dtype=np.float64) - np.asarray(planning_mm, dtype=np.float64)
    ijk = np.rint(geometry.world_to_index(positions_mm)).astype(np.int64)
    inside = np.all((ijk >= 0) & (ijk < np.asarray(geometry.size)), axis=1)
    ijk, u = ijk[inside], u[inside]
    shape = geometry.size[::-1]
    acc = np.zeros(shape + (4,), dtype=np.float64)  # count, then the three components' sums
    np.add.at(acc, (ijk[:, 2], ijk[:, 1], ijk[:, 0]), np.hstack([np.ones((len(u), 1)), -u]))
    stacked = geometry.apply_to(sitk.GetImageFromArray(acc.astype(np.float32), isVector=True))

    mean_u = acc[..., 1:].sum(axis=(0, 1, 2)) / max(len(u), 1)  # the particles' mean backward displacement

    def fill(sigma):
        """The normalised fill at ``sigma`` and the smoothed count (one smoothing of all four components). Where
        the smoothed count is below 1e-3 of its peak (some 3.7 sigma from every particle) the recursive filter's
        error is of the order of the count itself and the ratio is noise (measured: up to 1e6 mm on 5 % of the
        phantom's voxels and 27 % of the MR sample's for a uniform translation, where the answer is the
        translation everywhere): the fill there is the particles' mean displacement instead."""
        sm = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(stacked, sigma)).astype(np.float64)
        count = sm[..., 0]
        valid = count > 1e-3 * max(float(count.max()), 1e-12)
        out = np.where(valid[..., None], sm[..., 1:] / np.where(valid, count, 1.0)[..., None], mean_u)
        return out, count

    near, den_near = fill(sigma_mm)
    far, _ = fill(far_sigma_mm)
    weight = np.clip(den_near / max(den_near.max(), 1e-12) * 4.0, 0.0, 1.0)[..., None]
    disp = sitk.GetImageFromArray((weight * near + (1.0 - weight) * far).astype(np.float64), isVector=True)
    return geometry.apply_to(disp)


def warp_volume(case: Case, planning_mm: np.ndarray, positions_mm: np.ndarray, sigma_mm: float = 4.0,
                far_sigma_mm: float = 25.0) -> np.ndarray:
    """The planning image warped by the particle motion ``planning_mm -> positions_mm``, as (z, y, x) float32."""
    if case.image is None:
        raise InputError(f"case {case.name} has no intensity image to warp")
    return warp_array(case.image, case.geometry, planning_mm, positions_mm, sigma_mm, far_sigma_mm)


def warp_array(volume: np.ndarray, geometry: Geometry, planning_mm: np.ndarray, positions_mm: np.ndarray, sigma_mm: float = 4.0,
               far_sigma_mm: float = 25.0) -> np.ndarray:
    """:func:`warp_volume` of a (z, y, x) ``volume`` on ``geometry``."""
    tx = sitk.DisplacementFieldTransform(backward_displacement(geometry, planning_mm, positions_mm, sigma_mm, far_sigma_mm))
    moving = geometry.apply_to(sitk.GetImageFromArray(np.asarray(volume, dtype=np.float32)))
    return sitk.GetArrayFromImage(sitk.Resample(moving, moving, tx, sitk.sitkLinear, 0.0)).astype(np.float32)


def slab_region(geometry: Geometry, plane_image: sitk.Image, normal: np.ndarray, half_width_mm: float) -> tuple[tuple, tuple] | None:
    """Voxel index bounds ``lo <= ijk < hi`` of the box of ``geometry`` holding every point within
    ``half_width_mm`` of ``plane_image``'s pixels along ``normal`` (one voxel of padding); None when it misses
    the grid."""
    size = np.asarray(plane_image.GetSize())
    corners = []
    for c in np.ndindex(2, 2, 2):
        idx = [float(c[a] * (size[a] - 1)) for a in range(3)]
        corners.append(plane_image.TransformContinuousIndexToPhysicalPoint(idx))
    corners = np.asarray(corners)
    pts = np.vstack([corners + s * half_width_mm * np.asarray(normal) for s in (-1.0, 1.0)])
    ijk = geometry.world_to_index(pts)
    lo = np.maximum(np.floor(ijk.min(0)).astype(int) - 1, 0)
    hi = np.minimum(np.ceil(ijk.max(0)).astype(int) + 2, np.asarray(geometry.size))
    if np.any(hi <= lo):
        return None
    return tuple(int(v) for v in lo), tuple(int(v) for v in hi)


def render_plane(case: Case, planning_mm: np.ndarray, positions_mm: np.ndarray, plane_image: sitk.Image, normal: np.ndarray,
                 thickness_mm: float, sigma_mm: float = 4.0, far_sigma_mm: float = 25.0,
                 planning_image: sitk.Image | None = None) -> sitk.Image:
    """The planning image moved by ``planning_mm -> positions_mm`` as a frame on ``plane_image``'s pixels would
    show it (an image on ``plane_image``'s grid, float32): the field on the slab around the plane only, the
    intensity averaged over ``thickness_mm`` along ``normal`` (module docstring). ``planning_image``: the case's
    intensity image, when the caller keeps one (frame after frame it is not rebuilt from the array)."""
    if case.image is None:
        raise InputError(f"case {case.name} has no intensity image to render")
    if not (math.isfinite(thickness_mm) and thickness_mm > 0):
        raise InputError(f"rendering: the slice thickness must be a positive number of mm, got {thickness_mm!r}")
    _check_sigmas(sigma_mm, far_sigma_mm)
    g = case.geometry
    normal = np.asarray(normal, dtype=np.float64)
    region = slab_region(g, plane_image, normal, thickness_mm / 2 + 3.0 * sigma_mm)
    if region is None:
        raise InputError("rendering: the frame's plane does not cross the planning image")
    sub = g.crop(*region)
    field = backward_displacement(sub, planning_mm, positions_mm, sigma_mm, far_sigma_mm)
    tx = sitk.DisplacementFieldTransform(field)
    moving = case.intensity_image() if planning_image is None else planning_image
    # the planning grid's spacing along the normal: sub-planes no further apart, at half-voxel offsets when the
    # thickness is a whole number of voxels, make the linear samples' mean the box over the voxels exactly
    step_mm = 1.0 / float(np.linalg.norm((g.direction_matrix.T @ normal) / np.asarray(g.spacing_mm)))
    n = max(1, int(math.ceil(thickness_mm / step_mm - 1e-6)))
    acc = None
    for i in range(n):
        offset = ((i + 0.5) / n - 0.5) * thickness_mm
        ref = sitk.Image(plane_image.GetSize(), sitk.sitkFloat32)
        ref.SetSpacing(plane_image.GetSpacing())
        ref.SetDirection(plane_image.GetDirection())
        ref.SetOrigin(tuple(float(v) for v in np.asarray(plane_image.GetOrigin()) + offset * normal))
        arr = sitk.GetArrayFromImage(sitk.Resample(moving, ref, tx, sitk.sitkLinear, 0.0))
        acc = arr if acc is None else acc + arr
    out = sitk.GetImageFromArray((acc / n).astype(np.float32))
    out.CopyInformation(plane_image)
    return out


def particle_label_map(model: ParticleModel, positions_mm: np.ndarray, label_values: dict[str, int]) -> np.ndarray:
    """The label map (z, y, x) on the planning grid of particles at ``positions_mm`` (model order).

    Each organ is voxelised on the grid the particles were laid on (:attr:`ParticleModel.particle_grid`),
    stomach first and pancreas last as the phantom's labels are drawn, then resampled onto the planning
    grid (nearest neighbour) when that grid is another (an isotropic lattice of a thick-slice scan).
    """
    g = model.particle_grid
    out = np.zeros(g.size[::-1], dtype=np.int32)
    for organ in ("stomach", "left_kidney", "duodenum", "pancreas"):
        if organ in model.organs:
            out[voxelize(positions_mm, g, model.organ_slice(organ), model.sampling_step)] = label_values[organ]
    if model.lattice is None:
        return out
    img = model.lattice.apply_to(sitk.GetImageFromArray(out))
    ref = sitk.Image([int(v) for v in model.geometry.size], sitk.sitkInt32)
    model.geometry.apply_to(ref)
    return sitk.GetArrayFromImage(sitk.Resample(img, ref, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkInt32))
