"""Targets of the driven particles: where each particle on a driving slice must go this frame.

Three sources, all returning ``(idx, targets_mm)``: the sorted indices of the driven particles and
their (n_driven, 3) world targets in mm.

- :func:`affine_targets`: one :class:`~warpmpm.slices.InPlaneAffine` per slice (the paper's mode):
  ``x_i^t = A (x_i^{t-1} - c) + c + t`` in the slice plane, the out-of-plane coordinate unchanged.
- :func:`truth_targets`: given 3D positions (the ground truth's, an upper bound no image gives).
- :func:`registration_targets`: register each slice of a planning volume to the same slice of a
  captured volume (2D affine, SimpleITK) and apply the result as above.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .images import Geometry
from .model import ParticleModel
from .registration import capture_slice, register_slices, slice_mask
from .slices import DrivingSlice, InPlaneAffine, driven_indices, extract_slice, in_plane_axes


def affine_targets(model: ParticleModel, positions_mm: np.ndarray, slices: list[DrivingSlice], affines: list,
                   centre_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Driven indices and targets from one in-plane affine per driving slice.

    ``affines``: :class:`InPlaneAffine` (or ``(A, t_mm)`` pairs), one per slice. ``positions_mm`` is
    the state at t-1 (all particles); ``centre_mm`` defaults to the volume centre. A particle on two
    slices takes the target of the first.
    """
    if len(affines) != len(slices):
        raise InputError(f"{len(slices)} driving slices but {len(affines)} affines")
    centre = model.geometry.center_mm() if centre_mm is None else np.asarray(centre_mm, dtype=np.float64)
    idx_all, tgt_all = [], []
    taken = np.zeros(model.n, dtype=bool)
    for s, aff in zip(slices, affines):
        aff = InPlaneAffine.of(aff)
        idx = driven_indices(model, [s])
        idx = idx[~taken[idx]]
        taken[idx] = True
        e_u, e_v = in_plane_axes(model, s.orientation)
        idx_all.append(idx)
        tgt_all.append(aff.apply(positions_mm[idx], e_u, e_v, centre))
    idx = np.concatenate(idx_all)
    order = np.argsort(idx)
    return idx[order], np.concatenate(tgt_all)[order]


def truth_targets(model: ParticleModel, slices: list[DrivingSlice], truth_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Driven indices and their given 3D positions ``truth_mm`` (N, 3) as targets (through-plane motion included)."""
    truth_mm = np.asarray(truth_mm, dtype=np.float64)
    if truth_mm.shape != (model.n, 3):
        raise InputError(f"truth positions must have shape ({model.n}, 3), got {truth_mm.shape}")
    idx = driven_indices(model, slices)
    return idx, truth_mm[idx]


def in_plane_errors_mm(model: ParticleModel, slices: list[DrivingSlice], idx: np.ndarray, targets_mm: np.ndarray,
                       truth_mm: np.ndarray, organ: str = "pancreas") -> np.ndarray:
    """In-plane distance between targets and true positions of ``organ``'s driven particles, slice by slice (mm)."""
    on_organ = model.organ_slice(organ)[idx]
    errs = []
    for s in slices:
        on = model.slice_mask(s.orientation, s.index)[idx] & on_organ
        e_u, e_v = in_plane_axes(model, s.orientation)
        d = targets_mm[on] - truth_mm[idx][on]
        errs.append(np.sqrt((d @ e_u) ** 2 + (d @ e_v) ** 2))
    return np.concatenate(errs) if errs else np.zeros(0)


def registration_targets(model: ParticleModel, slices: list[DrivingSlice], planning_volume: np.ndarray,
                         captured_volume: np.ndarray, labels: np.ndarray, geometry: Geometry, label_values: dict[str, int],
                         centre_mm: np.ndarray, *, truth_mm: np.ndarray | None = None, noise_sd: float = 0.0,
                         in_plane_factor: float = 1.0) -> tuple[np.ndarray, np.ndarray, dict]:
    """Driven indices and targets from registering each driving slice of ``planning_volume`` with the
    same slice of ``captured_volume`` (both (z, y, x) on ``geometry``).

    The metric is restricted to the model's organs on the planning slice (``labels`` with
    ``label_values``, dilated). Returns ``(idx, targets, info)``; ``info`` holds per slice the
    registered affine, its time and iterations (``slices``), the mean time (``wall_s``) and, when
    ``truth_mm`` (all particles' true positions) is given, ``error_mm``: the mean in-plane distance
    between the targets and the true positions of the slices' pancreas particles.
    """
    affines, per_slice = [], []
    for s in slices:
        stored = extract_slice(planning_volume, geometry, s.orientation, s.index, centre_mm)
        captured = capture_slice(captured_volume, geometry, s.orientation, s.index, centre_mm, noise_sd=noise_sd,
                                 in_plane_factor=in_plane_factor)
        mask = slice_mask(labels, geometry, s.orientation, s.index, centre_mm, [label_values[o] for o in model.organs])
        reg = register_slices(stored, captured, centre_mm, mask=mask)
        if not reg.ok:
            raise InputError(f"registration of {s.orientation} slice {s.index} gave a degenerate transform ({reg.stop}); "
                             "targets would be nonsense")
        affines.append(reg.affine)
        per_slice.append({"slice": str(s), **reg.affine.to_json(), "wall_s": reg.wall_s, "iterations": reg.iterations,
                          "metric": reg.metric})
    idx, targets = affine_targets(model, model.positions_mm, slices, affines, centre_mm)
    info: dict = {"wall_s": float(np.mean([p["wall_s"] for p in per_slice])), "slices": per_slice, "affines": affines}
    if truth_mm is not None:
        err = in_plane_errors_mm(model, slices, idx, targets, truth_mm)
        info["error_mm"] = float(err.mean()) if err.size else float("nan")
    return idx, targets, info
