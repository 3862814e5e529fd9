"""Making images from particles: the planning image as a particle state shows it (a whole volume, or one cine plane's
slab), label maps from particles, the slice a device images and the masks of organs on a slice.

A state of the particle model (positions, mm) moves the planning image: each voxel takes the intensity
found where the tissue now at it came from. The backward displacement ``planning - now`` is scattered from
the particles at their current positions and filled by normalised Gaussian smoothing at two scales:
``sigma_mm`` near the organs, blended into a ``far_sigma_mm`` extrapolation elsewhere, so the tissue around
the organs moves with them instead of tearing at their boundaries (the paper deforms whole slices); beyond the
extrapolation's reach (where its weights are lost in the filter's error) the tissue takes the particles' mean
displacement, blended in smoothly (:func:`_normalise`).

The far fill is smoothed on cells of a quarter of its width, not on every voxel (:func:`backward_displacement`).
:func:`warp_volume` warps the whole volume (the ground truths' captured images). :func:`render_plane` renders
only what a cine frame images: the field is built on the slab of the planning grid around the frame's plane
(its thickness plus three ``sigma_mm``; the far fill on the whole grid's coarse cells, so it sees what lies beyond
the slab), and the image is sampled on the frame's pixels, averaged over the
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
from .slices import extract_slice

__all__ = ["backward_displacement", "FAR_CELLS_PER_SIGMA", "scatter_displacements", "warp_volume", "warp_array", "warp_image",
           "slab_region", "render_plane", "particle_label_map", "capture_slice", "slice_mask", "organ_intensity_volume"]


def _check_sigmas(sigma_mm: float, far_sigma_mm: float) -> None:
    for name, v in (("sigma_mm", sigma_mm), ("far_sigma_mm", far_sigma_mm)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise InputError(f"rendering: {name} must be a positive number of mm, got {v!r}")


def backward_displacement(geometry: Geometry, planning_mm: np.ndarray, positions_mm: np.ndarray, sigma_mm: float = 4.0,
                          far_sigma_mm: float = 25.0, far_geometry: Geometry | None = None,
                          out_geometry: Geometry | None = None) -> sitk.Image:
    """The backward displacement field (mm, ``planning - now``) on ``geometry`` (a vector image), from particles
    that moved from ``planning_mm`` to ``positions_mm`` (N, 3); particles outside the grid are left out (module
    docstring for the fill).

    The far fill is smoothed on cells of about ``far_sigma_mm`` / :data:`FAR_CELLS_PER_SIGMA` (blocks of whole voxels:
    4 x 4 x 2 of the phantom's 1.33 x 1.33 x 3 mm voxels at the default 25 mm; the particles scattered onto the blocks
    directly, which is the blocks' sum of the fine scatter) and interpolated linearly onto ``geometry``.
    ``far_geometry``: the grid the far fill is computed on, one of which ``geometry`` is a crop (:meth:`Geometry.crop`;
    a grid that is not, or does not hold it, is refused);
    :func:`render_plane` passes the whole planning grid, so the far fill of a frame's slab sees the particles beyond
    the slab, as the whole-volume warp's does. Default: ``geometry``. Measured on the default phantom under a smooth
    non-rigid motion (``benchmarks/rendering_speed.py``): within 8 mm of the particles, where the near fill weighs,
    the whole-volume field is within 0.016 mm of the fill on every voxel (0.09 mm within 40 mm; several mm only
    60 mm and more from every particle, where both fall back to the particles' mean displacement at slightly
    different places); :func:`warp_volume` takes 0.56-0.64x the time (docs/performance.md).

    ``out_geometry``: the grid the field is returned on, a crop of ``geometry`` (default: ``geometry`` itself); the
    near fill is still that of all of ``geometry`` (its weights' peak too). When the crop cuts one axis only (a frame's
    thickness out of its slab), the near fill is smoothed along that axis over ``geometry`` and along the other two
    over the crop only (the Gaussian is separable: the same numbers to float32 rounding, at about half the smoothing
    for a sagittal frame's slab; with the coarse far fill a frame's :func:`render_plane` takes 0.44-0.55x the time over four runs)."""
    _check_sigmas(sigma_mm, far_sigma_mm)
    positions_mm = np.asarray(positions_mm, dtype=np.float64)
    u = positions_mm - np.asarray(planning_mm, dtype=np.float64)
    out_g = geometry if out_geometry is None else out_geometry
    cut = _crop_offset(geometry, out_g)
    fg = geometry if far_geometry is None else far_geometry
    inner = np.asarray(_crop_offset(fg, geometry))
    offset = tuple(int(v) for v in inner + cut)  # out_g's first voxel in fg
    ijk = np.rint(geometry.world_to_index(positions_mm)).astype(np.int64)  # each particle's nearest voxel, once
    near_acc, near_range = scatter_displacements(ijk, geometry.size, u, (1, 1, 1))
    near, den_near, peak = _fill_near(geometry, near_acc, sigma_mm, near_range, cut, out_g.size)
    # whole voxels a coarse cell, leaving the 4 cells a side the recursive filter needs
    factors = tuple(max(1, min(int(far_sigma_mm / FAR_CELLS_PER_SIGMA / s), n // 4)) for s, n in zip(fg.spacing_mm, fg.size))
    far_acc, far_range = scatter_displacements(ijk + inner, fg.size, u, factors)
    far_coarse, _ = _fill(_coarse_geometry(fg, factors), far_acc, far_sigma_mm, far_range, blend=True)
    far = _upsample(far_coarse, factors, offset, near.shape[:3])
    weight = np.clip(den_near * (4.0 / max(peak, 1e-12)), 0.0, 1.0)[..., None]
    near -= far  # near's weight times near, the rest far: far + weight (near - far), in place
    near *= weight
    near += far
    disp = sitk.GetImageFromArray(near.astype(np.float64), isVector=True)
    return out_g.apply_to(disp)


def _fill_near(geometry: Geometry, acc: np.ndarray, sigma: float, u_range: np.ndarray, cut, size):
    """:func:`_fill` of ``acc`` on ``geometry`` returned on its crop of ``size`` voxels from voxel ``cut`` (x, y, z),
    and the smoothed count's peak over all of ``geometry``. A crop along one axis only is smoothed along that axis
    first, over everything, and along the other two over the crop (the count alone over everything, for its peak)."""
    cut_axes = [a for a in range(3) if size[a] != geometry.size[a]]
    if len(cut_axes) != 1:  # nothing cut, or several axes: smooth everything, then cut
        out, count = _fill(geometry, acc, sigma, u_range)
        z, y, x = (slice(c, c + n) for c, n in zip(cut[::-1], size[::-1]))
        return out[z, y, x], count[z, y, x], float(count.max())
    a = cut_axes[0]
    zero = sitk.RecursiveGaussianImageFilter.ZeroOrder
    first = sitk.RecursiveGaussian(geometry.apply_to(sitk.GetImageFromArray(acc, isVector=True)), sigma, False, zero, a)
    count = sitk.VectorIndexSelectionCast(first, 0)
    index = [slice(None)] * 3
    index[a] = slice(cut[a], cut[a] + size[a])
    part = first[tuple(index)]
    for b in range(3):
        if b != a:
            count = sitk.RecursiveGaussian(count, sigma, False, zero, b)
            part = sitk.RecursiveGaussian(part, sigma, False, zero, b)
    peak = float(sitk.GetArrayViewFromImage(count).max())
    out, den = _normalise(sitk.GetArrayFromImage(part), peak, u_range)
    return out, den, peak


#: cells of the far fill's coarse grid per ``far_sigma_mm`` (:func:`backward_displacement`), at least: a Gaussian of
#: that width sampled at a quarter of it and interpolated linearly stays within ~1 % of itself
FAR_CELLS_PER_SIGMA = 4.0


def _crop_offset(outer: Geometry, inner: Geometry) -> tuple[int, int, int]:
    """The voxel index (x, y, z) of ``inner``'s first voxel in ``outer``, of which it must be a crop (InputError
    otherwise)."""
    off = outer.world_to_index(np.asarray(inner.origin_mm, dtype=np.float64)[None, :])[0]
    same = (np.allclose(outer.spacing_mm, inner.spacing_mm, rtol=1e-6) and np.allclose(outer.direction, inner.direction, atol=1e-9)
            and np.allclose(off, np.rint(off), atol=1e-3))
    off = np.rint(off).astype(np.int64)
    if not same or np.any(off < 0) or np.any(off + np.asarray(inner.size) > np.asarray(outer.size)):
        raise InputError("rendering: a field's grid must be a crop of the grid it is computed from (same spacing and "
                         f"directions, inside it, origin on one of its voxels): {inner.size} voxels from voxel "
                         f"{off.tolist()} of a {outer.size} grid")
    return tuple(int(v) for v in off)


def scatter_displacements(ijk: np.ndarray, size, u: np.ndarray, factors) -> tuple[np.ndarray, np.ndarray]:
    """Each particle's count and backward displacement ``-u`` added at its nearest voxel ``ijk`` (N, 3: x, y, z) of a
    grid of ``size`` voxels (the rendering's fills; the tracker's forward field passes ``-u``) (z, y, x, 4: count, then the three components' sums; particles outside left out), summed
    over blocks of ``factors`` (x, y, z) voxels; and the mean, least and largest backward displacement of the particles
    inside the grid (3 x 3: rows mean, least, largest; :func:`_normalise`)."""
    inside = np.all((ijk >= 0) & (ijk < np.asarray(size)), axis=1)
    ijk, u = ijk[inside] // np.asarray(factors), u[inside]
    shape = tuple(-(-n // f) for n, f in zip(size, factors))[::-1]
    flat = np.ravel_multi_index((ijk[:, 2], ijk[:, 1], ijk[:, 0]), shape)
    n = int(np.prod(shape))
    acc = np.empty(shape + (4,), dtype=np.float32)
    acc[..., 0] = np.bincount(flat, minlength=n).reshape(shape)
    for c in range(3):
        acc[..., c + 1] = np.bincount(flat, weights=-u[:, c], minlength=n).reshape(shape)
    if len(u) == 0:
        return acc, np.zeros((3, 3), dtype=np.float32)
    return acc, np.stack([-u.mean(axis=0), (-u).min(axis=0), (-u).max(axis=0)]).astype(np.float32)


def _coarse_geometry(geometry: Geometry, factors) -> Geometry:
    """The grid of :func:`scatter_displacements`'s blocks of ``factors`` voxels: its voxel centres are the blocks' centres."""
    fx, fy, fz = factors
    origin = geometry.index_to_world(np.array([[(fx - 1) / 2, (fy - 1) / 2, (fz - 1) / 2]]))[0]
    size = tuple(-(-n // f) for n, f in zip(geometry.size, factors))
    return Geometry(size, tuple(float(s * f) for s, f in zip(geometry.spacing_mm, factors)), tuple(float(v) for v in origin),
                    geometry.direction)


def _fill(geometry: Geometry, acc: np.ndarray, sigma: float, u_range: np.ndarray, blend: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The normalised fill at ``sigma`` of the scattered count and sums ``acc`` (z, y, x, 4) on ``geometry``, and the
    smoothed count (one smoothing of all four components), made safe where the count is small (:func:`_normalise`)."""
    stacked = geometry.apply_to(sitk.GetImageFromArray(acc, isVector=True))
    sm = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(stacked, sigma))
    return _normalise(sm, float(sm[..., 0].max()), u_range, blend)


#: smoothed count, as a fraction of its peak, below which a fill is the particles' mean displacement; with ``blend``
#: (the far fill) it is the normalised fill above ``FILL_TRUST`` and the two are blended between (:func:`_normalise`)
FILL_FLOOR, FILL_TRUST = 1e-3, 3e-2


def _normalise(sm: np.ndarray, peak: float, u_range: np.ndarray, blend: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The smoothed sums over the smoothed count, and the count.

    A normalised Gaussian fill is a weighted mean of the particles' displacements, but the recursive filter's tails
    are not Gaussian (they go negative), so far from every particle the ratio is noise: measured on the default
    phantom under a smooth motion (the far fill), up to 0.3 mm outside the particles' range of displacements where
    the count is 3e-3 to 1e-2 of its peak, 3 mm at 1e-3 to 3e-3, 40 mm to 1e5 mm below. So the ratio is clamped to the
    particles' range (``u_range``: rows mean, least, largest, from :func:`scatter_displacements`), which a weighted mean with
    positive weights never leaves, and is the particles' mean displacement below :data:`FILL_FLOOR` of ``peak``.
    ``blend`` (the far fill, whose value is the field there): between :data:`FILL_FLOOR` and :data:`FILL_TRUST` the
    two are blended, smoothly in log count (a switch to the mean at the floor jumped by up to 3.8 mm between
    neighbouring voxels some 60 mm from every particle); the field changes there no faster than near the organs (``tests/test_rendering.py``). The near fill needs no blend: it weighs at
    most 4x its relative count (0.004 at the floor) against the far fill."""
    count = sm[..., 0]
    rel = count * (1.0 / max(peak, 1e-12))
    valid = rel > FILL_FLOOR
    out = sm[..., 1:] / np.where(valid, count, 1.0)[..., None]
    np.clip(out, u_range[1], u_range[2], out=out)
    out[~valid] = u_range[0]
    if blend:
        ramp = valid & (rel < FILL_TRUST)
        t = (np.log10(rel[ramp]) - math.log10(FILL_FLOOR)) / math.log10(FILL_TRUST / FILL_FLOOR)
        w = (t * t * (3.0 - 2.0 * t)).astype(out.dtype)[:, None]  # smoothstep: 0 at the floor, 1 at trust
        out[ramp] = u_range[0] + w * (out[ramp] - u_range[0])
    return out, count


def _upsample(field: np.ndarray, factors, offset, shape) -> np.ndarray:
    """A (z, y, x, c) ``field`` on :func:`_coarse_geometry`'s grid interpolated linearly onto the voxels ``offset +
    (0..shape)`` (x, y, z offset; z, y, x shape) of the fine grid, axis by axis (the nearest coarse value beyond the
    outermost coarse voxel centres). The coarse cells the voxels need are cut out first."""
    axes = []
    for f, o, n, m in zip(factors[::-1], offset[::-1], shape, field.shape[:3]):  # z, y, x
        c = np.clip((np.arange(n) + o - (f - 1) / 2.0) / f, 0.0, m - 1)  # each fine voxel's continuous coarse index
        i0 = np.minimum(np.floor(c).astype(np.int64), max(m - 2, 0))
        i1 = np.minimum(i0 + 1, m - 1)
        axes.append((i0, i1, c - i0))
    out = field[tuple(slice(int(i0.min()), int(i1.max()) + 1) for i0, i1, _ in axes)]
    for axis, (i0, i1, w) in enumerate(axes):
        lo = int(i0.min())
        w = w.astype(out.dtype).reshape([-1 if k == axis else 1 for k in range(out.ndim)])
        a0 = np.take(out, i0 - lo, axis=axis)
        out = a0 + w * (np.take(out, i1 - lo, axis=axis) - a0) if np.any(w != 0) else a0
    return out


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
    # the far fill over what lies within three far sigmas of the slab (weights beyond: under 1.1 %); the field returned
    # on the box of the sub-planes only (one voxel of padding: slab_region)
    reach = slab_region(g, plane_image, normal, thickness_mm / 2 + 3.0 * far_sigma_mm)
    inner = slab_region(g, plane_image, normal, thickness_mm / 2)
    inner = tuple(np.maximum(inner[0], region[0])), tuple(np.minimum(inner[1], region[1]))
    field = backward_displacement(sub, planning_mm, positions_mm, sigma_mm, far_sigma_mm, far_geometry=g.crop(*reach),
                                  out_geometry=g.crop(*inner))
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


def warp_image(case: Case, model: ParticleModel, gt_positions_mm: np.ndarray, sigma_mm: float = 4.0,
               far_sigma_mm: float = 25.0) -> np.ndarray:
    """The planning image warped by the GT particle motion (z, y, x): :func:`warp_volume`
    (a backward field filled at ``sigma_mm`` near the organs and ``far_sigma_mm`` elsewhere)."""
    return warp_volume(case, model.positions_mm, gt_positions_mm, sigma_mm, far_sigma_mm)


# --------------------------------------------------------------------------------------------
# Slices and masks
# --------------------------------------------------------------------------------------------

def capture_slice(warped_volume: np.ndarray, geometry: Geometry, orientation: str, index: int, centre_mm: np.ndarray, *,
                  noise_sd: float = 0.0, in_plane_factor: float = 1.0, seed: int = 0) -> sitk.Image:
    """The cine slice the device would see on a plane of the GT-warped volume.

    ``noise_sd`` adds Gaussian noise (intensity units); ``in_plane_factor > 1`` images at a coarser
    in-plane resolution (downsampled by that factor, then resampled back to the planning grid).
    """
    img = extract_slice(warped_volume, geometry, orientation, index, centre_mm)
    if in_plane_factor > 1.0:
        size = [max(2, int(round(s / in_plane_factor))) for s in img.GetSize()]
        spacing = [sp * s0 / s1 for sp, s0, s1 in zip(img.GetSpacing(), img.GetSize(), size)]
        coarse = sitk.Resample(img, size, sitk.Transform(), sitk.sitkLinear, img.GetOrigin(), spacing, img.GetDirection(), 0.0)
        img = sitk.Resample(coarse, img, sitk.Transform(), sitk.sitkLinear, 0.0)
    if noise_sd > 0:
        arr = sitk.GetArrayFromImage(img)
        arr = arr + np.random.default_rng(seed).normal(0.0, noise_sd, arr.shape).astype(np.float32)
        out = sitk.GetImageFromArray(arr.astype(np.float32))
        out.CopyInformation(img)
        img = out
    return img


def slice_mask(labels: np.ndarray, geometry: Geometry, orientation: str, index: int, centre_mm: np.ndarray, label_values,
               dilate_mm: float = 6.0) -> sitk.Image:
    """Mask of the given labels on a slice, dilated by ``dilate_mm`` so organ edges are in."""
    m = np.isin(labels, list(label_values)).astype(np.float32)
    img = extract_slice(m, geometry, orientation, index, centre_mm)
    img = sitk.Cast(img > 0.5, sitk.sitkUInt8)
    if dilate_mm <= 0:
        return img
    radius = [max(1, int(round(dilate_mm / s))) for s in img.GetSpacing()]
    return sitk.BinaryDilate(img, radius)


def organ_intensity_volume(labels: np.ndarray, label_values: dict[str, int], geometry: Geometry, sigma_mm: float = 2.0) -> np.ndarray:
    """A smooth synthetic intensity volume from a label map (for cases without an image)."""
    vol = np.zeros(labels.shape, dtype=np.float32)
    for n, (organ, value) in enumerate(sorted(label_values.items())):
        vol[labels == value] = 100.0 * (n + 1)
    img = geometry.apply_to(sitk.GetImageFromArray(vol))
    return sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(img, sigma_mm))
