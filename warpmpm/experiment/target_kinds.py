"""A run's driving targets from its ground truth: the ``--targets`` kinds of :class:`CaseConfig`.

- ``affine``: one in-plane affine per slice, fitted to the slice particles' GT motion (the paper's known
  ``A`` for axial slices under the paper protocol): what a perfect affine registration would measure.
- ``gt``: the slice particles' GT 3D positions, through-plane motion included: an upper bound no 2D
  image gives (always driven in 3D).
- ``gt-inplane``: the GT motion projected on each slice's plane: the best any 2D registration can give.
- ``registration``: register each planning slice with the slice captured from the GT-warped image, the
  whole slice and then each organ's footprint on it (organ-aware; the default).
- ``registration-affine``: the same with one affine per slice (the paper's).
- ``registration-bspline``: the whole slice's affine refined by a cubic B-spline field (deformable).
- ``registration-demons``: the organ-aware registration, each organ's motion refined by a demons field started
  from it (deformable and organ-aware).
- ``cine``: the captured planes imaged as a scanner's cine frames (the GT-warped planning image averaged over
  :attr:`~warpmpm.experiment.config.CaseConfig.cine_thickness_mm` around each slice, one frame a plane in the slices'
  order) and followed by the tracker's own frame pipeline (:class:`warpmpm.tracker.Tracker` with its default
  configuration but the linear prior, :attr:`~warpmpm.experiment.config.CaseConfig.cine_linear_prior`: each frame
  registered organ by organ against the estimate rendered on its plane, the frame check, the ``copy`` estimator):
  what ``warpmpm track --linear-prior 0`` gives for those frames, to the digit (tested).

With ``drive="inplane"`` a slice drives only its in-plane components (the through-plane motion is left
to the physics or to an orthogonal slice); ``"pinned"`` also holds the through-plane coordinate where
the target puts it (the previous position, as the paper's targets do).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..groundtruth import GroundTruth, paper_affine
from ..model import ParticleModel
from ..slices import DrivingSlice, InPlaneAffine, driven_indices, in_plane_axes
from ..targets import (DriveTargets, affine_drive_targets, combine_planes, in_plane_errors_mm, in_plane_truth_targets,
                       registration_targets, slice_targets)
from .baselines import propagate
from .capture import planning_and_gt_volumes
from .case import PreparedCase
from .config import CaseConfig

__all__ = ["RunTargets", "slice_affines", "MIN_ORGAN_PARTICLES", "truth_organ_affines", "cine_frames", "cine_targets", "run_targets"]


@dataclass
class RunTargets:
    """What a run drives, the slice motion it used and the registration's report.

    Attributes:
        drive: :class:`~warpmpm.targets.DriveTargets` (indices, targets, driven directions).
        affines: the in-plane motion of each whole slice (fitted, known or registered; with several registration
            passes, the first's, against the planning image).
        organ_affines: per slice, each organ's own motion (organ-aware registration; for ``gt`` / ``gt-inplane`` each
            organ's affine fitted to its true in-plane motion, for the baselines), else empty.
        registration: the registration's own error and time for the registration kinds, else None.
        in_plane_error_mm: mean in-plane distance of the targets of the slices' pancreas particles to their
            true positions (0 for the GT kinds), for every kind.
        fields: per slice, the deformable motion (``registration-bspline``), else empty.
        organ_fields: per slice, each organ's deformable motion (``registration-demons``), else empty.
        combined_mm: with several planes (registered, ``gt``, ``gt-inplane``), every particle under all planes' motions
            combined (the ``propagate_planes`` baseline: the estimate's information, copied to the whole body), else None.
    """

    drive: DriveTargets
    affines: list[InPlaneAffine]
    organ_affines: dict = field(default_factory=dict)
    registration: dict | None = None
    in_plane_error_mm: float = float("nan")
    fields: dict = field(default_factory=dict)
    organ_fields: dict = field(default_factory=dict)
    combined_mm: np.ndarray | None = None
    first_plane_mm: np.ndarray | None = None
    """``cine``: every particle moved by the first frame's registered motion alone (the ``propagate`` baseline: the first
    slice's motion copied), else None (``propagate`` is computed from :attr:`affines`)."""
    plane_match: object = None
    """For the registration kinds: ``plane_match(positions_mm)``, the mean correlation of the captured planes with the
    planning image moved to ``positions_mm`` (None: unmoved), the estimate's own measure (:mod:`warpmpm.plane_check`)."""

    @property
    def idx(self) -> np.ndarray:
        return self.drive.idx

    @property
    def targets_mm(self) -> np.ndarray:
        return self.drive.targets_mm

    def axes(self, drive: str) -> np.ndarray | None:
        """The driven directions for :meth:`~warpmpm.driving.SliceDrivenEstimator.estimate` (None: all three)."""
        return self.drive.axes if drive == "inplane" else None


def slice_affines(prep: PreparedCase, model: ParticleModel, gt_pos: np.ndarray, slices: list[DrivingSlice],
                  cfg: CaseConfig) -> list[InPlaneAffine]:
    """The in-plane affine of every driving slice: the paper's known A for axial slices under the paper
    protocol, else the least-squares fit of the slice particles' GT motion."""
    out = []
    for s in slices:
        if cfg.protocol == "paper" and s.orientation == "axial":
            out.append(InPlaneAffine(paper_affine(cfg.deformation, cfg.literal)))
        else:
            idx = driven_indices(model, [s])
            e_u, e_v = in_plane_axes(model, s.orientation)
            out.append(InPlaneAffine.fit(model.positions_mm[idx], gt_pos[idx], e_u, e_v, prep.centre_mm))
    return out


#: Fewest particles of an organ on a slice for the baselines of the GT kinds to fit the organ its own affine.
MIN_ORGAN_PARTICLES = 10


def truth_organ_affines(model: ParticleModel, gt_pos: np.ndarray, slices: list[DrivingSlice], centre_mm: np.ndarray) -> dict:
    """Per slice, each organ's in-plane affine fitted to its slice particles' true motion (organs with at least
    :data:`MIN_ORGAN_PARTICLES` there): what a perfect organ-aware affine registration would measure, so that
    ``propagate`` beside the ``gt`` / ``gt-inplane`` ceilings copies the same information organ by organ."""
    out = {}
    organ_of = np.asarray(model.organs)[model.organ_index]
    for s in slices:
        idx = driven_indices(model, [s])
        e_u, e_v = in_plane_axes(model, s.orientation)
        out[s] = {o: InPlaneAffine.fit(model.positions_mm[idx[organ_of[idx] == o]], gt_pos[idx[organ_of[idx] == o]], e_u, e_v, centre_mm)
                  for o in model.organs if np.count_nonzero(organ_of[idx] == o) >= MIN_ORGAN_PARTICLES}
    return out


def cine_frames(prep: PreparedCase, gt: GroundTruth, slices: list[DrivingSlice], thickness_mm: float,
                paths: list[str] | None = None) -> list:
    """The ``cine`` targets' frames: per slice, the GT-warped planning image averaged over ``thickness_mm`` around it
    (a rectangular slice profile), one voxel thick on the planning grid, as :class:`warpmpm.cine.CineFrame` (plane
    ``k``, 0.1 s apart); ``paths``: where each frame would be written (its name in messages)."""
    from ..cine import _frame
    from .cine_series import _frame_image

    case = prep.case
    if case.image is None:
        raise InputError("--targets cine images the planes from the planning image: give --image (the phantom has one)")
    _, warped = planning_and_gt_volumes(case, gt)
    rng = np.random.default_rng(0)
    out = []
    for k, s in enumerate(slices):
        ijk = np.asarray([(np.asarray(case.geometry.size) - 1) / 2.0])
        ijk[0, s.image_axis(case.geometry)] = s.index
        through = case.geometry.index_to_world(ijk)[0]
        img = _frame_image(warped, case, s.orientation, through, thickness_mm, 0.0, rng, None)
        f = _frame(paths[k] if paths else f"{prep.to_input(s)} (captured plane {k})", img, 0.1 * k, thickness_mm)
        f.plane = k
        out.append(f)
    return out


#: an organ's registered in-plane motion within this of its true in-plane motion (mean over its particles on the
#: plane) is a good registration (issue 52's label)
GOOD_REGISTRATION_MM = 1.0


def organ_check_rows(model: ParticleModel, frame, before_mm: np.ndarray, truth_mm: np.ndarray, registration, candidates: dict,
                     plane: str) -> list[dict]:
    """The organ check of one frame judged against the truth: per organ the tracker considered, whether its own motion
    was kept (else the whole slice's moved it) and why, and the mean in-plane distance (mm) of its particles on the plane
    (before the frame) moved by its own registration and by the whole slice's from where the truth puts them; ``good``:
    its own within :data:`GOOD_REGISTRATION_MM`."""
    if registration is None:
        return []
    organ_of = np.asarray(model.organs)[model.organ_index]
    on = np.abs(frame.distance_mm(before_mm)) <= frame.thickness_mm / 2
    P = frame.projector
    out = []
    for organ, c in candidates.items():
        sel = on & (organ_of == organ)
        if not sel.any():
            continue
        true = (truth_mm[sel] - before_mm[sel]) @ P

        def error(aff):
            return float(np.linalg.norm(aff.apply(before_mm[sel], frame.e_u, frame.e_v, frame.centre_mm) - before_mm[sel] - true,
                                        axis=1).mean())

        own = error(c["registration"].affine) if c["registration"] is not None and c["registration"].ok else float("nan")
        out.append({"plane": plane, "organ": organ, "kept": bool(c["kept"]), "why": c["why"], "particles": int(sel.sum()),
                    "own_error_mm": own, "whole_error_mm": error(registration[0].affine),
                    "true_motion_mm": float(np.linalg.norm(true, axis=1).mean()),
                    "good": bool(own <= GOOD_REGISTRATION_MM)})
    return out


def cine_targets(prep: PreparedCase, gt: GroundTruth, model: ParticleModel, gt_pos: np.ndarray, slices: list[DrivingSlice],
                 cfg: CaseConfig) -> RunTargets:
    """``--targets cine`` (module docstring): the captured planes through the tracker's frame pipeline."""
    import time

    from ..tracker import Tracker, TrackerConfig

    frames = cine_frames(prep, gt, slices, cfg.cine_thickness_mm)
    t0 = time.perf_counter()
    tracker = Tracker(prep.case, frames, TrackerConfig(organs=model.letters, registration_linear_prior=cfg.cine_linear_prior),
                      model=model)
    first, rows, affines, organ_affines, checked = None, [], [], {}, []
    for k, (s, f) in enumerate(zip(slices, frames)):
        before = tracker.positions_mm()
        tf = tracker.step(k, f)
        checked += organ_check_rows(model, f, before, gt_pos, tracker.last_registration, tracker.last_candidates,
                                    str(prep.to_input(s)))
        rows.append(tf.row)
        if first is None:
            first = tf.positions_mm.copy()
        reg = tracker.last_registration
        affines.append(reg[0].affine if reg else InPlaneAffine(np.eye(2)))
        organ_affines[s] = {o: r.affine for o, r in reg[1].items()} if reg else {}
    final = tracker.positions_mm()
    x0 = model.positions_mm
    drive = slice_targets(model, x0, slices, lambda s, idx: final[idx])
    err = in_plane_errors_mm(model, slices, drive.idx, drive.targets_mm, gt_pos)
    info = {"method": "cine (the tracker's frame pipeline)", "error_mm": float(err.mean()) if err.size else float("nan"),
            "median_error_mm": float(np.median(err)) if err.size else float("nan"),
            "wall_s": float(np.mean([r["registration_ms"] for r in rows])) / 1e3, "frames": rows,
            "tracked_wall_s": time.perf_counter() - t0, "thickness_mm": cfg.cine_thickness_mm,
            "skipped": [str(prep.to_input(s)) for s, r in zip(slices, rows) if r["solver"] == "none"], "organ_check": checked}
    return RunTargets(drive, affines, organ_affines, info, info["error_mm"], combined_mm=final, first_plane_mm=first)


def run_targets(prep: PreparedCase, gt: GroundTruth, model: ParticleModel, gt_pos: np.ndarray, slices: list[DrivingSlice],
                cfg: CaseConfig) -> RunTargets:
    """The targets of ``cfg.targets`` for ``model`` driven from ``slices``."""
    if cfg.targets == "cine":
        return cine_targets(prep, gt, model, gt_pos, slices, cfg)
    x0 = model.positions_mm
    if cfg.targets in ("affine", "gt", "gt-inplane"):
        affines = slice_affines(prep, model, gt_pos, slices, cfg)
        if cfg.targets == "affine":
            drive = affine_drive_targets(model, x0, slices, affines, prep.centre_mm)
        else:
            drive = in_plane_truth_targets(model, x0, slices, gt_pos)
            if cfg.targets == "gt":  # the true 3D positions, driven in 3D
                drive = DriveTargets(drive.idx, gt_pos[drive.idx], np.tile(np.eye(3), (len(drive.idx), 1, 1)))
        err = in_plane_errors_mm(model, slices, drive.idx, drive.targets_mm, gt_pos)
        organ_affines, combined = {}, None
        if cfg.targets != "affine":  # the baselines copy what the true in-plane motion shows, organ by organ
            organ_affines = truth_organ_affines(model, gt_pos, slices, prep.centre_mm)
        if len(slices) > 1:  # every plane's motion copied and combined (the fitted affine's: one per slice)
            copied = {s: propagate(model, s, a, prep.centre_mm, organ_affines.get(s)) for s, a in zip(slices, affines)}
            combined = combine_planes(model, x0, slices, lambda s, i: copied[s][i])
        return RunTargets(drive, affines, organ_affines, in_plane_error_mm=float(err.mean()) if err.size else float("nan"),
                          combined_mm=combined)
    case = prep.case
    planning, warped = planning_and_gt_volumes(case, gt)
    values = {o: case.label_map[o] for o in gt.model.organs}
    method = {"registration": "organs", "registration-affine": "affine", "registration-bspline": "bspline",
              "registration-demons": "demons"}[cfg.targets]
    drive, info = registration_targets(model, slices, planning, warped, case.labels, case.geometry, values, prep.centre_mm,
                                       truth_mm=gt_pos, method=method, backend=cfg.registration, passes=cfg.registration_passes,
                                       slice_name=lambda s: f"{s.orientation} slice {prep.to_input(s).index}")
    moved = info.pop("moved")
    if cfg.plane_check and info.get("passes", 1) == 1:  # each plane's motion checked against the captured planes
        from ..plane_check import check_planes, combined_motion

        pc, keep = check_planes(model, slices, moved, planning, warped, case.labels, case.geometry, values, prep.centre_mm,
                                name=lambda s: str(prep.to_input(s)))
        info["plane_check"] = pc.to_json()
        if pc.dropped:
            drive = slice_targets(model, model.positions_mm, slices, moved, keep)
            info["combined_mm"] = combined_motion(model, model.positions_mm, slices, moved, keep)
            err = in_plane_errors_mm(model, slices, drive.idx, drive.targets_mm, gt_pos) if len(drive.idx) else np.zeros(0)
            info["error_mm"] = float(err.mean()) if err.size else float("nan")
    first = info.pop("first_pass", None)  # several passes: the baselines copy the planes' motion against planning
    affines, organ_affines, fields = info.pop("affines"), info.pop("organ_affines"), info.pop("fields")
    organ_fields = info.pop("organ_fields")
    if first is not None:
        affines, organ_affines, fields, organ_fields = (first[k] for k in ("affines", "organ_affines", "fields", "organ_fields"))
    combined = info.pop("combined_mm")
    info["organ_affines"] = {str(prep.to_input(s)): {o: a.to_json() for o, a in d.items()} for s, d in organ_affines.items()}
    info["organ_fields"] = {str(prep.to_input(s)): {o: {"min_jacobian": f.min_jacobian, "wall_s": f.wall_s} for o, f in d.items()}
                            for s, d in organ_fields.items()}
    from ..plane_check import plane_match

    def match(positions_mm):
        return float(np.mean(plane_match(model, slices, planning, warped, case.labels, case.geometry, values, prep.centre_mm,
                                         positions_mm)))

    return RunTargets(drive, affines, organ_affines, info, info.get("error_mm", float("nan")), fields, organ_fields,
                      combined if len(slices) > 1 else None, plane_match=match)
