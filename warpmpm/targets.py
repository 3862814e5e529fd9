"""Targets of the driven particles: where each particle on a driving slice must go this frame.

A slice measures motion in its own plane only. Targets carry, per driven particle, the directions its
slices measure (:class:`DriveTargets`), so the drive can act on those alone and leave the through-plane
motion to the physics or to a second, orthogonal slice.

- :func:`affine_targets` / :func:`affine_drive_targets`: one :class:`~warpmpm.slices.InPlaneAffine` per
  slice (the paper's mode): ``x_i^t = A (x_i^{t-1} - c) + c + t`` in the slice plane.
- :func:`truth_targets`: given 3D positions (the ground truth's: an upper bound no image gives);
  :func:`in_plane_truth_targets`: their in-plane part (the best any 2D registration can give).
- :func:`registration_targets`: register each slice of a planning volume to the same slice of a
  captured volume (SimpleITK), the whole slice and then each organ's footprint on it.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from .errors import InputError, SimulationError, InputWarning
from .images import Geometry
from .imaging import capture_slice, particle_label_map, slice_mask, warp_array
from .metrics import correlation
from .model import ParticleModel
from .registration import SliceField, register_organ_demons, register_slice_bspline, register_slice_organs
from .slices import DrivingSlice, InPlaneAffine, copy_organ_motion, driven_indices, extract_slice, in_plane_axes

__all__ = ["plane_projector", "DriveTargets", "slice_targets", "affine_drive_targets", "affine_targets",
           "truth_targets", "in_plane_truth_targets", "in_plane_errors_mm", "field_motion", "MIN_ORGAN_PIXELS",
           "registration_targets", "MAX_PASSES", "combine_planes"]


def plane_projector(model_or_geometry, orientation: str) -> np.ndarray:
    """(3, 3) projector onto a slice's plane: ``e_u e_u^T + e_v e_v^T``."""
    e_u, e_v = in_plane_axes(model_or_geometry, orientation)
    return np.outer(e_u, e_u) + np.outer(e_v, e_v)


@dataclass
class DriveTargets:
    """What a frame drives: particles, targets and, per particle, the directions a slice measures.

    Attributes:
        idx: (n,) sorted indices of the driven particles.
        targets_mm: (n, 3) targets; along directions no slice measures, the previous position.
        axes: (n, 3, 3) projector onto the directions the particle's slices measure (a slice's plane; two
            orthogonal slices through a particle measure all three directions). Passed to
            :meth:`~warpmpm.driving.SliceDrivenEstimator.estimate` it drives only those (in-plane driving).
    """

    idx: np.ndarray
    targets_mm: np.ndarray
    axes: np.ndarray


def slice_targets(model: ParticleModel, positions_mm: np.ndarray, slices: list[DrivingSlice], moved, keep=None) -> DriveTargets:
    """Combine per-slice in-plane targets into one target per driven particle.

    ``moved(s, idx)`` gives the targets (len(idx), 3) of the particles ``idx`` on slice ``s``; only their
    in-plane components count. A particle on several slices takes each slice's in-plane components, in
    the least-squares sense where two slices measure the same direction:
    ``x = pinv(sum P_s) sum P_s t_s + (I - Q) x_prev`` with ``P_s`` the slices' plane projectors and
    ``Q`` the projector onto what they span. ``keep(s, idx)`` (a boolean mask) drops particles from a slice's
    targets (:func:`warpmpm.plane_check.check_planes`); a particle kept by no slice is not driven.
    """
    positions_mm = np.asarray(positions_mm, dtype=np.float64)
    A = np.zeros((model.n, 3, 3))
    b = np.zeros((model.n, 3))
    on_any = np.zeros(model.n, dtype=bool)
    for s in slices:
        idx = driven_indices(model, [s])
        if keep is not None:
            idx = idx[keep(s, idx)]
            if not len(idx):
                continue
        P = plane_projector(model, s.orientation)
        t = np.asarray(moved(s, idx), dtype=np.float64)
        A[idx] += P
        b[idx] += t @ P.T
        on_any[idx] = True
    idx = np.nonzero(on_any)[0]
    if not len(idx):
        return DriveTargets(idx, np.zeros((0, 3)), np.zeros((0, 3, 3)))
    A, b, x = A[idx], b[idx], positions_mm[idx]
    Ainv = np.linalg.pinv(A, rcond=1e-6)
    Q = np.einsum("nij,njk->nik", A, Ainv)
    Q = np.where(np.abs(Q) < 1e-9, 0.0, Q)
    targets = np.einsum("nij,nj->ni", Ainv, b) + x - np.einsum("nij,nj->ni", Q, x)
    return DriveTargets(idx, targets, Q)


def affine_drive_targets(model: ParticleModel, positions_mm: np.ndarray, slices: list[DrivingSlice], affines: list,
                         centre_mm: np.ndarray | None = None) -> DriveTargets:
    """:class:`DriveTargets` from one in-plane affine per driving slice (:func:`affine_targets`)."""
    if len(affines) != len(slices):
        raise InputError(f"{len(slices)} driving slices but {len(affines)} affines")
    centre = model.geometry.center_mm() if centre_mm is None else np.asarray(centre_mm, dtype=np.float64)
    by_slice = {s: InPlaneAffine.of(a) for s, a in zip(slices, affines)}

    def moved(s, idx):
        e_u, e_v = in_plane_axes(model, s.orientation)
        return by_slice[s].apply(positions_mm[idx], e_u, e_v, centre)

    return slice_targets(model, positions_mm, slices, moved)


def affine_targets(model: ParticleModel, positions_mm: np.ndarray, slices: list[DrivingSlice], affines: list,
                   centre_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Driven indices and targets from one in-plane affine per driving slice.

    ``affines``: :class:`InPlaneAffine` (or ``(A, t_mm)`` pairs), one per slice. ``positions_mm`` is
    the state at t-1 (all particles); ``centre_mm`` defaults to the volume centre. A particle on two
    slices takes each slice's in-plane components (:func:`slice_targets`).
    """
    t = affine_drive_targets(model, positions_mm, slices, affines, centre_mm)
    return t.idx, t.targets_mm


def truth_targets(model: ParticleModel, slices: list[DrivingSlice], truth_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Driven indices and their given 3D positions ``truth_mm`` (N, 3) as targets (through-plane motion included)."""
    truth_mm = np.asarray(truth_mm, dtype=np.float64)
    if truth_mm.shape != (model.n, 3):
        raise InputError(f"truth positions must have shape ({model.n}, 3), got {truth_mm.shape}")
    idx = driven_indices(model, slices)
    return idx, truth_mm[idx]


def in_plane_truth_targets(model: ParticleModel, positions_mm: np.ndarray, slices: list[DrivingSlice],
                           truth_mm: np.ndarray) -> DriveTargets:
    """The true motion projected on each slice's plane: the best any 2D registration of the slices can give."""
    truth_mm = np.asarray(truth_mm, dtype=np.float64)
    if truth_mm.shape != (model.n, 3):
        raise InputError(f"truth positions must have shape ({model.n}, 3), got {truth_mm.shape}")
    return slice_targets(model, positions_mm, slices, lambda s, idx: truth_mm[idx])


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


def field_motion(field: SliceField, positions_mm: np.ndarray, e_u: np.ndarray, e_v: np.ndarray, centre_mm: np.ndarray) -> np.ndarray:
    """Positions moved in the slice plane by a deformable slice motion (the coordinate along the normal unchanged)."""
    d = np.asarray(positions_mm, dtype=np.float64) - centre_mm
    uv = np.stack([d @ e_u, d @ e_v], axis=1)
    delta = field.forward(uv) - uv
    return positions_mm + delta[:, :1] * e_u[None, :] + delta[:, 1:] * e_v[None, :]


#: Smallest footprint (pixels) of an organ on a slice for it to be registered on its own.
MIN_ORGAN_PIXELS = 25


def registration_targets(model: ParticleModel, slices: list[DrivingSlice], planning_volume: np.ndarray,
                         captured_volume: np.ndarray, labels: np.ndarray, geometry: Geometry, label_values: dict[str, int],
                         centre_mm: np.ndarray, *, truth_mm: np.ndarray | None = None, noise_sd: float = 0.0,
                         in_plane_factor: float = 1.0, method: str = "organs", positions_mm: np.ndarray | None = None,
                         backend: str = "itk", passes: int = 1, slice_name=None) -> tuple[DriveTargets, dict]:
    """Targets from registering each driving slice of ``planning_volume`` with the same slice of
    ``captured_volume`` (both (z, y, x) on ``geometry``); ``positions_mm`` is the state at t-1 (default: planning).

    The whole slice is registered with a 2D affine, the metric restricted to the model's organs on it
    (``labels`` with ``label_values``, dilated): the paper's mode, ``method="affine"``. With ``"organs"``
    (the default) each organ's footprint on the slice is then registered on its own, starting from the
    whole slice's motion, and every particle takes its own organ's motion: organs on one slice may move
    apart or slide along each other (one affine would follow the pushed neighbour and move the pancreas
    with it); an organ with fewer than :data:`MIN_ORGAN_PIXELS` pixels takes the whole slice's. With
    ``"bspline"`` a cubic B-spline field on top of the affine gives every particle its own in-plane motion
    (:func:`~warpmpm.registration.register_slice_bspline`); a slice whose field folds falls back to the
    organ-aware registration, with a warning and the reason in ``info["fallbacks"]``. With ``"demons"`` the
    organ-aware registration is refined organ by organ: each organ with at least :data:`MIN_ORGAN_PIXELS` pixels on
    the slice gets a demons field started from its own motion (:func:`~warpmpm.registration.register_organ_demons`)
    that moves its particles (``info["organ_fields"]``: slice -> organ -> field); a folding field falls back to the
    organ's affine, with a warning and the reason in ``info["fallbacks"]``. ``backend``: the affine
    registrations' optimiser (:func:`~warpmpm.registration.register_slices`; the B-spline and demons fields are ITK's).

    ``passes > 1`` with several planes (:func:`_rendered_passes`): each later pass registers the captured slices
    against the planning volume moved by the last pass's motion of every particle (all planes combined), so each
    plane's reference already holds the motion through it that the other planes measured; a pass is kept only
    while it makes the rendered planes match the captured ones better (``info["plane_match"]``, ``info["passes"]``).

    Returns ``(targets, info)``; ``info`` holds every particle's position under the slices' motions, combined in the
    least-squares sense where slices share a direction (``combined_mm``), the whole-slice affines (``affines``, one per slice),
    each slice's organ affines (``organ_affines``: slice -> organ -> affine), the mean time per slice
    (``wall_s``), and with ``truth_mm`` (all particles' true positions) ``error_mm`` and ``median_error_mm``:
    the in-plane distance between the targets and the true positions of the slices' pancreas particles.
    """
    if not (isinstance(passes, int) and not isinstance(passes, bool) and 1 <= passes <= MAX_PASSES):
        raise InputError(f"registration passes must be a whole number from 1 to {MAX_PASSES}, got {passes!r}")
    if method not in ("organs", "affine", "bspline", "demons"):
        raise InputError(f"unknown slice registration method {method!r}; use organs, affine, bspline or demons")
    kw = dict(truth_mm=truth_mm, noise_sd=noise_sd, in_plane_factor=in_plane_factor, method=method, backend=backend,
              slice_name=slice_name or (lambda s: f"{s.orientation} slice {s.index}"))
    if passes > 1 and len(slices) > 1:
        if positions_mm is not None:
            raise InputError("registration passes > 1 render the planning volume from the planning positions; "
                             "give no positions_mm")
        return _rendered_passes(model, slices, planning_volume, captured_volume, labels, geometry, label_values, centre_mm,
                                passes, kw)
    targets, info, _ = _registration_pass(model, slices, planning_volume, captured_volume, labels, geometry, label_values,
                                          centre_mm, positions_mm=positions_mm, **kw)
    return targets, info


#: Most registration passes (:func:`registration_targets`).
MAX_PASSES = 5


def _rendered_passes(model, slices, planning_volume, captured_volume, labels, geometry, label_values, centre_mm, passes, kw):
    """:func:`registration_targets` with ``passes > 1`` on several planes. A plane measures motion in its own plane
    only; motion through it changes what it shows and is read as in-plane motion (on the contact protocol's
    sagittal + coronal slices the first pass's pancreas targets were 4.5 mm off). Each later pass renders the planning
    volume moved by every particle's motion from the last kept pass (each plane's per-organ motion, combined in the
    least-squares sense where planes share a direction), registers the captured slices against it and composes the
    result. The kept pass is the last that raised the mean correlation of the rendered and captured planes over the
    organs (no truth is used to choose). A later pass's affines move the last pass's state, not the planning one:
    ``info["first_pass"]`` keeps the first pass's (against the planning image), which one-plane baselines copy;
    ``info["combined_mm"]`` is the kept pass's whole motion."""
    x0 = model.positions_mm
    values = [label_values[o] for o in model.organs]
    ref, lab, x = planning_volume, labels, x0
    best, kept, scores, n_kept, first, wall = -np.inf, None, [], 0, None, 0.0
    captured = {s: capture_slice(captured_volume, geometry, s.orientation, s.index, centre_mm, noise_sd=kw["noise_sd"],
                                 in_plane_factor=kw["in_plane_factor"]) for s in slices}  # the same every pass
    for k in range(passes):
        t0 = time.perf_counter()
        try:
            targets, info, moved_all = _registration_pass(model, slices, ref, captured_volume, lab, geometry, label_values,
                                                          centre_mm, positions_mm=x, **kw)
        except InputError as e:
            if kept is None:
                raise
            kept[1]["fallbacks"].append(f"registration pass {k + 1} failed ({e}); pass {n_kept} kept")
            break
        if first is None:  # the planes' motion against the planning image itself: what the one-pass baselines copy
            first = {key: info[key] for key in ("affines", "organ_affines", "fields", "organ_fields")}
        volume = warp_array(planning_volume, geometry, x0, moved_all)
        now = particle_label_map(model, moved_all, {o: label_values[o] for o in model.organs})
        score = float(np.mean([_correlation(extract_slice(volume, geometry, s.orientation, s.index, centre_mm), captured[s],
                                            slice_mask(now, geometry, s.orientation, s.index, centre_mm, values))
                               for s in slices]))
        scores.append(score)
        wall += time.perf_counter() - t0
        if score <= best:
            break
        best, kept, n_kept = score, (targets, info), k + 1
        ref, lab, x = volume, now, moved_all
    targets, info = kept
    info["passes"], info["plane_match"], info["first_pass"] = n_kept, scores, first
    info["wall_s"] = wall / len(slices)  # every pass, with its rendering and check, per slice
    return targets, info


def _correlation(a: sitk.Image, b: sitk.Image, mask: sitk.Image) -> float:
    """Normalised cross-correlation of two slices over a mask (-1 .. 1; -1 where either is flat there)."""
    m = sitk.GetArrayViewFromImage(mask) > 0
    return correlation(sitk.GetArrayFromImage(a)[m], sitk.GetArrayFromImage(b)[m], flat=-1.0)


def _registration_pass(model: ParticleModel, slices: list[DrivingSlice], planning_volume: np.ndarray,
                       captured_volume: np.ndarray, labels: np.ndarray, geometry: Geometry, label_values: dict[str, int],
                       centre_mm: np.ndarray, *, truth_mm, noise_sd, in_plane_factor, method, positions_mm, backend, slice_name):
    """One registration of every slice (:func:`registration_targets`); also returns every particle's position
    under the slices' motions, combined."""
    positions_mm = model.positions_mm if positions_mm is None else np.asarray(positions_mm, dtype=np.float64)
    affines, organ_affines, fields, organ_fields, walls, fallbacks = [], {}, {}, {}, [], []
    for s in slices:
        stored = extract_slice(planning_volume, geometry, s.orientation, s.index, centre_mm)
        captured = capture_slice(captured_volume, geometry, s.orientation, s.index, centre_mm, noise_sd=noise_sd,
                                 in_plane_factor=in_plane_factor)
        mask = slice_mask(labels, geometry, s.orientation, s.index, centre_mm, [label_values[o] for o in model.organs])
        extra = 0.0
        if method == "bspline":
            f = register_slice_bspline(stored, captured, centre_mm, mask)
            if f.ok:
                fields[s] = f
                affines.append(f.affine)
                organ_affines[s] = {}
                walls.append(f.wall_s)
                continue
            extra = f.wall_s
            fallbacks.append(f"{s}: the B-spline field folds (smallest Jacobian determinant {f.min_jacobian:.2f}); "
                             "the organ-aware registration is used instead")
            warnings.warn(f"registration of {s}: {fallbacks[-1].split(': ', 1)[1]}", InputWarning, stacklevel=2)
        own = {o: slice_mask(labels, geometry, s.orientation, s.index, centre_mm, [label_values[o]], dilate_mm=0.0)
               for o in model.organs} if method in ("organs", "bspline", "demons") else {}
        whole, per_organ = register_slice_organs(stored, captured, centre_mm, mask, own, MIN_ORGAN_PIXELS, backend=backend)
        if not whole.ok:
            raise SimulationError(f"registration of {slice_name(s)} gave a degenerate transform ({whole.stop}); its targets "
                                  "would be nonsense (a blank or featureless slice there? choose another plane)")
        affines.append(whole.affine)
        organ_affines[s] = {o: r.affine for o, r in per_organ.items()}
        walls.append(extra + whole.wall_s + sum(r.wall_s for r in per_organ.values()))
        if method == "demons":
            organ_fields[s] = {}
            for o, fp in own.items():
                if int(np.count_nonzero(sitk.GetArrayViewFromImage(fp))) < MIN_ORGAN_PIXELS:
                    continue
                f = register_organ_demons(stored, captured, organ_affines[s].get(o, whole.affine), fp)
                walls[-1] += f.wall_s
                if f.ok:
                    organ_fields[s][o] = f
                else:
                    fallbacks.append(f"{s}, {o}: the demons field folds (smallest Jacobian determinant {f.min_jacobian:.2f}); "
                                     "the organ's affine is used instead")
                    warnings.warn(f"registration of {s}: {fallbacks[-1].split(': ', 1)[1]}", InputWarning, stacklevel=2)

    whole = dict(zip(slices, affines))
    organ_of = np.asarray(model.organs)[model.organ_index]

    def moved(s, idx):
        e_u, e_v = in_plane_axes(model, s.orientation)
        if s in fields:
            return field_motion(fields[s], positions_mm[idx], e_u, e_v, centre_mm)
        out = copy_organ_motion(positions_mm[idx], organ_of[idx], e_u, e_v, centre_mm, whole[s], organ_affines[s])
        for organ, f in organ_fields.get(s, {}).items():
            sel = organ_of[idx] == organ
            out[sel] = field_motion(f, positions_mm[idx[sel]], e_u, e_v, centre_mm)
        return out

    targets = slice_targets(model, positions_mm, slices, moved)
    info: dict = {"wall_s": float(np.mean(walls)), "affines": affines, "organ_affines": organ_affines, "fields": fields,
                  "organ_fields": organ_fields, "method": method, "fallbacks": fallbacks, "moved": moved}
    if truth_mm is not None:
        err = in_plane_errors_mm(model, slices, targets.idx, targets.targets_mm, truth_mm)
        info["error_mm"] = float(err.mean()) if err.size else float("nan")
        info["median_error_mm"] = float(np.median(err)) if err.size else float("nan")
    info["combined_mm"] = combine_planes(model, positions_mm, slices, moved)
    return targets, info, info["combined_mm"]


def combine_planes(model: ParticleModel, positions_mm: np.ndarray, slices: list[DrivingSlice], moved) -> np.ndarray:
    """Every particle under all slices' in-plane motions at once: ``moved(s, idx)`` gives the positions of particles
    ``idx`` under slice ``s``'s motion; each slice contributes its in-plane components, averaged (least squares)
    where slices share a direction (the ``propagate_planes`` baseline)."""
    everyone = np.arange(model.n)
    num, span = np.zeros((model.n, 3)), np.zeros((3, 3))
    for s in slices:
        P = plane_projector(model, s.orientation)
        num += (moved(s, everyone) - positions_mm) @ P.T
        span += P
    return positions_mm + num @ np.linalg.pinv(span).T
