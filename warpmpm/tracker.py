"""Track a cine series: a planning scan with its organ labels and 2D cine frames in, 3D organ motion out.

For each frame, in acquisition order: the frame is registered, organ by organ
(:func:`warpmpm.registration.register_slice_organs`, the organ footprints from the current estimate's
label map), against the current estimate rendered on the frame's plane (the planning image moved by the
estimate and averaged over the slice thickness, :func:`warpmpm.imaging.render_plane`; the default
``reference="estimate"``), or against the last frame of the same plane (``reference="previous-frame"``, the
first against the planning image); the particles lying within the frame's slice thickness of its plane *in the current
estimate* (not at planning: organs move through a plane as they breathe) take that motion in the plane
(the through-plane part is left to the physics or to another plane). Every organ a plane shows takes the motion
the planes observed, combined over the series' planes (the last frame of each); then a registered estimator
(:mod:`warpmpm.estimators`) decides every particle's position:

- ``estimator="copy"`` (default): that observed motion as it is (each organ by what the frame shows of it, an organ it
  does not measure by the whole slice's motion); the measured best, see :attr:`TrackerConfig.estimator`.
- ``estimator="slice-driven"``: the seed's multi-organ MPM moves from the previous frame's state, predicted
  by the frame's motion, to a new equilibrium driven at the particles on the frame's plane.
- ``estimator="completion"``: the equilibrium of the whole abdomen (organs, the tissue around them, the held spine;
  :mod:`warpmpm.solvers.completion`) driven by that observed motion decides the organs farther than ``reach_mm`` from
  every plane; the others keep the copy. Its response to each seen organ's affine motion is solved once before the
  first frame (:class:`~warpmpm.solvers.completion.ReducedCompletion`, one plane set: every plane of the series), so
  a frame is a small fit and a matrix product (milliseconds).

The ground truth, when there is one, is never read here.

Per frame the tracker writes a row of ``track.csv`` and hands the estimate to its outputs (:mod:`warpmpm.outputs`:
the label map on the planning grid by default, the 3D displacement field, DICOM objects, the accumulated dose, a
recording); the whole session (inputs checked, the output folder, ``track.json``) is :func:`warpmpm.session.track`.
"""

from __future__ import annotations

import csv
import os
import time
import warnings
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import SimpleITK as sitk

from .cine import CineFrame
from .errors import InputError, InputWarning
from .images import ORGANS, Case
from .model import ParticleModel, build_model
from .registration import BACKENDS, register_slice_organs, slice_metric
from .slices import copy_organ_motion
from .imaging import particle_label_map, render_plane, scatter_displacements
from .estimators import FrameObservation, get_estimator
from .solvers import SolverConfig
from .solvers.completion import CompletionConfig

__all__ = ["TRACK_FIELDS", "TrackerConfig", "TrackedFrame", "Tracker", "displacement_field"]

TRACK_FIELDS = ["frame", "time_s", "plane", "file", "solver", "steps", "linear_iterations", "converged", "slice_converged", "settled",
                "body_motion_mm", "reason",
                "wall_s", "rms_residual_mm", "frame_match", "registration_ms",
                "reference_ms", "pancreas_x_mm", "pancreas_y_mm", "pancreas_z_mm", "pancreas_shift_mm"] + [f"max_{o}_mm" for o in ORGANS] + [
                "field_jacobian_min", "field_folded_voxels"]


#: a frame whose registered reference matches it with a squared correlation below this over the organs (|r| < 0.2) is not
#: driven: a blank, corrupt or foreign frame (synthetic frames of the tracked anatomy match at r^2 above 0.8)
MIN_FRAME_MATCH = 0.04


def _off_scan_message(frame, geometry, organ_distance_mm: np.ndarray, letters: str) -> str:
    """The refusal of a frame whose plane misses the organs: how far it lies from them and from the planning scan."""
    size = np.asarray(geometry.size, dtype=np.float64) - 1
    corners = geometry.index_to_world(np.array([size * np.array(b) for b in np.ndindex(2, 2, 2)]))
    d = frame.distance_mm(corners)
    near = float(np.min(np.abs(organ_distance_mm)))
    if d.min() > 0 or d.max() < 0:
        scan = f"it does not cross the planning scan either: it lies {float(np.min(np.abs(d))):.1f} mm outside it"
    else:
        scan = "it crosses the planning scan but not the organs"
    return (f"cine frame {frame.path}: its plane lies {near:.1f} mm from the nearest organ of the model ({letters}; "
            f"{frame.thickness_mm:g} mm thick); {scan}. Is the cine of this patient and this session, and in the scanner "
            "coordinates of the planning scan (both world LPS)?")


@dataclass(frozen=True)
class TrackerConfig:
    """How a series is tracked."""

    estimator: str = "copy"
    """Which registered estimator (:data:`warpmpm.estimators.ESTIMATORS`, ``warpmpm estimators``) turns a frame's observed
    motion into every particle's position. ``copy`` (default): each organ moved by the in-plane motion the frame shows
    of it, no physics; the measured best: on the finite-element series the slice-driven MPM's estimate equals it on
    every organ, for 0.02-0.05 s more a frame. ``slice-driven``: the seed's MPM driven at the plane's particles from the
    frame's predicted motion (:attr:`solver`, :attr:`max_steps`, :attr:`wait_settled`, :attr:`predict` apply to it
    only). ``completion``: the whole abdomen's equilibrium driven by the observed motion, set up once for the
    series' planes (:attr:`completion`, 40-90 s on 2 cores); every organ within :attr:`reach_mm` of a plane keeps the
    copy, the others take the equilibrium's motion. Measured on finite-element series (``benchmarks/track_fem.py``) it
    equals the copy on the seen organs and is better on an organ no plane reaches in 1 of 4 cases (CT sample, sagittal +
    coronal, left kidney 2.18 mm against 2.73), worse in 3 (MR sample, sagittal, duodenum 1.96 against 1.15; CT,
    sagittal, kidney 2.01 against 1.73; phantom, sagittal, kidney 2.44 against 2.28): not the default."""
    materials: str | None = None
    """The organs' and tissues' materials (:mod:`warpmpm.materials`: ``paper``, ``tissue`` or a JSON file) for the
    estimators that use any: the slice-driven MPM (default ``paper``, the seed's) and the completion (default
    ``tissue``, :attr:`CompletionConfig.materials`). None: each its own default. The copy uses none."""
    completion: CompletionConfig = field(default_factory=CompletionConfig)
    """The completion model's settings (:class:`~warpmpm.solvers.completion.CompletionConfig`)."""
    preset: str | None = None
    """The label preset of the planning labels (``amos``, ``totalseg_mr``, ``totalseg_ct``): which other labels are
    vertebrae (held still) and liver in the completion model; None: only the organs and the body outline are known."""

    organs: str = "psdl"
    """Organ combination (paper letters) of the model; organs absent from the labels are left out."""
    particle_step: int = 1
    """In-plane particle sampling step of the planning model."""
    max_steps: int = 3000
    """Steps per frame before the frame is reported not converged."""
    displacement: bool = False
    """Also write each frame's 3D displacement field."""
    wait_settled: bool = False
    """The settled mode: every frame runs on until the whole model has settled, with adaptive damping and a PD
    drive (:class:`~warpmpm.driving.ConvergenceConfig`, :class:`~warpmpm.solvers.config.SolverConfig`); ``max_steps``
    still caps a frame."""
    solver: SolverConfig = field(default_factory=lambda: SolverConfig(method="auto"))
    """The MPM solver's settings. Default ``method="auto"``: a predicted frame starts in equilibrium, which one
    Newton iteration confirms where the explicit rule needs its 100-step window (docs/performance.md); a frame
    the Newton iterations do not settle goes on explicitly."""
    margin_mm: float = 40.0
    """Room around the organs for the motion of a whole series (the grid is built once)."""
    predict: bool = True
    """Start each frame from a prediction: every particle moved by the in-plane motion its organ shows on the
    frame (the ``propagate`` baseline's step), then the physics corrects it from there. Without it the frame
    starts from the last frame's estimate and the body lags the slice until it has settled."""
    registration: str = "gauss-newton"
    """The slice registration's backend (:func:`warpmpm.registration.register_slices`): ``"gauss-newton"``
    (default: measured on five MR cine series, 3-3.6x faster than ITK's and as accurate or better; docs/results.md) or
    ``"itk"``."""
    registration_linear_prior: float = 10.0
    """With the Gauss-Newton backend, how strongly a frame's registration keeps the linear part (scale, shear,
    rotation) of its motion near the identity (the whole slice) or the whole slice's (each organ's):
    :attr:`warpmpm.gauss_newton.GaussNewtonConfig.linear_prior`. Frames 0.1-0.3 s apart mostly translate; a small
    footprint fixes its translation well and its linear part poorly, and the error of that part is carried to
    the organ's particles away from the plane and accumulates frame after frame."""
    reference: Literal["estimate", "previous-frame"] = "estimate"
    """What a frame is registered against. ``"estimate"`` (default): the current estimate rendered on the frame's
    plane (:func:`warpmpm.imaging.render_plane`), so the registration measures what the estimate still misses
    and its errors do not add up frame after frame; through-plane motion another plane has measured is in the
    reference. ``"previous-frame"``: the plane's last frame (the first: the planning image), the motion since then.
    The estimate is 11.6 % lower on the mean of five MR cine series, lower on each, for ~30 ms a frame of rendering
    (docs/results.md)."""
    unseen: Literal["whole-slice", "nearest", "global", "none"] = "whole-slice"
    """The ``copy`` estimator's rule for an organ the frame's registration does not measure (off the plane, or too little
    of it on it): ``whole-slice`` the whole slice's in-plane affine applied at the organ; ``nearest`` the mean in-plane
    motion of the nearest measured organ (centroids); ``global`` the mean in-plane motion of the measured organs' particles;
    ``none`` no motion from this frame. Measured in ``docs/decisions/2026-12-04-estimators.md``."""
    reach_mm: float = 15.0
    """How far (mm) a particle may start from a plane and still come onto it during the series: those within
    half the slice thickness plus this of a plane at planning are the candidates checked every frame."""


@dataclass
class TrackedFrame:
    """One frame's estimate: positions (N, 3, mm) and what it cost."""

    positions_mm: np.ndarray
    row: dict


class Tracker:
    """Follows a cine series frame after frame (module docstring)."""

    def __init__(self, case: Case, frames: list[CineFrame], config: TrackerConfig | None = None,
                 model: ParticleModel | None = None):
        """``model``: the planning particle model when it is built already (``warpmpm run``'s ``cine`` targets track
        the run's own model); None: built from ``case`` (:attr:`TrackerConfig.organs`, :attr:`~TrackerConfig.particle_step`)."""
        cfg = config or TrackerConfig()
        self.config, self.case, self.frames = cfg, case, frames
        if cfg.registration not in BACKENDS:
            raise InputError(f"TrackerConfig.registration must be one of {', '.join(BACKENDS)}, got {cfg.registration!r}")
        lp = cfg.registration_linear_prior
        if not (isinstance(lp, (int, float)) and not isinstance(lp, bool) and np.isfinite(lp) and lp >= 0):
            raise InputError(f"--linear-prior (TrackerConfig.registration_linear_prior) must be a finite number >= 0, got {lp!r}")
        if cfg.unseen not in ("whole-slice", "nearest", "global", "none"):
            raise InputError(f"TrackerConfig.unseen must be whole-slice, nearest, global or none, got {cfg.unseen!r}")
        if cfg.reference not in ("estimate", "previous-frame"):
            raise InputError(f"TrackerConfig.reference must be 'estimate' or 'previous-frame', got {cfg.reference!r}")

        estimator_class = get_estimator(cfg.estimator)
        if cfg.estimator != "slice-driven" and (cfg.wait_settled or not cfg.predict):
            raise InputError(f"--wait-settled and --no-predict set the slice-driven MPM; the {cfg.estimator} estimator does not "
                             "use it: drop them, or add --estimator slice-driven")
        if case.image is None:
            raise InputError("tracking needs the planning image (--image): the frames are registered against it, moved by the estimate")
        if cfg.materials is not None:
            from .materials import material_table

            table = material_table(cfg.materials)
            cfg = replace(cfg, completion=replace(cfg.completion, materials=cfg.materials))
            self.config = cfg
        if model is None:
            present = [o for o in ORGANS if o in case.label_map and np.any(case.labels == case.label_map[o])]
            wanted = [o for o, c in zip(ORGANS, "psdl") if c in cfg.organs and o in present]
            model = build_model(case, tuple(wanted), sampling_step=cfg.particle_step)
        if cfg.materials is not None:
            model = replace(model, materials={**model.materials, **table.organ_materials(model.organs)})
        self.model: ParticleModel = model
        m = self.model
        self.label_values = {o: case.label_map[o] for o in m.organs}
        candidates: dict[int, tuple[CineFrame, np.ndarray]] = {}  # per plane: its first frame and its candidates
        for f in frames:
            if f.plane in candidates:
                continue
            dist = f.distance_mm(m.positions_mm)
            if not np.any(np.abs(dist) <= f.thickness_mm / 2):
                raise InputError(_off_scan_message(f, case.geometry, dist, m.letters))
            candidates[f.plane] = (f, np.nonzero(np.abs(dist) <= f.thickness_mm / 2 + cfg.reach_mm)[0])
        if all(abs(f.normal[2]) > np.cos(np.radians(10.0)) for f in frames):
            warnings.warn("every cine frame is transversal: no plane sees superior-inferior motion, so the estimate's "
                          "superior-inferior motion is a guess; image a sagittal or coronal plane too", InputWarning, stacklevel=2)
        #: every particle that may lie on a plane during the series (each frame drives those on it now)
        self.driven = np.unique(np.concatenate([c for _, c in candidates.values()]))
        #: the estimator (:mod:`warpmpm.estimators`), set up once for the series' planes
        self.estimator = estimator_class(m, case, list(candidates.values()), self.driven, cfg)
        self.planning_image = case.intensity_image()  # rendered frame after frame: built once
        self.last_frame: dict[int, CineFrame] = {}
        self.labels_now = case.labels.copy()
        self.propagated = m.positions_mm.copy()  # the baseline: each frame's slice motion copied to every particle
        # per plane, the estimate (and the baseline) when that plane was last imaged, and its label map: a frame's
        # registration measures the motion since then, so that is what it moves (with interleaved planes the
        # other plane's frames have moved the model meanwhile, and applying the motion to the current state
        # would count the shared direction twice)
        self.plane_positions: dict[int, np.ndarray] = {}
        self.plane_propagated: dict[int, np.ndarray] = {}
        self.plane_labels: dict[int, np.ndarray] = {}
        #: the last frame's registration: (the whole slice's, {organ: its own}) results, None when it failed
        self.last_registration = None
        self.last_candidates: dict = {}
        #: the baselines for an organ a frame does not measure, through the estimator interface: the copy with the
        #: ``nearest`` and ``global`` rules (:attr:`TrackerConfig.unseen`), each following the series from its own state
        #: (``particles.npz``: ``nearest_mm``, ``global_mm``; ``evaluate-track`` scores them on the organs no frame measured)
        self.baselines: dict[str, dict] = {}
        for rule in ("nearest", "global"):
            b = get_estimator("copy")(m, case, list(candidates.values()), self.driven, replace(cfg, unseen=rule))
            self.baselines[rule] = {"estimator": b, "positions": m.positions_mm.copy(), "plane": {}}
        #: the organs some frame's registration measured (the others were seen by no plane)
        self.measured_organs: set = set()

    def positions_mm(self) -> np.ndarray:
        """The current estimate: every particle's position (N, 3), mm, world LPS."""
        return self.estimator.positions_mm()

    def _organ_masks(self, frame: CineFrame, labels: np.ndarray) -> tuple[sitk.Image, dict]:
        """The organs' footprints on ``frame``'s plane in ``labels`` (the reference's content: the current estimate's
        label map, or the plane's when it was last imaged): the whole (dilated 6 mm) and each organ's own."""
        img = self.case.geometry.apply_to(sitk.GetImageFromArray(labels.astype(np.int32)))
        lab = frame.slice_2d(img, sitk.sitkNearestNeighbor)
        arr = sitk.GetArrayFromImage(lab)
        own = {}
        for o, v in self.label_values.items():
            mi = sitk.GetImageFromArray((np.rint(arr) == v).astype(np.uint8))
            mi.CopyInformation(lab)
            own[o] = mi
        whole = sitk.GetImageFromArray(np.isin(np.rint(arr), list(self.label_values.values())).astype(np.uint8))
        whole.CopyInformation(lab)
        whole = sitk.BinaryDilate(whole, [max(1, int(round(6.0 / s))) for s in whole.GetSpacing()])
        if not np.any(sitk.GetArrayViewFromImage(whole)):
            raise InputError(f"cine frame {frame.path} shows none of the organs {self.model.letters}")
        return whole, own

    def on_plane(self, frame: CineFrame, positions_mm: np.ndarray) -> np.ndarray:
        """Which driven candidates lie within half the slice thickness of ``frame``'s plane at ``positions_mm``
        (all particles' positions, N x 3): a mask over :attr:`driven`."""
        return np.abs(frame.distance_mm(positions_mm[self.driven])) <= frame.thickness_mm / 2

    def step(self, n: int, frame: CineFrame) -> TrackedFrame:
        """Estimate one frame (from the previous one's state)."""
        m = self.model
        self.last_registration = None
        #: the last frame's organ check: organ -> its own registration, kept or not and why
        self.last_candidates: dict = {}
        x = self.positions_mm()
        prev = self.last_frame.get(frame.plane)
        t_ref = time.perf_counter()
        by_estimate = self.config.reference == "estimate"
        if by_estimate or prev is None:
            shown = x if by_estimate else m.positions_mm
            stored = frame.slice_2d(render_plane(self.case, m.positions_mm, shown, frame.image, frame.normal, frame.thickness_mm,
                                                 planning_image=self.planning_image))
        else:
            stored = prev.slice_2d()
        ref_s = time.perf_counter() - t_ref
        captured = frame.slice_2d()
        mask, own = self._organ_masks(frame, self.labels_now if by_estimate else self.plane_labels.get(frame.plane, self.case.labels))
        t_reg = time.perf_counter()
        try:
            whole, per_organ = register_slice_organs(stored, captured, frame.centre_mm, mask, own, backend=self.config.registration,
                                                     linear_prior=self.config.registration_linear_prior,
                                                     candidates=self.last_candidates)
        except InputError as exc:  # a blank or constant frame: flagged and not driven, the series goes on
            return self._skipped(n, frame, x, time.perf_counter() - t_reg, ref_s, str(exc))
        reg_s = time.perf_counter() - t_reg  # the whole call: refused organs and the fit checks cost time too
        if not whole.ok:
            return self._skipped(n, frame, x, reg_s, ref_s, whole.stop)
        match = -slice_metric(stored, captured, mask, whole.affine)  # r^2 of the frame and its registered reference
        if not match >= MIN_FRAME_MATCH:
            return self._skipped(n, frame, x, reg_s, ref_s, f"the frame does not look like the estimate on its plane (r^2 {match:.3f} "
                                 f"after registration over the organs, at least {MIN_FRAME_MATCH} needed): a blank, corrupt or "
                                 "foreign frame?", match=match)
        organ_of = np.asarray(m.organs)[m.organ_index]
        self.last_registration = (whole, per_organ)

        organ_affines = {o: r.affine for o, r in per_organ.items()}

        def observed(now, then):
            """``now`` with its in-plane components replaced by where the frame's per-organ motion takes ``then``
            (the positions when the plane was last imaged); the through-plane components are kept."""
            moved = copy_organ_motion(then, organ_of, frame.e_u, frame.e_v, frame.centre_mm, whole.affine, organ_affines)
            return now + (moved - now) @ frame.projector

        on = self.on_plane(frame, x)
        if not on.any():
            raise InputError(f"cine frame {frame.path}: no particle of the current estimate lies on its plane "
                             f"(the organs have moved out of it)")
        # the registration moves the reference's content: the estimate now, or the plane when it was last imaged
        seen = observed(x, x if by_estimate else self.plane_positions.get(frame.plane, m.positions_mm))
        if self.estimator.baseline_from_estimate:  # the baseline: the frame's motion from the last estimate
            self.propagated = (seen.copy() if by_estimate else
                               observed(self.propagated, self.plane_propagated.get(frame.plane, m.positions_mm)))
        else:  # the baseline on its own: the frame's motion applied to the copy's positions (the estimate leaves the copy)
            self.propagated = observed(self.propagated, self.propagated if by_estimate else
                                       self.plane_propagated.get(frame.plane, m.positions_mm))
        est = self.estimator.estimate(FrameObservation(frame, x, seen, on, tuple(per_organ)))
        positions, solve = est.positions_mm, est.solve
        self.measured_organs |= set(per_organ)
        for b in self.baselines.values():  # each from its own state, by the frame's motion
            now = b["positions"]
            b_seen = observed(now, now if by_estimate else b["plane"].get(frame.plane, m.positions_mm))
            b["positions"] = b["estimator"].estimate(FrameObservation(frame, now, b_seen, on, tuple(per_organ))).positions_mm
            b["plane"][frame.plane] = b["positions"].copy()
        self.last_frame[frame.plane] = frame
        self.labels_now = particle_label_map(m, positions, self.label_values)
        self.plane_positions[frame.plane] = positions
        self.plane_propagated[frame.plane] = self.propagated.copy()
        self.plane_labels[frame.plane] = self.labels_now
        return TrackedFrame(positions, self._row(n, frame, positions, reg_s, ref_s, frame_match=match, **solve))

    def _skipped(self, n: int, frame: CineFrame, x: np.ndarray, reg_s: float, ref_s: float, why: str,
                 match: float = float("nan")) -> TrackedFrame:
        """A frame whose slice registration failed: the estimate holds where it was (the frame is flagged in
        ``track.csv``, not hidden), and the motion missed here is measured by the plane's next frame: registered
        against the estimate (which held), or with ``reference="previous-frame"`` against the plane's last good frame."""
        nxt = "the held estimate" if self.config.reference == "estimate" else "its last good frame"
        warnings.warn(f"cine frame {frame.path}: the slice registration failed ({why}); the estimate holds the last frame's "
                      f"state and the plane's next frame is registered against {nxt}", InputWarning, stacklevel=3)
        return TrackedFrame(x.copy(), self._row(n, frame, x, reg_s, ref_s, solver="none", steps=0, linear_iterations=0, converged=False,
                                                slice_converged=False,
                                                settled=False, body_motion_mm=float("nan"), reason=f"registration failed: {why}", wall_s=0.0,
                                                rms_residual_mm=float("nan"), frame_match=match))

    def _row(self, n: int, frame: CineFrame, positions_mm: np.ndarray, reg_s: float, ref_s: float, **solve) -> dict:
        """A frame's ``track.csv`` row: what the solve did (``solve``), the registration's and the reference's
        (rendering) times, the pancreas centroid and its shift from planning, and each organ's largest displacement."""
        m = self.model
        pan = m.organ_slice("pancreas")
        c = positions_mm[pan].mean(0)
        disp = np.linalg.norm(positions_mm - m.positions_mm, axis=1)
        row = {"frame": n, "time_s": round(frame.time_s, 4), "plane": frame.plane, "file": os.path.basename(frame.path), **solve,
               "registration_ms": 1e3 * reg_s, "reference_ms": 1e3 * ref_s, "pancreas_x_mm": c[0], "pancreas_y_mm": c[1], "pancreas_z_mm": c[2],
               "pancreas_shift_mm": float(np.linalg.norm(c - m.positions_mm[pan].mean(0)))}
        for o in ORGANS:
            row[f"max_{o}_mm"] = float(disp[m.organ_slice(o)].max()) if o in m.organs else ""
        return row

    def run(self, out_dir: str, progress=None, outputs=None) -> list[dict]:
        """Track every frame, writing ``track.csv`` and ``particles.npz`` into ``out_dir`` and each of ``outputs``
        (:mod:`warpmpm.outputs`; None: the label maps, and the displacement fields with :attr:`TrackerConfig.displacement`);
        returns the CSV rows. Every output is closed here (``ok=False`` when tracking fails)."""
        from .outputs import DisplacementFields, LabelMaps

        if outputs is None:
            outputs = [LabelMaps()] + ([DisplacementFields()] if self.config.displacement else [])
        elif self.config.displacement and not any(o.name == "displacement" for o in outputs):
            outputs = [*outputs, DisplacementFields()]
        ok = False
        try:
            rows = self._run(out_dir, progress, list(outputs))
            ok = True
            return rows
        finally:
            for o in outputs:
                o.close(ok)

    def field_quality(self, field_mm: np.ndarray) -> dict:
        """The smallest Jacobian determinant of ``x -> x + u(x)`` inside the planning organs, and how many of their
        voxels it folds (determinant <= 0)."""
        from .fields import jacobian_determinant

        inside = np.isin(self.case.labels, list(self.label_values.values()))
        J = jacobian_determinant(field_mm, self.case.geometry)[inside]
        return {"field_jacobian_min": float(J.min()) if J.size else float("nan"), "field_folded_voxels": int(np.sum(J <= 0))}

    def _run(self, out_dir: str, progress, outputs) -> list[dict]:
        os.makedirs(out_dir, exist_ok=True)
        for o in outputs:
            o.begin(self, out_dir)
        field_needed = any(o.needs_field for o in outputs)
        rows, positions, propagated = [], [], []
        baselines = {name: [] for name in self.baselines}
        for n, frame in enumerate(self.frames):
            t0 = time.perf_counter()
            tf = self.step(n, frame)
            tf.row["latency_s"] = time.perf_counter() - t0
            rows.append(tf.row)
            positions.append(tf.positions_mm)
            propagated.append(self.propagated.copy())
            for name, b in self.baselines.items():
                baselines[name].append(b["positions"].copy())
            field_mm = None
            if field_needed:
                field_mm = sitk.GetArrayFromImage(displacement_field(self.model, tf.positions_mm, self.case))
                tf.row.update(self.field_quality(field_mm))
            for o in outputs:
                o.frame(self, out_dir, n, frame, tf.positions_mm, self.labels_now, field_mm)
            if progress:
                unit = "Newton iterations" if tf.row["solver"] == "quasistatic" else "steps"
                work = (f"{tf.row['solver']} {1e3 * tf.row['wall_s']:.0f} ms" if tf.row["solver"] in ("completion", "copy") else
                        f"{tf.row['steps']} {unit}")
                progress(f"frame {n}: plane {frame.plane}, {work}, {tf.row['latency_s'] * 1e3:.0f} ms "
                         f"(registration {tf.row['registration_ms']:.0f} ms, reference {tf.row['reference_ms']:.0f} ms), pancreas moved {tf.row['pancreas_shift_mm']:.2f} mm")
        _write_csv(os.path.join(out_dir, "track.csv"), rows, TRACK_FIELDS + ["latency_s"])
        for o in outputs:
            o.end(self, out_dir, rows)
        tmp = os.path.join(out_dir, "particles.part.npz")
        np.savez_compressed(tmp, planning_mm=self.model.positions_mm, organ_index=self.model.organ_index,
                            organs=np.asarray(self.model.organs), estimate_mm=np.asarray(positions), propagate_mm=np.asarray(propagated),
                            measured_organs=np.asarray(sorted(self.measured_organs), dtype=str),
                            **{f"{name}_mm": np.asarray(v) for name, v in baselines.items()})
        os.replace(tmp, os.path.join(out_dir, "particles.npz"))
        return rows


def displacement_field(model: ParticleModel, positions_mm: np.ndarray, case: Case, sigma_mm: float = 4.0) -> sitk.Image:
    """The 3D displacement (mm, world axes, float32) on the planning grid: each particle's displacement
    ``positions_mm - model.positions_mm`` scattered to its planning voxel and filled by normalised Gaussian
    smoothing (``sigma_mm``), ``u(x) = G*(sum u_p) / G*(count)``, faded out away from the organs by the weight
    ``w = min(1, 4 G*count / max G*count)`` and exactly zero where ``w < 1e-3`` (about 3.5 sigma outside an
    organ's surface). The smoothing runs only over the particles' voxel box plus four sigmas (beyond it the
    weight is below 2e-4); the field there is the full grid's to float32 rounding."""
    g = case.geometry
    positions_mm = np.asarray(positions_mm, dtype=np.float64)
    if positions_mm.shape != model.positions_mm.shape:
        raise InputError(f"displacement field: {positions_mm.shape[0] if positions_mm.ndim == 2 else positions_mm.shape} positions "
                         f"for a model of {model.positions_mm.shape[0]} particles; pass one (x, y, z) mm row per particle")
    if not np.isfinite(positions_mm).all():
        raise InputError("displacement field: the estimate holds non-finite positions; nothing was written")
    size = np.asarray(g.size)
    ijk = np.clip(np.rint(g.world_to_index(model.positions_mm)).astype(np.int64), 0, size - 1)
    margin = np.ceil(4.0 * sigma_mm / np.asarray(g.spacing_mm)).astype(np.int64)
    lo = np.maximum(ijk.min(0) - margin, 0)
    hi = np.minimum(ijk.max(0) + margin + 1, size)
    box = tuple(int(v) for v in hi - lo)
    sub = g.crop(tuple(int(v) for v in lo), tuple(int(v) for v in hi))
    # count, then the sums of u (the scatter adds the negated argument: the rendering's backward field)
    acc, _ = scatter_displacements(ijk - lo, box, model.positions_mm - positions_mm, (1, 1, 1))
    sm = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(sub.apply_to(sitk.GetImageFromArray(acc, isVector=True)), sigma_mm))
    d = sm[..., 0]
    w = np.clip(d * (4.0 / max(float(d.max()), 1e-12)), 0.0, 1.0)
    w[w < 1e-3] = 0.0
    f = np.zeros(tuple(g.size[::-1]) + (3,), dtype=np.float32)
    f[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]] = sm[..., 1:] * (w / np.maximum(d, 1e-6))[..., None]
    return g.apply_to(sitk.GetImageFromArray(f, isVector=True))


def _write_csv(path: str, rows: list[dict], fields: list[str]) -> None:
    tmp = path + ".part"
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})
    os.replace(tmp, path)
