"""The experiment runner: one case end to end (:func:`run_case`), sweeps over cases x deformations x
organ combinations x driving slices (:func:`sweep`), the paper-form summary, and the CLI.

A case run: read (or generate) the planning case, crop it to its organs, build the particle model,
make the pseudo ground truth, compute the driving targets, run the slice-driven estimate, and
evaluate it beside the baselines ``initial`` (no motion), ``propagate`` (the driving slice's
in-plane affine applied to every particle) and ``volume_registration`` (3D affine registration of
the planning volume to the GT volume).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace

import numpy as np

from .driving import (ConvergenceConfig, DrivingSlice, SliceDrivenEstimator, affine_targets, apply_in_plane_affine,
                      driven_indices, in_plane_axes, parse_slices)
from .groundtruth import GroundTruth, contact_ground_truth, fit_in_plane_affine, paper_affine, paper_ground_truth
from .images import ORGANS, Case, InputError, crop_to_organs, load_case, parse_organs
from .metrics import evaluate
from .model import ParticleModel, build_model, orientation_image_axis
from .phantom import make_phantom
from .solver import SimulationError, SolverConfig

COMBINATIONS = ("p", "ps", "pd", "pl", "psd", "psl", "pdl", "psdl")


@dataclass(frozen=True)
class CaseConfig:
    """Everything that defines one run (the options of ``examples/run_case.py``).

    Slice indices are voxel indices of the input volume (before the crop this runner does).
    """

    image: str | None = None
    labels: str | None = None
    preset: str = "amos"
    phantom_seed: int = 0
    phantom_resolution: float = 1.0
    organs: str = "psdl"
    slices: str | None = None
    protocol: str = "paper"
    deformation: int = 1
    targets: str = "affine"
    device: str | None = None
    particle_step: int = 1
    perturb: bool = True
    literal: bool = False
    max_steps: int = 6000
    baselines: tuple[str, ...] = ("initial", "propagate", "volume_registration")
    exclude_driven: bool | None = None
    rrd_every: int = 20
    solver: SolverConfig = field(default_factory=SolverConfig)


@dataclass
class PreparedCase:
    """A case cropped to its organs with its full (all-organ) particle model."""

    case: Case
    offset: tuple[int, int, int]
    input_centre_mm: np.ndarray
    full_model: ParticleModel
    input_size: tuple[int, int, int] = (0, 0, 0)


def prepare_case(cfg: CaseConfig) -> PreparedCase:
    if cfg.labels is None and cfg.image is not None:
        raise InputError("--image needs --labels (the label map defines the organs)")
    if cfg.labels is None:
        case = make_phantom(seed=cfg.phantom_seed, resolution=cfg.phantom_resolution, preset=cfg.preset)
    else:
        case = load_case(cfg.labels, cfg.image, cfg.preset)
    organs = parse_organs(cfg.organs)
    case.check_organs(organs)
    # The GT scene holds every organ of the method present in the label map.
    present = tuple(o for o in ORGANS if o in case.label_map and np.any(case.labels == case.label_map[o]))
    input_centre = case.geometry.center_mm()
    cropped, offset = crop_to_organs(case, present, margin_mm=15.0)
    full = build_model(cropped, present, sampling_step=cfg.particle_step)
    return PreparedCase(cropped, offset, input_centre, full, case.geometry.size)


def resolve_slices(prep: PreparedCase, model: ParticleModel, text: str | None) -> list[DrivingSlice]:
    """Driving slices in the cropped volume from input-volume indices (default: mid-pancreas axial)."""
    if text is None or text == "":
        axis = orientation_image_axis(model.geometry, "axial")
        ks = model.voxel_ijk[model.organ_slice("pancreas"), axis]
        return [DrivingSlice("axial", int(np.median(ks)))]
    out = []
    for s in parse_slices(text):
        axis = orientation_image_axis(model.geometry, s.orientation)
        size_in = prep.case.geometry.size[axis]  # cropped size
        local = s.index - prep.offset[axis]
        if not (0 <= s.index < prep.input_size[axis]):
            raise InputError(f"{s.orientation} slice {s.index} is outside the volume (valid 0..{prep.input_size[axis] - 1})")
        if not (0 <= local < size_in):
            raise InputError(f"{s.orientation} slice {s.index} holds none of the organs in use "
                             f"(they span input indices {prep.offset[axis]}..{prep.offset[axis] + size_in - 1})")
        out.append(DrivingSlice(s.orientation, int(local)))
    return out


def make_ground_truth(prep: PreparedCase, cfg: CaseConfig) -> GroundTruth:
    if cfg.protocol == "paper":
        return paper_ground_truth(prep.full_model, cfg.deformation, literal=cfg.literal, perturb=cfg.perturb,
                                  seed=cfg.phantom_seed, centre_mm=prep.input_centre_mm, solver_config=cfg.solver, device=cfg.device)
    if cfg.protocol == "contact":
        return contact_ground_truth(prep.full_model, seed=cfg.phantom_seed + 31 * cfg.deformation, perturb=cfg.perturb,
                                    solver_config=cfg.solver, device=cfg.device)
    raise InputError(f"unknown protocol {cfg.protocol!r}; use paper or contact")


def slice_affines(prep: PreparedCase, model: ParticleModel, gt_pos: np.ndarray, slices: list[DrivingSlice], cfg: CaseConfig):
    """The in-plane affine (A, t) of every driving slice: the paper's known A for axial slices under the
    paper protocol, else the least-squares fit of the slice particles' GT motion."""
    out = []
    for s in slices:
        if cfg.protocol == "paper" and s.orientation == "axial":
            out.append((paper_affine(cfg.deformation, cfg.literal), np.zeros(2)))
        else:
            idx = driven_indices(model, [s])
            e_u, e_v = in_plane_axes(model, s.orientation)
            out.append(fit_in_plane_affine(model.positions_mm[idx], gt_pos[idx], e_u, e_v, prep.input_centre_mm))
    return out


def _gt_for_model(gt: GroundTruth, model: ParticleModel) -> np.ndarray:
    """GT positions of ``model``'s particles (a sub-combination of the GT model, same order)."""
    keep = np.isin(gt.model.organ_index, [gt.model.organs.index(o) for o in model.organs])
    return gt.positions_mm[keep]


def volume_registration_baseline(prep: PreparedCase, gt: GroundTruth, model: ParticleModel) -> tuple[np.ndarray, dict]:
    from .registration import planning_and_gt_volumes, register_volumes_affine

    case = prep.case
    values = {o: case.label_map[o] for o in gt.model.organs}
    planning, target = planning_and_gt_volumes(case, gt)
    # As the paper's elastix comparison: both volumes masked to the organs in use (planning contour
    # on the planning image, GT contour on the GT image), the metric over the dilated GT region.
    use = [values[o] for o in model.organs]
    gt_mask = np.isin(gt.label_map(values), use)
    planning = np.where(np.isin(case.labels, use), planning, 0.0)
    target = np.where(gt_mask, target, 0.0)
    import SimpleITK as sitk
    m_img = case.geometry.apply_to(sitk.GetImageFromArray(gt_mask.astype(np.uint8)))
    mask = sitk.GetArrayFromImage(sitk.BinaryDilate(m_img, [3, 3, 1])).astype(bool)
    reg = register_volumes_affine(planning, target, case.geometry, mask=mask)
    return reg.apply(model.positions_mm), {"wall_s": reg.wall_s, "fallback_to_identity": reg.fallback}


def run_prepared(prep: PreparedCase, gt: GroundTruth, cfg: CaseConfig, rrd=None) -> dict:
    """The estimate and baselines of one (organs, slices, targets) on a prepared case and its GT."""
    organs = parse_organs(cfg.organs)
    model = prep.full_model.subset(organs)
    gt_pos = _gt_for_model(gt, model)
    slices = resolve_slices(prep, model, cfg.slices)
    idx = driven_indices(model, slices)
    affines = slice_affines(prep, model, gt_pos, slices, cfg)
    reg_info = None
    if cfg.targets == "affine":
        idx, targets = affine_targets(model, model.positions_mm, slices, affines, prep.input_centre_mm)
    elif cfg.targets == "gt":
        targets = gt_pos[idx]
    elif cfg.targets == "registration":
        from .registration import registration_targets

        idx, targets, reg_info = registration_targets(prep, gt, model, slices)
    else:
        raise InputError(f"unknown targets {cfg.targets!r}; use affine, gt or registration")
    pmask = model.organ_slice("pancreas")
    exclude_driven = cfg.exclude_driven if cfg.exclude_driven is not None else len(slices) > 1
    excl = np.zeros(model.n, dtype=bool)
    if exclude_driven:
        excl[idx] = True
    geom = prep.case.geometry

    def score(pos):
        return evaluate(pos[pmask], gt_pos[pmask], geom, excl[pmask], model.sampling_step)

    results: dict[str, dict] = {}
    if "initial" in cfg.baselines:
        results["initial"] = score(model.positions_mm)
    if "propagate" in cfg.baselines:
        e_u, e_v = in_plane_axes(model, slices[0].orientation)
        A, t = affines[0] if reg_info is None else (reg_info["slices"][0]["A"], reg_info["slices"][0]["t_mm"])
        results["propagate"] = score(apply_in_plane_affine(model.positions_mm, e_u, e_v, np.asarray(A), np.asarray(t), prep.input_centre_mm))
    if "volume_registration" in cfg.baselines:
        pos, info = volume_registration_baseline(prep, gt, model)
        results["volume_registration"] = score(pos) | info
    logger = None
    if rrd is not None:
        from viewer.recording import RunLogger

        logger = RunLogger(rrd, model, gt_pos=gt_pos, every=cfg.rrd_every)
        logger.log_planning()
        logger.log_slices(slices, idx, targets, prep)
    est = SliceDrivenEstimator(model, slices, driven=idx, solver_config=replace(cfg.solver, device=cfg.device),
                               convergence=ConvergenceConfig(max_steps=cfg.max_steps), extra_points_mm=np.vstack([targets, gt_pos]),
                               callback=None if logger is None else logger.step_callback)
    res = est.estimate(targets)
    results["estimate"] = score(res.positions_mm) | {
        "steps": res.steps, "wall_s": res.wall_s, "converged": res.converged, "reason": res.reason,
        "rms_residual_mm": res.final_rms_mm, "rel_residual": res.final_rel_residual,
        "ms_per_step": 1e3 * res.wall_s / max(res.steps, 1),
    }
    if reg_info is not None:
        results["registration"] = {k: v for k, v in reg_info.items() if k != "slices"}
    out = {
        "case": prep.case.name,
        "organs": model.letters,
        "slices": [f"{s.orientation}:{s.index + prep.offset[orientation_image_axis(model.geometry, s.orientation)]}" for s in slices],
        "protocol": cfg.protocol,
        "deformation": cfg.deformation,
        "targets": cfg.targets,
        "device": str(est.mpm.device),
        "n_particles": model.counts(),
        "n_driven": int(len(idx)),
        "excluded_driven": bool(exclude_driven),
        "solver": est.mpm.summary(),
        "gains": res.gains,
        "gt": {k: v for k, v in gt.params.items() if k not in ("A",)} | {"steps": gt.steps, "wall_s": gt.wall_s},
        "results": results,
    }
    if logger is not None:
        logger.log_result(res, out)
        logger.close()
    out["_positions"] = res.positions_mm
    return out


def run_case(cfg: CaseConfig, rrd: str | None = None) -> dict:
    """Run one whole case (see module docstring); returns the JSON-able result dict."""
    if cfg.device not in (None, "cpu") and not str(cfg.device).startswith("cuda"):
        raise InputError(f"unknown device {cfg.device!r}; use cpu or cuda")
    if cfg.device and str(cfg.device).startswith("cuda"):
        import warp as wp

        wp.init()
        if not wp.is_cuda_available():
            raise InputError("--device cuda asked for, but no CUDA device is available")
    t0 = time.perf_counter()
    prep = prepare_case(cfg)
    if cfg.slices not in (None, "", "auto"):
        # every slice must be inside the volume and hold particles: fail before the (costly) GT
        model = prep.full_model.subset(parse_organs(cfg.organs))
        driven_indices(model, resolve_slices(prep, model, cfg.slices))
    if cfg.targets not in ("affine", "gt", "registration"):
        raise InputError(f"unknown targets {cfg.targets!r}; use affine, gt or registration")
    if cfg.protocol == "paper" and cfg.deformation not in range(1, 9):
        raise InputError(f"deformation must be 1..8, got {cfg.deformation}")
    gt = make_ground_truth(prep, cfg)
    out = run_prepared(prep, gt, cfg, rrd)
    out["total_wall_s"] = time.perf_counter() - t0
    return out


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------

def format_table(out: dict) -> str:
    """The run's table: each baseline and the estimate with error, p95, Dice (and steps, time)."""
    rows = ["| method | error mm | p95 mm | Dice | steps | wall s |", "|---|---|---|---|---|---|"]
    for name in ("initial", "propagate", "volume_registration", "estimate"):
        r = out["results"].get(name)
        if r is None:
            continue
        steps = str(r.get("steps", ""))
        wall = f"{r['wall_s']:.2f}" if "wall_s" in r else ""
        rows.append(f"| {name} | {r['error_mm']:.2f} | {r['p95_mm']:.2f} | {r['dice']:.3f} | {steps} | {wall} |")
    head = (f"case {out['case']}, organs {out['organs']}, slices {','.join(out['slices'])}, protocol {out['protocol']}"
            f" (deformation {out['deformation']}), targets {out['targets']}, device {out['device']}, "
            f"particles {sum(out['n_particles'].values())} ({out['n_particles']}), driven {out['n_driven']}")
    est = out["results"]["estimate"]
    tail = (f"estimate: {'converged' if est['converged'] else 'NOT converged'} ({est['reason']}) in {est['steps']} steps, "
            f"{est['ms_per_step']:.2f} ms/step, RMS residual {est['rms_residual_mm']:.3f} mm")
    if "registration" in out["results"]:
        r = out["results"]["registration"]
        tail += f"\nregistration: in-plane error of the slice's pancreas particles {r['error_mm']:.2f} mm, {r['wall_s'] * 1e3:.1f} ms per slice"
    return head + "\n" + "\n".join(rows) + "\n" + tail


def write_json_atomic(path: str, data: dict) -> None:
    """Write JSON through a temporary file and a rename: never a half-written file."""
    path = os.path.abspath(path)
    d = os.path.dirname(path)
    if not os.path.isdir(d):
        raise InputError(f"output folder {d} does not exist")
    clean = {k: v for k, v in data.items() if not k.startswith("_")}
    fd, tmp = tempfile.mkstemp(dir=d, suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(clean, f, indent=2, default=_json_default)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


# --------------------------------------------------------------------------------------------
# Sweep
# --------------------------------------------------------------------------------------------

SWEEP_FIELDS = ["case", "protocol", "deformation", "organs", "orientation", "slice", "targets", "excluded_driven", "n_driven", "n_pancreas",
                "error_mm", "p95_mm", "dice", "steps", "wall_s", "converged",
                "initial_error_mm", "initial_dice", "propagate_error_mm", "propagate_dice",
                "count_pancreas", "count_stomach", "count_duodenum", "count_left_kidney", "failure"]


def _row_key(r) -> tuple:
    return (str(r["case"]), str(r["protocol"]), str(r["deformation"]), str(r["organs"]), str(r["orientation"]), str(r["slice"]))


def sweep_task(case: dict, deformation: int, combinations, orientations, protocol: str, slice_stride: int, base: CaseConfig,
               done: frozenset = frozenset()) -> list[dict]:
    """All rows of one (case, deformation): every combination x orientation x pancreas slice not in ``done``.

    A plain function of picklable arguments, so it runs inline, in a process pool or on a Dask worker.
    """
    name = case.get("name", "case")
    cfg0 = replace(base, **{k: v for k, v in case.items() if k != "name"}, protocol=protocol, deformation=int(deformation),
                   baselines=("initial", "propagate"))
    prep = prepare_case(cfg0)
    gt = None
    rows = []
    for combo in combinations:
        organs = parse_organs(combo)
        if not set(organs) <= set(prep.full_model.organs):
            continue
        model = prep.full_model.subset(organs)
        for orientation in orientations:
            axis = orientation_image_axis(model.geometry, orientation)
            counts = prep.full_model.slice_counts(orientation)
            ks = np.unique(model.voxel_ijk[model.organ_slice("pancreas"), axis])[::slice_stride]
            for k in ks:
                k_in = int(k) + prep.offset[axis]
                key = (name, protocol, str(deformation), combo, orientation, str(k_in))
                if key in done:
                    continue
                if gt is None:
                    gt = make_ground_truth(prep, cfg0)
                on = {o: int(counts[k, i]) for i, o in enumerate(prep.full_model.organs)}
                row = {"case": name, "protocol": protocol, "deformation": int(deformation), "organs": combo,
                       "orientation": orientation, "slice": k_in, "targets": cfg0.targets,
                       **{f"count_{o}": (on.get(o, 0) if o in organs else 0) for o in ORGANS}}
                try:
                    out = run_prepared(prep, gt, replace(cfg0, organs=combo, slices=f"{orientation}:{k_in}"))
                except SimulationError as exc:  # keep the row (so a re-run does not retry it) and go on
                    rows.append(row | {"error_mm": float("nan"), "dice": float("nan"), "converged": False, "failure": str(exc)})
                    continue
                r = out["results"]
                rows.append(row | {"excluded_driven": out["excluded_driven"], "n_driven": out["n_driven"],
                             "n_pancreas": out["n_particles"]["pancreas"], "error_mm": r["estimate"]["error_mm"],
                             "p95_mm": r["estimate"]["p95_mm"], "dice": r["estimate"]["dice"], "steps": r["estimate"]["steps"],
                             "wall_s": r["estimate"]["wall_s"], "converged": r["estimate"]["converged"],
                             "initial_error_mm": r["initial"]["error_mm"], "initial_dice": r["initial"]["dice"],
                             "propagate_error_mm": r["propagate"]["error_mm"], "propagate_dice": r["propagate"]["dice"]})
    return rows


def add_sweep_arguments(p: argparse.ArgumentParser, phantom_resolution: float) -> None:
    """The case and task options shared by ``examples/sweep.py`` and ``examples/multi_direction.py``."""
    p.add_argument("--labels", help="label map of one real case (default: phantoms)")
    p.add_argument("--image")
    p.add_argument("--preset", default="amos")
    p.add_argument("--phantom-seeds", default="0", help="comma-separated phantom seeds when no --labels")
    p.add_argument("--phantom-resolution", type=float, default=phantom_resolution)
    p.add_argument("--particle-step", type=int, default=1)
    p.add_argument("--deformations", default="1,2,3,4,5,6,7,8")
    p.add_argument("--protocol", default="paper", choices=["paper", "contact"])
    p.add_argument("--device", default=None)
    p.add_argument("--workers", type=int, default=1, help="parallel tasks (one per case x deformation)")
    p.add_argument("--scheduler", default=None, help="'local' for a Dask LocalCluster of --workers, or a Dask scheduler address")


def sweep_cases(labels: str | None, image: str | None, preset: str, phantom_seeds: str, phantom_resolution: float) -> list[dict]:
    """The case dicts of :func:`sweep` from command-line values: one labelled case (named for its
    folder) or a phantom per comma-separated seed (``phantom<seed>``)."""
    if labels:
        return [{"name": os.path.basename(os.path.dirname(os.path.abspath(labels))), "labels": labels, "image": image, "preset": preset}]
    try:
        seeds = [int(s) for s in phantom_seeds.split(",")]
    except ValueError:
        raise InputError(f"--phantom-seeds must be comma-separated integers, got {phantom_seeds!r}") from None
    return [{"name": f"phantom{s}", "phantom_seed": s, "phantom_resolution": phantom_resolution} for s in seeds]


def run_tasks(fn, args: list[tuple], on_result, *, workers: int = 1, scheduler: str | None = None) -> list[tuple]:
    """Call ``fn(*a)`` for every ``a`` in ``args`` and hand each result to ``on_result`` as it finishes.

    ``scheduler=None``: here (``workers <= 1``) or in a local process pool of ``workers`` (spawned,
    so each process initialises Warp itself); ``"local"``: a Dask ``LocalCluster`` of ``workers``
    single-threaded processes; any other value: the address of a running Dask scheduler. A task that
    raises does not stop the others: it is reported on stderr and returned as ``(args, message)``.
    """
    failed: list[tuple] = []

    def fail(a, exc):
        msg = f"{type(exc).__name__}: {exc}"
        print(f"task {a[:2]} failed: {msg}", file=sys.stderr)
        failed.append((a, msg))

    if scheduler is None and workers <= 1:
        for a in args:
            try:
                result = fn(*a)
            except (SimulationError, InputError) as exc:
                fail(a, exc)
                continue
            on_result(result)
    elif scheduler is None:
        import concurrent.futures as cf
        import multiprocessing as mp

        with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as ex:
            futures = {ex.submit(fn, *a): a for a in args}
            for fut in cf.as_completed(futures):
                try:
                    result = fut.result()
                except Exception as exc:  # noqa: BLE001 - a worker's error must not lose the other tasks' rows
                    fail(futures[fut], exc)
                    continue
                on_result(result)
    else:
        from distributed import Client, LocalCluster, as_completed

        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) if scheduler == "local" else None
        client = Client(cluster if cluster is not None else scheduler)
        try:
            futures = {client.submit(fn, *a, pure=False): a for a in args}
            for fut in as_completed(list(futures)):
                try:
                    result = fut.result()
                except Exception as exc:  # noqa: BLE001
                    fail(futures[fut], exc)
                    continue
                on_result(result)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    return failed


def _report_failures(failed: list[tuple], n_tasks: int) -> None:
    """One stderr line naming the (case, deformation) tasks that failed and why."""
    if failed:
        print(f"{len(failed)} of {n_tasks} tasks failed (re-run to retry them): "
              + "; ".join(f"{a[0].get('name', 'case')} def{a[1]}: {m}" for a, m in failed), file=sys.stderr)


def _read_rows(path: str) -> list[dict]:
    if not os.path.exists(path):
        return []
    with open(path) as f:
        return list(csv.DictReader(f))


class _CsvAppender:
    """Append rows to a CSV as tasks finish (flushed per task), in the file's own column order when it exists."""

    def __init__(self, path: str, fields: list[str]):
        self.path, self.fields = path, fields

    def __enter__(self):
        new_file = not os.path.exists(self.path)
        if not new_file:  # a CSV from an older version keeps its header
            with open(self.path) as f:
                self.fields = next(csv.reader(f), None) or self.fields
        self.f = open(self.path, "a", newline="")
        self.w = csv.DictWriter(self.f, fieldnames=self.fields, extrasaction="ignore")
        if new_file:
            self.w.writeheader()
        return self

    def write(self, rows: list[dict]) -> None:
        for row in rows:
            self.w.writerow(row)
        self.f.flush()

    def __exit__(self, *exc):
        self.f.close()


def sweep(cases: list[dict], deformations, combinations, orientations=("axial",), out_csv: str = "sweep.csv", *,
          protocol: str = "paper", slice_stride: int = 1, base: CaseConfig | None = None, scheduler: str | None = None,
          workers: int = 1, progress=print) -> list[dict]:
    """Brute-force sweep; one CSV row per simulation, resumable (finished rows are skipped).

    ``cases``: dicts of :class:`CaseConfig` fields naming a case (``{"phantom_seed": 3}`` or
    ``{"labels": ..., "image": ..., "preset": ...}``) with a ``name``. Work is split into one task per
    (case, deformation). ``scheduler=None`` runs them here (``workers > 1``: a local process pool);
    ``"local"`` starts a Dask ``LocalCluster`` of ``workers`` processes; any other value is a Dask
    scheduler address (``tcp://host:8786``). Rows are written here as tasks finish.
    """
    base = base or CaseConfig()
    rows = _read_rows(out_csv)
    done = frozenset(_row_key(r) for r in rows)
    args = [(c, int(d), tuple(combinations), tuple(orientations), protocol, slice_stride, base, done) for c in cases for d in deformations]
    with _CsvAppender(out_csv, SWEEP_FIELDS) as out:

        def keep(task_rows):
            out.write(task_rows)
            for row in task_rows:
                rows.append({k: str(v) for k, v in row.items()})
                if progress:
                    progress(f"{row['case']} def{row['deformation']} {row['organs']} {row['orientation']}:{row['slice']} "
                             f"error {row['error_mm']:.2f} mm")

        _report_failures(run_tasks(sweep_task, args, keep, workers=workers, scheduler=scheduler), len(args))
    return rows


def summarize(rows: list[dict]) -> str:
    """Paper-form summary: best slice per (case, deformation, combination), then mean +- sd per combination."""
    best: dict[tuple, dict] = {}
    for r in rows:
        key = (r["case"], r["deformation"], r["organs"])
        if key not in best or float(r["error_mm"]) < float(best[key]["error_mm"]):
            best[key] = r
    lines = ["| condition | error mm | Dice | n |", "|---|---|---|---|"]
    by_combo: dict[str, list] = {}
    for (case, d, combo), r in best.items():
        by_combo.setdefault(combo, []).append(r)
    any_rows = list(best.values())
    if any_rows:
        ie = np.array([float(r["initial_error_mm"]) for r in any_rows])
        idc = np.array([float(r["initial_dice"]) for r in any_rows])
        lines.append(f"| initial (no estimation) | {ie.mean():.2f} +- {ie.std():.2f} | {idc.mean():.3f} | {len(ie)} |")
    for combo in COMBINATIONS:
        if combo not in by_combo:
            continue
        rs = by_combo[combo]
        e = np.array([float(r["error_mm"]) for r in rs])
        dc = np.array([float(r["dice"]) for r in rs])
        pe = np.array([float(r["propagate_error_mm"]) for r in rs])
        lines.append(f"| {combo}, best slice | {e.mean():.2f} +- {e.std():.2f} | {dc.mean():.3f} +- {dc.std():.3f} | {len(e)} |")
        lines.append(f"| {combo}, propagate (same slice) | {pe.mean():.2f} +- {pe.std():.2f} | | {len(pe)} |")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Multi-direction protocol (axial + sagittal and/or coronal slices)
# --------------------------------------------------------------------------------------------

MULTI_CONDITIONS = ("a", "ac", "as", "asc")
MULTI_FIELDS = ["case", "protocol", "deformation", "condition", "pick", "slices", "n_driven", "n_excluded_pancreas",
                "error_mm", "dice", "initial_error_mm", "initial_dice", "volume_registration_error_mm", "volume_registration_dice",
                "steps", "wall_s", "converged"]

#: The paper's multi-direction table (20 MR cases x 8 deformations, psdl, GT targets, driven particles excluded).
PAPER_MULTI = {"a": (4.26, 1.16, 0.610), "ac": (3.12, 0.989, 0.636), "as": (2.42, 0.584, 0.650), "asc": (2.13, 0.598, 0.662)}


def multi_direction_task(case: dict, deformation: int, axial_model_path: str, plane_model_path: str, base: CaseConfig,
                         top: int = 3) -> list[dict]:
    """The paper's multi-direction validation for one (case, deformation), organs psdl, GT targets.

    The axial slice is the psdl slice the axial selection model ranks best; the sagittal and coronal
    candidates are the ``top`` slices the plane model (Dice rank from particle counts) ranks best.
    Conditions: ``a`` (axial only), ``ac`` and ``as`` (axial + each of the ``top`` candidates), ``asc``
    (axial + every sagittal x coronal pair of candidates). Particles on any driving slice are excluded
    from the metrics, as in the paper; the baselines (no motion, 3D affine registration of the planning
    volume to the GT volume) are scored with the same exclusion. Each condition gives two rows: ``pick=top1`` (the first-ranked
    candidates, what a user would get without a ground truth) and ``pick=best_of_{top}`` (the best
    run among the candidates judged against the GT: the paper's rule).
    """
    from .selection import SelectionModel

    axial_model = SelectionModel.load(axial_model_path)
    plane_model = SelectionModel.load(plane_model_path)
    name = case.get("name", "case")
    cfg0 = replace(base, **{k: v for k, v in case.items() if k != "name"}, deformation=int(deformation), organs="psdl",
                   targets="gt", exclude_driven=True, baselines=("initial",))
    prep = prepare_case(cfg0)
    full = prep.full_model
    geom = full.geometry

    def label(orientation, k):
        return f"{orientation}:{k + prep.offset[orientation_image_axis(geom, orientation)]}"

    ranked_axial, _ = axial_model.rank(full, ("axial",), combinations=("psdl",), k=1)
    ax = label(*ranked_axial[0][0][:2])
    cand = {o: [label(*key[:2]) for key, _ in plane_model.rank(full, (o,), combinations=("psdl",), k=top)[0]]
            for o in ("sagittal", "coronal")}
    runs = {"a": [[ax]],
            "ac": [[ax, c] for c in cand["coronal"]],
            "as": [[ax, s] for s in cand["sagittal"]],
            "asc": [[ax, s, c] for s in cand["sagittal"] for c in cand["coronal"]]}
    gt = make_ground_truth(prep, cfg0)
    model = full.subset(parse_organs("psdl"))
    pancreas = model.organ_slice("pancreas")
    gt_pos = _gt_for_model(gt, model)
    vr_pos, _ = volume_registration_baseline(prep, gt, model)  # the 3D affine baseline, scored per condition below
    rows = []
    for cond in MULTI_CONDITIONS:
        outs = []
        for slices in runs[cond]:
            out = run_prepared(prep, gt, replace(cfg0, slices=",".join(slices)))
            r = out["results"]
            idx = driven_indices(model, resolve_slices(prep, model, ",".join(slices)))
            n_excl = int(np.sum(pancreas[idx]))
            excl = np.zeros(model.n, dtype=bool)
            excl[idx] = True
            vr = evaluate(vr_pos[pancreas], gt_pos[pancreas], prep.case.geometry, excl[pancreas], model.sampling_step)
            outs.append({"case": name, "protocol": cfg0.protocol, "deformation": int(deformation), "condition": cond,
                         "slices": ",".join(out["slices"]), "n_driven": out["n_driven"], "n_excluded_pancreas": n_excl,
                         "error_mm": r["estimate"]["error_mm"], "dice": r["estimate"]["dice"],
                         "initial_error_mm": r["initial"]["error_mm"], "initial_dice": r["initial"]["dice"],
                         "volume_registration_error_mm": vr["error_mm"], "volume_registration_dice": vr["dice"],
                         "steps": r["estimate"]["steps"], "wall_s": r["estimate"]["wall_s"], "converged": r["estimate"]["converged"]})
        rows.append(outs[0] | {"pick": "top1"})
        if len(outs) > 1:
            rows.append(min(outs, key=lambda o: o["error_mm"]) | {"pick": f"best_of_{top}"})
        else:
            rows.append(outs[0] | {"pick": f"best_of_{top}"})
    return rows


def multi_direction(cases: list[dict], deformations, axial_model_path: str, plane_model_path: str, out_csv: str, *,
                    base: CaseConfig | None = None, top: int = 3, workers: int = 1, scheduler: str | None = None,
                    progress=print) -> list[dict]:
    """:func:`multi_direction_task` over cases x deformations (run as :func:`sweep`'s tasks: here, in a
    local process pool, or on Dask),
    written to ``out_csv`` as tasks finish; resumable (finished (case, deformation) pairs are skipped)."""
    from .selection import SelectionModel

    for path in (axial_model_path, plane_model_path):
        SelectionModel.load(path)  # fail early, naming the missing model
    base = base or CaseConfig()
    rows = _read_rows(out_csv)
    done = {(r["case"], str(r["deformation"])) for r in rows}
    args = [(c, int(d), axial_model_path, plane_model_path, base, top) for c in cases for d in deformations
            if (c.get("name", "case"), str(d)) not in done]
    with _CsvAppender(out_csv, MULTI_FIELDS) as out:

        def keep(task_rows):
            out.write(task_rows)
            rows.extend({k: str(v) for k, v in row.items()} for row in task_rows)
            if progress and task_rows:
                progress(f"{task_rows[0]['case']} def{task_rows[0]['deformation']}: " + ", ".join(
                    f"{r['condition']} {r['error_mm']:.2f}" for r in task_rows if r["pick"] == "top1"))

        _report_failures(run_tasks(multi_direction_task, args, keep, workers=workers, scheduler=scheduler), len(args))
    return rows


def summarize_multi(rows: list[dict]) -> str:
    """The multi-direction table (mean +- sd over cases x deformations) beside the paper's."""
    lines = ["| condition | pick | error mm | Dice | initial error mm | 3D affine registration error mm | n | paper error mm | paper Dice |",
             "|---|---|---|---|---|---|---|---|---|"]
    names = {"a": "axial only", "ac": "axial + coronal", "as": "axial + sagittal", "asc": "axial + sagittal + coronal"}
    picks = sorted({r["pick"] for r in rows}, key=lambda p: (p != "top1", p))
    for cond in MULTI_CONDITIONS:
        for pick in picks:
            rs = [r for r in rows if r["condition"] == cond and r["pick"] == pick]
            if not rs:
                continue
            e = np.array([float(r["error_mm"]) for r in rs])
            dc = np.array([float(r["dice"]) for r in rs])
            ie = np.array([float(r["initial_error_mm"]) for r in rs])
            ve = np.array([float(r.get("volume_registration_error_mm") or "nan") for r in rs])
            pe, psd, pdice = PAPER_MULTI[cond]
            paper = f"{pe:.2f} +- {psd:.2f} | {pdice:.3f}" if pick != "top1" else " | "
            lines.append(f"| {names[cond]} | {pick} | {e.mean():.2f} +- {e.std():.2f} | {dc.mean():.3f} +- {dc.std():.3f} | "
                         f"{ie.mean():.2f} +- {ie.std():.2f} | {ve.mean():.2f} +- {ve.std():.2f} | {len(e)} | {paper} |")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="run_case", description="Estimate 3D pancreas motion from 2D slices with a multi-organ "
                                "MPM model; prints the estimate beside the baselines. With no arguments: the built-in phantom.")
    p.add_argument("--image", help="planning image (NIfTI, MHA/MHD, NRRD or a DICOM folder)")
    p.add_argument("--labels", help="label map on the image's grid; without it the built-in phantom is used")
    p.add_argument("--preset", default="amos", choices=["amos", "totalseg_ct", "totalseg_mr"], help="label convention")
    p.add_argument("--phantom-seed", type=int, default=0, help="seed of the phantom (and of the GT perturbations)")
    p.add_argument("--phantom-resolution", type=float, default=1.0, help="phantom voxel size factor (2: 8x fewer voxels)")
    p.add_argument("--organs", default="psdl", help="organ combination: p, ps, pd, pl, psd, psl, pdl, psdl")
    p.add_argument("--slices", default=None, help="driving slices, e.g. axial:12,sagittal:40 (input-volume voxel indices); "
                   "'auto': the axial slice and organ combination the selection model ranks best; 'auto:as', 'auto:ac', "
                   "'auto:asc': psdl, that axial slice plus the best sagittal and/or coronal slice of --plane-selector; "
                   "default: mid-pancreas axial")
    p.add_argument("--selector", default="selection_model.json", help="trained selection model for --slices auto")
    p.add_argument("--plane-selector", default=None, help="trained sagittal/coronal model for --slices auto:as, auto:ac, auto:asc")
    p.add_argument("--protocol", default="paper", choices=["paper", "contact"])
    p.add_argument("--deformation", type=int, default=1, help="paper deformation type 1..8 (also varies the contact seed)")
    p.add_argument("--targets", default="affine", choices=["affine", "gt", "registration"])
    p.add_argument("--device", default=None, choices=["cpu", "cuda"], help="Warp device (default: CUDA when available)")
    p.add_argument("--particle-step", type=int, default=None, help="in-plane particle sampling step (default 2 for the phantom, 1 for files)")
    p.add_argument("--no-perturb", action="store_true", help="simulate the GT with the estimator's nominal materials (debugging)")
    p.add_argument("--literal-angles", action="store_true", help="read the paper's r, g literally as r/2pi radians")
    p.add_argument("--max-steps", type=int, default=6000)
    p.add_argument("--no-volume-registration", action="store_true", help="skip the (slow) 3D registration baseline")
    p.add_argument("--rrd", help="write a Rerun recording of the run to this .rrd file")
    p.add_argument("--rrd-every", type=int, default=20, help="log particle positions every this many steps (scalars every step)")
    p.add_argument("--json", help="write the results as JSON to this file")
    return p


AUTO_MODES = {"auto": "a", "auto:a": "a", "auto:ac": "ac", "auto:as": "as", "auto:asc": "asc"}


def auto_condition(cfg: CaseConfig, selector_path: str, plane_selector_path: str | None = None) -> tuple[str, str, dict]:
    """(organs, slices) chosen by the selection models for this case, and what they reported.

    ``cfg.slices`` is ``auto`` (or ``auto:a``): the axial slice and organ combination the axial model
    ranks best. ``auto:ac``, ``auto:as``, ``auto:asc``: organs psdl, the best psdl axial slice, plus
    the first-ranked coronal and/or sagittal slice of the plane model (the paper's second model).
    """
    from .selection import SelectionModel

    mode = AUTO_MODES.get(cfg.slices)
    if mode is None:
        raise InputError(f"unknown --slices {cfg.slices!r}; use one of {', '.join(AUTO_MODES)}")
    if mode != "a" and not plane_selector_path:
        raise InputError(f"--slices {cfg.slices} needs --plane-selector (the sagittal/coronal model)")
    sel = SelectionModel.load(selector_path)
    plane = SelectionModel.load(plane_selector_path) if mode != "a" else None
    prep = prepare_case(replace(cfg, slices=None, organs="p"))
    geom = prep.full_model.geometry
    ranked, wall = sel.rank(prep.full_model, k=5, combinations=None if mode == "a" else ("psdl",))
    (orientation, k, combo), pred = ranked[0]
    chosen = [(orientation, k)]
    info = {"selection_ms": wall * 1e3, "predicted": pred, "top": [[list(key), p] for key, p in ranked]}
    for letter, o in (("s", "sagittal"), ("c", "coronal")):
        if letter in mode:
            top, w = plane.rank(prep.full_model, (o,), combinations=("psdl",), k=3)
            chosen.append(top[0][0][:2])
            info["selection_ms"] += w * 1e3
            info[f"top_{o}"] = [[list(key), p] for key, p in top]
    slices = ",".join(f"{o}:{k + prep.offset[orientation_image_axis(geom, o)]}" for o, k in chosen)
    return combo, slices, info


def config_from_args(a) -> CaseConfig:
    step = a.particle_step if a.particle_step is not None else (2 if a.labels is None else 1)
    baselines = ("initial", "propagate") if a.no_volume_registration else ("initial", "propagate", "volume_registration")
    return CaseConfig(image=a.image, labels=a.labels, preset=a.preset, phantom_seed=a.phantom_seed, phantom_resolution=a.phantom_resolution,
                      organs=a.organs, slices=a.slices, protocol=a.protocol, deformation=a.deformation, targets=a.targets,
                      device=a.device, particle_step=step, perturb=not a.no_perturb, literal=a.literal_angles, max_steps=a.max_steps,
                      baselines=baselines, rrd_every=a.rrd_every)


def main(argv=None) -> int:
    a = build_parser().parse_args(argv)
    try:
        cfg = config_from_args(a)
        if a.json:
            d = os.path.dirname(os.path.abspath(a.json))
            if not os.path.isdir(d):
                raise InputError(f"output folder {d} for --json does not exist")
        if a.rrd:
            d = os.path.dirname(os.path.abspath(a.rrd))
            if not os.path.isdir(d):
                raise InputError(f"output folder {d} for --rrd does not exist")
        selection = None
        if cfg.slices is not None and cfg.slices.startswith("auto"):
            organs, slices, selection = auto_condition(cfg, a.selector, a.plane_selector)
            cfg = replace(cfg, organs=organs, slices=slices)
        out = run_case(cfg, rrd=a.rrd)
        if selection is not None:
            out["selection"] = selection
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except SimulationError as exc:
        print(f"simulation error: {exc}", file=sys.stderr)
        return 3
    print(format_table(out))
    if out.get("selection"):
        print(f"selected {out['organs']} {','.join(out['slices'])} in {out['selection']['selection_ms']:.2f} ms "
              f"(predicted {out['selection']['predicted']:.2f})")
    if a.json:
        write_json_atomic(a.json, out)
        print(f"wrote {a.json}")
    if a.rrd:
        print(f"wrote {a.rrd} (open with: python -m viewer {a.rrd})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
