"""One run end to end: :func:`run_case` (prepare, ground truth, run) and :func:`run_prepared` (the
estimate and baselines of one condition on a prepared case and its GT, reused by sweeps)."""

from __future__ import annotations

import math

import time
import warnings
from dataclasses import replace

import numpy as np

from ..driving import ConvergenceConfig, DriveResult, SliceDrivenEstimator
from ..errors import InputError, InputWarning
from ..groundtruth import GroundTruth
from ..metrics import evaluate
from ..recorder import NullRecorder, Recorder
from ..slices import driven_indices
from .baselines import propagate, volume_registration
from .organs import baseline_positions, organ_scores, true_distances
from .case import PreparedCase, prepare_case
from .config import CaseConfig
from .result import EstimateScores, RunResult, Scores
from .tables import format_table
from .target_kinds import run_targets
from .truth import gt_for_model, make_ground_truth

__all__ = ["run_prepared", "check_device", "Progress", "size_report", "run_case"]


def run_prepared(prep: PreparedCase, gt: GroundTruth, cfg: CaseConfig, recorder: Recorder | None = None,
                 progress: Progress | None = None) -> RunResult:
    """The estimate and baselines of one (organs, slices, targets) on a prepared case and its GT."""
    recorder = recorder or NullRecorder()
    progress = progress or Progress(None)
    model = prep.model(cfg.organs)
    gt_pos = gt_for_model(gt, model)
    slices = prep.resolve_slices(model, cfg.slices)
    tg = run_targets(prep, gt, model, gt_pos, slices, cfg)
    idx, targets = tg.idx, tg.targets_mm
    axes = tg.axes(cfg.drive) if cfg.targets != "gt" else None
    pmask = model.organ_slice("pancreas")
    exclude_driven = bool(cfg.exclude_driven)  # the same error set for every number of planes
    excl = np.zeros(model.n, dtype=bool)
    if exclude_driven:
        excl[idx] = True
    geom = model.particle_grid  # voxelised where the particles were laid (the planning grid, or a thick scan's lattice)

    offslice = pmask.copy()
    offslice[idx] = False
    driven_share = 1.0 - offslice.sum() / max(pmask.sum(), 1)
    if driven_share > 0.5:
        warnings.warn(f"{driven_share:.0%} of the pancreas particles lie on the driving slices: error and Dice mostly score "
                      "the targets given to them; read error_offslice_mm", InputWarning, stacklevel=2)

    if all(s.orientation == "axial" for s in slices):
        warnings.warn("only axial planes drive this run: no plane sees superior-inferior motion, so every method's "
                      "superior-inferior motion is a guess; add a sagittal or coronal plane (--slices axial:K,sagittal:I)",
                      InputWarning, stacklevel=2)

    def offslice_error(pos) -> float:
        return float(np.linalg.norm(pos[offslice] - gt_pos[offslice], axis=1).mean()) if offslice.any() else float("nan")

    on_plane = np.zeros(model.n, dtype=bool)
    on_plane[idx] = True
    truth_d = true_distances(model, gt_pos)  # the same for every method

    def score(pos, **info) -> Scores:
        m = evaluate(pos[pmask], gt_pos[pmask], geom, excl[pmask], model.sampling_step)
        out = Scores.of(m, offslice_error(pos), **info)
        out.organs = organ_scores(model, pos, gt_pos, on_plane, truth_distances=truth_d)
        return out

    results: dict[str, Scores] = {}
    copies: dict[str, np.ndarray] = {}  # the baselines that copy the planes' motion, checked by the estimate's measure
    copy_mm = None
    if "initial" in cfg.baselines:
        results["initial"] = score(model.positions_mm)
    if "propagate" in cfg.baselines:  # the first slice's motion, as the estimate gets it (per organ when organ-aware)
        copy_mm = tg.first_plane_mm if tg.first_plane_mm is not None else propagate(
            model, slices[0], tg.affines[0], prep.centre_mm, tg.organ_affines.get(slices[0]), tg.fields.get(slices[0]),
            tg.organ_fields.get(slices[0]))
        results["propagate"] = score(copy_mm)
        copies["propagate"] = copy_mm
        if tg.first_plane_mm is None and (tg.organ_affines.get(slices[0]) or tg.fields.get(slices[0]) or tg.organ_fields.get(slices[0])):
            results["propagate_affine"] = score(propagate(model, slices[0], tg.affines[0], prep.centre_mm))
    if "propagate" in cfg.baselines and tg.combined_mm is not None:  # every plane's motion, combined, copied to the body
        results["propagate_planes"] = score(tg.combined_mm)
        copies["propagate_planes"] = tg.combined_mm
    if "rigid" in cfg.baselines:  # each seen organ's observed translation; organs on no plane from their neighbours
        drive_axes = tg.drive.axes if cfg.targets != "gt" else np.tile(np.eye(3), (len(idx), 1, 1))
        for name, pos in baseline_positions(model, idx, targets, drive_axes).items():
            if name == "rigid":
                results[name] = score(pos)
            else:  # nearest / global: only the organs no plane crosses
                unseen = [o for o in model.organs if not results["rigid"].organs[o]["seen"]]
                nan = float("nan")
                r = Scores(error_mm=nan, p95_mm=nan, max_mm=nan, dice=nan, n=0) if "pancreas" not in unseen else score(pos)
                r.organs = organ_scores(model, pos, gt_pos, on_plane, only=unseen, truth_distances=truth_d)
                results[name] = r
    if "completion" in cfg.baselines:  # the whole-abdomen equilibrium completing what the planes see
        from ..solvers.completion import CompletionModel, complete

        if tg.combined_mm is not None:
            copy_mm = tg.combined_mm
        elif copy_mm is None:
            copy_mm = tg.first_plane_mm if tg.first_plane_mm is not None else propagate(
                model, slices[0], tg.affines[0], prep.centre_mm, tg.organ_affines.get(slices[0]), tg.fields.get(slices[0]),
                tg.organ_fields.get(slices[0]))
        t0 = time.perf_counter()
        from ..solvers.completion import CompletionConfig

        ccfg = CompletionConfig() if cfg.materials is None else CompletionConfig(materials=cfg.materials)
        cm = CompletionModel(prep.case, cfg.preset, model, ccfg, device=cfg.device)
        c = complete(cm, idx, targets, tg.drive.axes if cfg.targets != "gt" else None, copy_mm)
        results["completion"] = score(c.positions_mm, wall_s=time.perf_counter() - t0, converged=c.converged,
                                      iterations=c.iterations, residual=c.residual, unknowns=c.info["unknowns"])
        progress.say(f"completion: {c.info['unknowns']:,} unknowns, {c.iterations} CG iterations, "
                     f"{'converged' if c.converged else 'NOT converged'} in {time.perf_counter() - t0:.1f} s")
    if "volume_registration" in cfg.baselines:
        pos, info = volume_registration(prep, gt, model)
        results["volume_registration"] = score(pos, **info)
    recorder.begin(model, gt_pos)
    recorder.log_slices(slices, idx, targets, prep.case, prep.centre_mm)
    if tg.combined_mm is not None:  # the copy's observation: every plane's motion combined, or the one plane's, by organ
        copy_mm = tg.combined_mm
    elif copy_mm is None:
        copy_mm = propagate(model, slices[0], tg.affines[0], prep.centre_mm, tg.organ_affines.get(slices[0]),
                            tg.fields.get(slices[0]), tg.organ_fields.get(slices[0]))
    results["copy"] = _copy_estimate(prep, model, tg, idx, copy_mm, score)
    positions = {"copy": results["copy"].info.pop("positions_mm")}
    mpm = None
    if cfg.estimator == "slice-driven" or "slice-driven" in cfg.baselines:
        mpm, positions["slice-driven"] = _slice_driven(prep, model, slices, tg, idx, targets, axes, gt_pos, cfg, recorder, progress,
                                                       pmask, geom, excl, offslice_error, on_plane, truth_d)
        results["slice-driven"] = mpm
    if tg.plane_match is not None:  # each estimate's own measure: the captured planes against it rendered on them
        unmoved = tg.plane_match(None)
        for name, pos in copies.items():  # the copies of the planes' motion, by the same measure
            m_copy = tg.plane_match(pos)
            results[name].info["plane_match"] = m_copy
            if m_copy < unmoved - 0.005:
                results[name].info["worse_than_no_motion"] = True
                warnings.warn(f"{name}: the copied motion matches the captured planes worse than no motion (mean correlation "
                              f"{m_copy:.3f} against {unmoved:.3f} unmoved)", InputWarning, stacklevel=2)
        for name, pos in positions.items():
            est = results[name]
            est.plane_match, est.plane_match_unmoved = tg.plane_match(pos), unmoved
            if not len(idx):
                est.flag = "no plane's motion passed the plane check: the estimate is no motion"
            elif est.plane_match < unmoved - 0.005:
                est.flag = (f"worse than no motion by its own measure: the captured planes match it rendered on them with mean "
                            f"correlation {est.plane_match:.3f}, the unmoved planning image {unmoved:.3f}")
            if est.flag and name == cfg.estimator:
                warnings.warn(f"estimate ({name}): {est.flag}", InputWarning, stacklevel=2)
    results["estimate"] = results[cfg.estimator]
    solver, gains, device = ({}, None, "cpu") if mpm is None else (mpm.info.pop(k) for k in ("solver", "gains", "device"))
    out = RunResult(
        case=prep.case.name, organs=model.letters, slices=[str(prep.to_input(s)) for s in slices], protocol=cfg.protocol,
        deformation=cfg.deformation, targets=cfg.targets, device=device, n_particles=model.counts(), n_driven=int(len(idx)),
        excluded_driven=bool(exclude_driven), solver=solver, gains=gains,
        gt={k: v for k, v in gt.params.items() if k not in ("A",)} | {"steps": gt.steps, "wall_s": gt.wall_s},
        results=results, registration=tg.registration, positions_mm=positions[cfg.estimator],
        drive=cfg.drive if cfg.targets != "gt" else "3d", target_in_plane_error_mm=tg.in_plane_error_mm, estimator=cfg.estimator)
    recorder.log_result(positions[cfg.estimator], mpm.steps if mpm is not None else 0, out.to_json(), format_table(out))
    return out


def _copy_estimate(prep, model, tg, idx, copy_mm, score) -> EstimateScores:
    """The ``copy`` estimator (:class:`warpmpm.estimators.copying.CopyEstimator`) on the run's observation: every particle
    where the planes' observed motion puts it (each organ a plane measured by its own motion, the others by the whole
    slice's). The positions ride in ``info["positions_mm"]`` (taken out before the JSON)."""
    from ..estimators import FrameObservation, get_estimator

    t0 = time.perf_counter()
    measured = tuple(sorted({o for d in tg.organ_affines.values() for o in d} | {o for d in tg.organ_fields.values() for o in d}))
    on = np.zeros(len(idx), dtype=bool) if not len(idx) else np.ones(len(idx), dtype=bool)
    est = get_estimator("copy")(model, prep.case, [], np.asarray(idx), None)
    res = est.estimate(FrameObservation(None, model.positions_mm.copy(), np.asarray(copy_mm, dtype=np.float64), on, measured))
    wall = time.perf_counter() - t0
    m = score(res.positions_mm)
    return EstimateScores(
        error_mm=m.error_mm, p95_mm=m.p95_mm, max_mm=m.max_mm, dice=m.dice, n=m.n, error_offslice_mm=m.error_offslice_mm,
        steps=0, wall_s=wall, converged=True, slice_converged=True, reason=res.solve["reason"], rms_residual_mm=0.0,
        rel_residual=0.0, ms_per_step=0.0, settled=True, body_motion_mm=0.0, min_det_f=float("nan"), finished_by="copy",
        organs=m.organs, info={"positions_mm": res.positions_mm, "measured_organs": list(measured)})


def _slice_driven(prep, model, slices, tg, idx, targets, axes, gt_pos, cfg, recorder, progress, pmask, geom, excl,
                  offslice_error, on_plane, truth_d):
    """The seed's slice-driven MPM (:class:`warpmpm.driving.SliceDrivenEstimator`) driven at the planes' particles to
    the run's targets: its scores (the solver's summary, gains and device in ``info``) and its positions."""
    def on_step(estimator, step, rel, rms):
        recorder.on_step(estimator, step, rel, rms)
        progress.step("slice-driven", step, rms, cfg.max_steps)

    if cfg.materials is not None:  # the estimate's materials; the truth keeps its own
        from ..materials import material_table

        model = replace(model, materials={**model.materials, **material_table(cfg.materials).organ_materials(model.organs)})
    est = SliceDrivenEstimator(model, slices, driven=idx, solver_config=replace(cfg.solver, device=cfg.device),
                               convergence=ConvergenceConfig(max_steps=cfg.max_steps, wait_settled=cfg.wait_settled),
                               extra_points_mm=np.vstack([targets, gt_pos]), callback=on_step)
    progress.say(f"slice-driven: {len(idx):,} particles driven on {', '.join(str(prep.to_input(s)) for s in slices)}, "
                 f"cell {est.mpm.dx_mm:.2f} mm, grid {'x'.join(map(str, est.mpm.grid_shape))}")
    if len(idx):
        res = est.estimate(targets, axes=axes)
    else:  # the plane check dropped every plane's motion: nothing is driven, the estimate is no motion
        res = DriveResult(model.positions_mm.copy(), 0, 0.0, np.zeros(0), np.zeros(0), True,
                          "nothing driven (no plane passed the plane check)", settled=True, body_motion_mm=0.0, min_det_f=1.0)
    progress.done(f"slice-driven: {res.steps} steps in {res.wall_s:.1f} s ({res.reason})")
    if res.converged and not res.settled:  # the driven slice stopped; the body had not: not an equilibrium
        warnings.warn(f"slice-driven: the driven particles met the stopping rule ({res.reason}) but the model was still moving "
                      f"({res.body_motion_mm:.2f} mm at the 99th percentile): reported not converged (--wait-settled runs on "
                      "until it settles)", InputWarning, stacklevel=3)
    m = evaluate(res.positions_mm[pmask], gt_pos[pmask], geom, excl[pmask], model.sampling_step)
    scores = EstimateScores(
        **{k: m[k] for k in ("error_mm", "p95_mm", "max_mm", "dice", "n")}, error_offslice_mm=offslice_error(res.positions_mm),
        steps=res.steps, wall_s=res.wall_s, converged=bool(res.converged and res.settled), slice_converged=bool(res.converged),
        reason=res.reason,
        rms_residual_mm=res.final_rms_mm, rel_residual=res.final_rel_residual, ms_per_step=1e3 * res.wall_s / max(res.steps, 1),
        settled=res.settled, body_motion_mm=res.body_motion_mm, min_det_f=res.min_det_f,
        linear_iterations=res.linear_iterations, finished_by=res.method,
        organs=organ_scores(model, res.positions_mm, gt_pos, on_plane, truth_distances=truth_d))
    from ..materials import material_table

    scores.info = {"solver": est.mpm.summary(), "gains": res.gains.to_json() if res.gains else None, "device": str(est.mpm.device),
                   "materials": material_table(cfg.materials or "paper").name}
    return scores, res.positions_mm


def check_device(device: str | None) -> None:
    """:class:`InputError` when CUDA is asked for and none is available."""
    if device and str(device).startswith("cuda"):
        import warp as wp

        wp.init()
        if not wp.is_cuda_available():
            raise InputError(f"--device {device} asked for, but no CUDA device is available; use --device cpu")
        if ":" in str(device):
            n = int(str(device).split(":")[1])
            if n >= wp.get_cuda_device_count():
                raise InputError(f"--device {device}: there are {wp.get_cuda_device_count()} CUDA device(s), numbered from 0")


class Progress:
    """Where a run says how far it has got: stage lines to ``write`` (None: silent), and a live step line
    when ``live`` (a terminal). Not live (a log), a long stage still says where it is: once its pace is known (after
    :attr:`FIRST_LINE_S` s), a line with the time per step and the most the stage can still take at its step cap, then
    one every :attr:`EVERY_S` s."""

    FIRST_LINE_S = 10.0
    EVERY_S = 60.0

    def __init__(self, write, live: bool = False, every: int = 50):
        self.write, self.live, self.every = write, live, every
        self._t0, self._last, self._what = None, None, None

    def say(self, text: str) -> None:
        if self.write is not None:
            self.write(text)

    def step(self, what: str, step: int, rms_mm: float, cap: int | None = None) -> None:
        if self.write is None:
            return
        if self.live:
            if step % self.every == 0:
                self.write(f"\r{what}: step {step}, driven RMS residual {rms_mm:.3f} mm", end="")
            return
        now = time.perf_counter()
        if self._what != what:
            self._what, self._t0, self._last = what, now, None
            return
        wait = self.FIRST_LINE_S if self._last is None else self.EVERY_S
        if now - (self._last or self._t0) >= wait and step > 0:
            pace = (now - self._t0) / step
            left = f"; at most {cap - step:,} steps more, up to {pace * (cap - step):.0f} s" if cap else ""
            self.write(f"{what}: step {step:,}, {pace * 1e3:.0f} ms a step, driven RMS residual {rms_mm:.3f} mm{left}")
            self._last = now

    def done(self, text: str) -> None:
        if self.write is not None:
            self.say(("\r" if self.live else "") + text)


def size_report(prep: PreparedCase, cfg: CaseConfig) -> str:
    """The model's size, its grid and the memory the largest simulation of the run needs (the GT's finer grid)."""
    from ..groundtruth import gt_solver_config
    from ..solvers import cpu_threads, default_device, grid_layout, memory_estimate_bytes

    m = prep.full_model
    dx, _, shape = grid_layout(m, replace(cfg.solver, device=cfg.device))
    gdx, _, gshape = grid_layout(m, gt_solver_config(cfg.solver, cfg.device))
    threads = cpu_threads(cfg.solver, cfg.device or default_device())  # each thread of a split CPU step has its own grid copy
    mem = max(memory_estimate_bytes(m.n, shape, threads), memory_estimate_bytes(m.n, gshape, threads))
    lattice = f", isotropic {m.lattice.spacing_mm[0]:.2f} mm lattice (thick slices)" if m.lattice is not None else ""
    return (f"model: {m.n:,} particles ({', '.join(f'{o} {c:,}' for o, c in m.counts().items())}){lattice}; estimate grid "
            f"{'x'.join(map(str, shape))} of {dx:.2f} mm, ground truth {'x'.join(map(str, gshape))} of {gdx:.2f} mm; "
            f"~{mem / 1e6:.0f} MB" + (f"; {threads} CPU threads a step" if threads > 1 else ""))


def run_case(cfg: CaseConfig, recorder: Recorder | None = None, progress: Progress | None = None) -> RunResult:
    """Run one whole case: prepare it, check the slices, simulate the GT, then :func:`run_prepared`.

    Every input is checked before the (costly) GT simulation. The recorder, when given, is closed here
    (``ok=False`` when the run fails or is interrupted, so a file recorder leaves nothing behind).
    """
    recorder = recorder or NullRecorder()
    progress = progress or Progress(None)
    ok = False
    try:
        if cfg.is_auto:
            raise InputError("--slices auto must be resolved first (warpmpm.experiment.auto.auto_condition)")
        check_device(cfg.device)
        t0 = time.perf_counter()
        prep = prepare_case(cfg)
        if cfg.slices not in (None, ""):
            # every slice must be inside the volume and hold particles: fail before the (costly) GT
            model = prep.model(cfg.organs)
            driven_indices(model, prep.resolve_slices(model, cfg.slices))
        progress.say(size_report(prep, cfg))
        progress.say(f"ground truth: reading the field {cfg.truth_field}..." if cfg.protocol == "field" else
                     f"ground truth ({cfg.protocol}, deformation {cfg.deformation}): simulating...")
        gt = make_ground_truth(prep, cfg, callback=lambda est, step, rel, rms: progress.step("ground truth", step, rms))
        moving = float(gt.params.get("gt_body_motion_mm", float("nan")))
        unsettled = not gt.params.get("gt_settled", True) and math.isfinite(moving)
        progress.done((f"ground truth: the field read and the planning image warped by it in {gt.wall_s:.1f} s"
                       if cfg.protocol == "field" else f"ground truth: {gt.steps} steps in {gt.wall_s:.1f} s") + (
            f" (its body still moved {moving:.2f} mm per 100 steps when it stopped: a transient, not an equilibrium)" if unsettled else ""))
        out = run_prepared(prep, gt, cfg, recorder, progress)
        out.total_wall_s = time.perf_counter() - t0
        ok = True
        return out
    finally:
        recorder.close(ok=ok)
