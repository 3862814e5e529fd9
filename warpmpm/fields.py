"""Displacement fields as truths: the format, reading with checks, sampling, folds and warping.

**The format** (written by ``warpmpm make-truth`` and by the tracker's ``--displacement``, read by
``run --truth-field``, ``make-cine --truth`` and ``evaluate-track``): a 3-component float vector image (NIfTI,
MHA/MHD or NRRD) on the planning image's grid; the value at a voxel is the displacement, in mm along the world
LPS axes (+x patient left, +y posterior, +z superior), of the tissue that sits at that voxel's centre at planning:
a *forward* field, ``x_t = x_0 + u(x_0)``. These are ITK's physical axes: a field written by ITK, SimpleITK, ANTs or
elastix (``transformix -def``, which writes a backward field: negate and invert it first) is read as it is; a tool
working in RAS must negate x and y.
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import SimpleITK as sitk

from .errors import InputError, InputWarning
from .images import Geometry, check_file_integrity, grid_differences

__all__ = ["write_field", "read_field", "jacobian_determinant", "sample_field", "inverse_positions", "warp_volume"]


def write_field(field_mm: np.ndarray, geometry: Geometry, path: str) -> None:
    """Write a (z, y, x, 3) displacement (mm, world LPS) as a float32 vector image on ``geometry``, through a
    temporary name so that a failure leaves no half-written file."""
    field_mm = np.asarray(field_mm, dtype=np.float32)
    if field_mm.shape != tuple(geometry.size[::-1]) + (3,):
        raise InputError(f"a field of shape {field_mm.shape} does not fit the grid {geometry.size} (x, y, z) with 3 components")
    img = geometry.apply_to(sitk.GetImageFromArray(field_mm, isVector=True))
    base, ext = _split_ext(path)
    tmp = base + ".part" + ext
    sitk.WriteImage(img, tmp, True)
    os.replace(tmp, path)


def _split_ext(path: str) -> tuple[str, str]:
    for ext in (".nii.gz", ".nii", ".mha", ".mhd", ".nrrd", ".nhdr"):
        if path.endswith(ext):
            return path[: -len(ext)], ext
    raise InputError(f"{path}: a field is written as .nii.gz, .nii, .mha or .nrrd")


def read_field(path: str, geometry: Geometry, organ_mask: np.ndarray | None = None) -> np.ndarray:
    """Read a displacement field for the planning grid ``geometry`` as (z, y, x, 3) float64 mm, world LPS.

    Refused with :class:`InputError` naming the problem: a missing or truncated file, another grid (size, spacing,
    origin or direction), another number of components, non-finite values. A fold (Jacobian determinant of
    ``x + u(x)`` at or below zero) inside ``organ_mask`` is an :class:`InputWarning` naming how many voxels fold.
    """
    from .errors import check_input_file

    check_input_file(path, "truth field", "give a displacement field (a 3-component NIfTI/MHA on the planning grid)")
    check_file_integrity(path)
    try:
        img = sitk.ReadImage(path)
    except RuntimeError as exc:
        raise InputError(f"{path}: not a readable image ({str(exc).strip().splitlines()[-1]})") from exc
    if img.GetDimension() != 3:
        raise InputError(f"{path}: a {img.GetDimension()}D image; a truth field is a 3D image of 3-vectors")
    if img.GetNumberOfComponentsPerPixel() != 3:
        raise InputError(f"{path}: {img.GetNumberOfComponentsPerPixel()} component(s) per voxel; a displacement field has 3 "
                         "(mm along world x, y, z)")
    diff = grid_differences(Geometry.of(img), geometry)
    if diff:
        raise InputError(f"{path} is not on the planning image's grid ({'; '.join(diff)}); resample it onto the planning grid "
                         "(the displacement of the tissue at each planning voxel)")
    f = sitk.GetArrayFromImage(img).astype(np.float64)
    bad = ~np.isfinite(f).all(-1)
    if bad.any():
        k, j, i = (int(v[0]) for v in np.nonzero(bad))
        raise InputError(f"{path} holds {int(bad.sum())} voxels with non-finite displacements, the first at (i, j, k) = "
                         f"({i}, {j}, {k})")
    if organ_mask is not None:
        det = jacobian_determinant(f, geometry)
        folds = int(np.count_nonzero((det <= 0) & organ_mask))
        if folds:
            warnings.warn(f"{path}: the field folds (Jacobian determinant <= 0) at {folds} organ voxels (smallest "
                          f"{float(det[organ_mask].min()):.2f}); the tissue there would turn inside out", InputWarning, stacklevel=2)
    return f


def jacobian_determinant(field_mm: np.ndarray, geometry: Geometry) -> np.ndarray:
    """det(I + grad u) at every voxel (z, y, x), by central differences along the scan's axes mapped to world axes."""
    sp = np.asarray(geometry.spacing_mm)
    # d u / d(index axis a), a = i, j, k  -> numpy axes 2, 1, 0
    du = np.stack([np.gradient(field_mm, axis=2 - a) / sp[a] for a in range(3)], -1)  # (..., 3 comps, 3 scan axes)
    D = geometry.direction_matrix  # columns: scan axes in world
    grad = du @ D.T  # d u_c / d world_b = sum_a du_c/dl_a * D[b, a]
    J = grad + np.eye(3)
    return np.linalg.det(J)


def sample_field(field_mm: np.ndarray, geometry: Geometry, points_mm: np.ndarray) -> np.ndarray:
    """The displacement (N, 3) mm at world points (trilinear between voxel centres, the edge value beyond)."""
    from scipy import ndimage

    q = geometry.world_to_index(np.asarray(points_mm, dtype=np.float64))
    coords = q[:, ::-1].T
    return np.stack([ndimage.map_coordinates(field_mm[..., c], coords, order=1, mode="nearest") for c in range(3)], -1)


def inverse_positions(field_mm: np.ndarray, geometry: Geometry, points_mm: np.ndarray, iterations: int = 20) -> np.ndarray:
    """For each world point ``y``, the planning point ``x`` with ``x + u(x) = y`` (fixed-point iteration
    ``x <- y - u(x)``; it converges where the field's gradient is below one)."""
    y = np.asarray(points_mm, dtype=np.float64)
    x = y.copy()
    for _ in range(iterations):
        x = y - sample_field(field_mm, geometry, x)
    return x


def warp_volume(volume: np.ndarray, field_mm: np.ndarray, geometry: Geometry, order: int = 1) -> np.ndarray:
    """The volume (z, y, x) as it looks once the tissue has moved by the forward field: ``W(y) = V(x)`` with
    ``x + u(x) = y`` (trilinear, ``order=0`` for labels; the edge value beyond the scan)."""
    from scipy import ndimage

    nz, ny, nx = volume.shape
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    y = geometry.index_to_world(np.stack([i.ravel(), j.ravel(), k.ravel()], 1).astype(np.float64))
    x = inverse_positions(field_mm, geometry, y)
    q = geometry.world_to_index(x)
    out = ndimage.map_coordinates(volume, q[:, ::-1].T, order=order, mode="nearest")
    return out.reshape(volume.shape).astype(volume.dtype)
