"""A driving slice and its in-plane motion: the method's central object.

A cine MR slice is a plane of the planning volume: an orientation (axial, sagittal, coronal) and a
voxel index along the image axis closest to that orientation's normal. Its in-plane coordinates are
the offsets ``(u, v) = ((x - c) . e_u, (x - c) . e_v)`` in mm from a centre ``c``, with ``e_u, e_v``
the world directions of the slice's two in-plane image axes (in image-axis order).

The motion a 2D registration measures on a slice is an :class:`InPlaneAffine`::

    x' = A (x - c) + c + t        (in the plane; the coordinate along the normal is unchanged)

with ``A`` a 2x2 matrix (rotation, scale, shear) and ``t`` a translation in mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import SimpleITK as sitk

from .errors import InputError
from .images import ORIENTATION_WORLD_AXIS, Geometry, orientation_image_axis  # noqa: F401 (re-exported: the plane of a slice)
from .model import ParticleModel

__all__ = ["Orientation", "ORIENTATIONS", "in_plane_axes", "DrivingSlice", "parse_slices", "driven_indices", "copy_organ_motion",
           "apply_in_plane_affine", "InPlaneAffine", "extract_slice"]


Orientation = Literal["axial", "sagittal", "coronal"]
ORIENTATIONS: tuple[str, ...] = ("axial", "sagittal", "coronal")

def in_plane_axes(model_or_geometry, orientation: str) -> tuple[np.ndarray, np.ndarray]:
    """World unit vectors (e_u, e_v) of a slice's two in-plane image axes, in image-axis order."""
    geometry = getattr(model_or_geometry, "geometry", model_or_geometry)
    normal = orientation_image_axis(geometry, orientation)
    u, v = [a for a in range(3) if a != normal]
    return geometry.axis_world_direction(u), geometry.axis_world_direction(v)


@dataclass(frozen=True)
class DrivingSlice:
    """A driving slice: orientation (axial, sagittal, coronal) and voxel index of the planning volume."""

    orientation: str
    index: int

    def __str__(self) -> str:
        return f"{self.orientation}:{self.index}"

    def image_axis(self, geometry: Geometry) -> int:
        """The image axis this slice is normal to."""
        return orientation_image_axis(geometry, self.orientation)

    def shifted(self, offset: int) -> "DrivingSlice":
        """The same plane with its index moved by ``offset`` voxels (between a volume and its crop)."""
        return DrivingSlice(self.orientation, int(self.index) + int(offset))


def parse_slices(text: str) -> list[DrivingSlice]:
    """Parse ``"axial:12,sagittal:40"`` into :class:`DrivingSlice` objects (a repeated slice counts once)."""
    out: list[DrivingSlice] = []
    for part in [p.strip() for p in text.split(",") if p.strip()]:
        if ":" not in part:
            raise InputError(f"slice {part!r} must read ORIENTATION:INDEX, e.g. axial:12")
        o, i = part.split(":", 1)
        o = o.strip().lower()
        if o not in ORIENTATIONS:
            raise InputError(f"unknown slice orientation {o!r} in {part!r}; use axial, sagittal or coronal")
        try:
            idx = int(i)
        except ValueError:
            raise InputError(f"slice index {i!r} in {part!r} is not an integer") from None
        s = DrivingSlice(o, idx)
        if s not in out:
            out.append(s)
    if not out:
        raise InputError("no driving slice given")
    return out


def driven_indices(model: ParticleModel, slices: list[DrivingSlice]) -> np.ndarray:
    """Indices of the particles lying on any of ``slices`` (sorted, unique).

    Raises :class:`InputError` for an index outside the volume or a slice holding no particle.
    """
    if not slices:
        raise InputError("no driving slice given")
    mask = np.zeros(model.n, dtype=bool)
    for s in slices:
        on = model.slice_mask(s.orientation, s.index)
        if not on.any():
            raise InputError(f"{s.orientation} slice {s.index} holds no particle of the organs {model.letters}")
        mask |= on
    return np.nonzero(mask)[0]


def apply_in_plane_affine(positions_mm: np.ndarray, e_u: np.ndarray, e_v: np.ndarray, A: np.ndarray, t_mm: np.ndarray,
                          centre_mm: np.ndarray) -> np.ndarray:
    """``x' = A (x - c) + c + t`` in the plane spanned by (e_u, e_v); the out-of-plane coordinate is unchanged."""
    aff = InPlaneAffine(A, t_mm)
    return aff.apply(positions_mm, e_u, e_v, centre_mm)


@dataclass(frozen=True, eq=False)
class InPlaneAffine:
    """The in-plane motion of a slice, ``x' = A (x - c) + c + t`` (module docstring).

    Checked at construction: ``A`` must be a finite, non-degenerate 2x2 matrix (|det A| >= 1e-6,
    condition number <= 1e6) and ``t_mm`` a finite 2-vector; otherwise :class:`InputError`.

    Attributes:
        A: (2, 2) linear part (rotation, scale, shear), dimensionless.
        t_mm: (2,) translation along (e_u, e_v) in mm.
    """

    A: np.ndarray
    t_mm: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self):
        A = np.asarray(self.A, dtype=np.float64)
        t = np.zeros(2) if self.t_mm is None else np.asarray(self.t_mm, dtype=np.float64).reshape(-1)
        if A.shape != (2, 2) or t.shape != (2,):
            raise InputError(f"an in-plane affine needs A of shape (2, 2) and t of shape (2,), got {A.shape} and {t.shape}")
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(t))):
            raise InputError("the in-plane affine holds a non-finite value")
        det = np.linalg.det(A)
        if abs(det) < 1e-6 or np.linalg.cond(A) > 1e6:
            raise InputError(f"the in-plane affine is singular or degenerate (det {det:.3g})")
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "t_mm", t)

    @classmethod
    def identity(cls) -> "InPlaneAffine":
        return cls(np.eye(2), np.zeros(2))

    @classmethod
    def of(cls, value) -> "InPlaneAffine":
        """An :class:`InPlaneAffine` from itself, an ``(A, t)`` pair or a bare ``A``."""
        if isinstance(value, cls):
            return value
        if isinstance(value, (tuple, list)) and len(value) == 2:
            return cls(value[0], value[1])
        return cls(value)

    @classmethod
    def fit(cls, before_mm: np.ndarray, after_mm: np.ndarray, e_u: np.ndarray, e_v: np.ndarray,
            centre_mm: np.ndarray) -> "InPlaneAffine":
        """Least-squares in-plane affine about ``centre_mm`` mapping ``before`` to ``after`` (N >= 3 points)."""
        before_mm = np.asarray(before_mm, dtype=np.float64)
        if len(before_mm) < 3:
            raise InputError(f"fitting an in-plane affine needs at least 3 points, got {len(before_mm)}")
        d0 = before_mm - centre_mm
        d1 = np.asarray(after_mm, dtype=np.float64) - centre_mm
        uv0 = np.stack([d0 @ e_u, d0 @ e_v], axis=1)
        uv1 = np.stack([d1 @ e_u, d1 @ e_v], axis=1)
        X = np.hstack([uv0, np.ones((len(uv0), 1))])
        sol, *_ = np.linalg.lstsq(X, uv1, rcond=None)
        return cls(sol[:2].T, sol[2])

    def apply(self, positions_mm: np.ndarray, e_u: np.ndarray, e_v: np.ndarray, centre_mm: np.ndarray) -> np.ndarray:
        """The moved positions (N, 3) in mm; the coordinate along the slice normal is unchanged."""
        positions_mm = np.asarray(positions_mm, dtype=np.float64)
        d = positions_mm - np.asarray(centre_mm, dtype=np.float64)
        uv = np.stack([d @ e_u, d @ e_v], axis=1)
        delta = uv @ self.A.T + self.t_mm - uv
        return positions_mm + delta[:, :1] * e_u[None, :] + delta[:, 1:] * e_v[None, :]

    def inverse(self) -> "InPlaneAffine":
        Ainv = np.linalg.inv(self.A)
        return InPlaneAffine(Ainv, -Ainv @ self.t_mm)

    def to_json(self) -> dict:
        return {"A": self.A.tolist(), "t_mm": self.t_mm.tolist()}


def copy_organ_motion(positions_mm: np.ndarray, organ_of: np.ndarray, e_u: np.ndarray, e_v: np.ndarray, centre_mm: np.ndarray,
                      whole: "InPlaneAffine", organs: dict | None = None) -> np.ndarray:
    """The copy of a plane's motion: every position moved in the plane (e_u, e_v) by its organ's in-plane affine
    (``organs``: organ name -> :class:`InPlaneAffine`; ``organ_of``: each position's organ name), an organ without one by
    the whole slice's (``whole``); the through-plane coordinate unchanged. The one place the copy is computed: the
    tracker's observation, ``run``'s ``propagate`` baselines and its copy estimate all call it."""
    out = whole.apply(positions_mm, e_u, e_v, centre_mm)
    for organ, aff in (organs or {}).items():
        sel = organ_of == organ
        if sel.any():
            out[sel] = aff.apply(np.asarray(positions_mm)[sel], e_u, e_v, centre_mm)
    return out


def extract_slice(volume: np.ndarray, geometry: Geometry, orientation: str, index: int, centre_mm: np.ndarray) -> sitk.Image:
    """The 2D image of ``volume`` (z, y, x) on slice ``index`` of an orientation, in centred in-plane mm."""
    axis = orientation_image_axis(geometry, orientation)
    if not (0 <= int(index) < geometry.size[axis]):
        raise InputError(f"{orientation} slice {index} is outside the volume (valid 0..{geometry.size[axis] - 1})")
    u, v = [a for a in range(3) if a != axis]
    np_axis = 2 - axis  # numpy order is (z, y, x)
    plane = np.take(volume, int(index), axis=np_axis).astype(np.float32)
    # remaining numpy axes are (v, u) in that order: the larger image axis first
    img = sitk.GetImageFromArray(plane)
    idx0 = np.zeros(3)
    idx0[axis] = index
    x0 = geometry.index_to_world(idx0[None, :])[0] - np.asarray(centre_mm, dtype=np.float64)
    e_u, e_v = in_plane_axes(geometry, orientation)
    img.SetOrigin((float(x0 @ e_u), float(x0 @ e_v)))
    img.SetSpacing((geometry.spacing_mm[u], geometry.spacing_mm[v]))
    return img
