"""Accuracy metrics: mean and 95th-percentile particle error (mm) and Dice of voxelised regions."""

from __future__ import annotations

import numpy as np

from .images import Geometry
from .model import voxelize

__all__ = ["particle_errors_mm", "dice", "correlation", "covering_geometry", "evaluate"]


def particle_errors_mm(estimate_mm: np.ndarray, truth_mm: np.ndarray) -> np.ndarray:
    """Per-particle distance ||x_GT - x_est|| in mm."""
    estimate_mm = np.asarray(estimate_mm, dtype=np.float64)
    truth_mm = np.asarray(truth_mm, dtype=np.float64)
    if estimate_mm.shape != truth_mm.shape:
        raise ValueError(f"estimate {estimate_mm.shape} and truth {truth_mm.shape} differ in shape")
    return np.linalg.norm(estimate_mm - truth_mm, axis=1)


def dice(a: np.ndarray, b: np.ndarray) -> float:
    """Dice coefficient 2|A & B| / (|A| + |B|) of two boolean masks (1.0 when both are empty)."""
    a = np.asarray(a, dtype=bool)
    b = np.asarray(b, dtype=bool)
    total = int(a.sum()) + int(b.sum())
    return 1.0 if total == 0 else 2.0 * int(np.logical_and(a, b).sum()) / total


def correlation(a: np.ndarray, b: np.ndarray, flat: float = 0.0) -> float:
    """Normalised cross-correlation of two equally long intensity vectors (-1 .. 1); ``flat`` where either is constant
    (or empty), which has no correlation: 0 to count it as no match, -1 to make it lose every comparison."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a = a - a.mean() if a.size else a
    b = b - b.mean() if b.size else b
    den = float(np.sqrt((a @ a) * (b @ b)))
    return float(a @ b) / den if den > 0 else float(flat)


def covering_geometry(geometry: Geometry, *point_sets_mm: np.ndarray, margin_voxels: int = 2) -> Geometry:
    """``geometry`` extended (same spacing and direction) so that every point of ``point_sets_mm`` lies inside it.

    Returns ``geometry`` itself when they already do: a Dice on a grid that clips the truth (a GT that
    moved out of the planning volume) would count the clipped part as missing from both.
    """
    pts = np.vstack([np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in point_sets_mm if len(p)])
    if not len(pts):
        return geometry
    ijk = np.rint(geometry.world_to_index(pts)).astype(np.int64)
    size = np.asarray(geometry.size)
    lo = np.minimum(ijk.min(0) - margin_voxels, 0)
    hi = np.maximum(ijk.max(0) + 1 + margin_voxels, size)
    if np.all(lo == 0) and np.all(hi == size):
        return geometry
    return geometry.crop(tuple(int(v) for v in lo), tuple(int(v) for v in hi))


def evaluate(estimate_mm: np.ndarray, truth_mm: np.ndarray, geometry: Geometry, exclude: np.ndarray | None = None,
             sampling_step: int = 1) -> dict:
    """Error (mean, p95, max; mm) and Dice of the voxelised regions of two particle sets.

    Both sets are voxelised on ``geometry`` in the same way (:func:`warpmpm.model.voxelize`).
    ``exclude`` (boolean per particle) drops particles from both metrics, as the paper did for the
    particles on driving slices in its multi-slice protocol. The grid is extended where either set
    leaves it (:func:`covering_geometry`), so nothing is clipped from the Dice.
    """
    keep = np.ones(len(truth_mm), dtype=bool) if exclude is None else ~np.asarray(exclude, dtype=bool)
    err = particle_errors_mm(estimate_mm[keep], truth_mm[keep])
    grid = covering_geometry(geometry, estimate_mm[keep], truth_mm[keep])
    d = dice(voxelize(estimate_mm[keep], grid, sampling_step=sampling_step),
             voxelize(truth_mm[keep], grid, sampling_step=sampling_step))
    return {
        "error_mm": float(err.mean()) if err.size else float("nan"),
        "p95_mm": float(np.percentile(err, 95)) if err.size else float("nan"),
        "max_mm": float(err.max()) if err.size else float("nan"),
        "dice": float(d),
        "n": int(keep.sum()),
    }
