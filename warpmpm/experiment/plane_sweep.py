"""Sweeps of cine-plane placements on finite-element truths: the training table of a plane-selection model.

For each case (a phantom seed, or a labelled scan), truth seed and load, a finite-element truth series is made
(:mod:`warpmpm.truth_fem`) and its frame of largest pancreas motion is the truth. Each placement of the planes (one
sagittal plane across the pancreas, or a sagittal plane across it with a coronal plane where it shows the most
pancreas) takes the true in-plane motion of its particles (``gt-inplane``: the ceiling of any 2D registration) and is
scored for the methods that use that information: the copy of the planes' motion (``propagate`` /
``propagate_planes``), ``rigid`` (each seen organ's observed translation) and the completion solve. Every organ's mean
error (mm) is a column, beside the features a user has before treatment: what each organ shows on the planes and how
far it lies from them.

One CSV row per (case, truth seed, load, placement), resumable (finished rows are skipped), one task per (case, truth
seed, load) so it runs here, in a process pool or on Dask (:func:`warpmpm.experiment.tasks.run_tasks`).
"""

from __future__ import annotations

import csv
import os
import tempfile
from dataclasses import replace

import numpy as np

from ..errors import InputError, SimulationError
from ..images import ORGANS
from ..plane_placement import FEATURES as PLACEMENT_FEATURES
from .io import CsvAppender, read_rows
from .tasks import report_failures, run_tasks

__all__ = ["FAMILIES", "METHODS", "PLANE_SWEEP_FIELDS", "placement_labels", "plane_features", "plane_sweep_task",
           "refresh_features", "sweep_planes"]

#: the placement families: ``sagittal`` (one plane, MRIdian-like) and ``sagittal+coronal`` (Unity-like, the coronal
#: plane where it shows the most pancreas)
FAMILIES = ("sagittal", "sagittal+coronal")
#: the methods scored for every placement
METHODS = ("initial", "copy", "rigid", "completion")

_COUNTS = [f"{o}_on_planes" for o in ORGANS]
#: the features of :mod:`warpmpm.plane_placement` (``n_planes`` is read from ``planes``)
_FEATURES = [f for f in PLACEMENT_FEATURES if f != "n_planes"]
PLANE_SWEEP_FIELDS = (["case", "truth_seed", "load", "family", "planes", "rule", "frame"] + _COUNTS + _FEATURES
                      + [f"{m}_{o}_mm" for m in METHODS for o in ORGANS] + ["wall_s", "failure"])


def _row_key(r) -> tuple:
    return (str(r["case"]), str(r["truth_seed"]), str(r["load"]), str(r["planes"]))


def placement_labels(prep, model, family: str, n_positions: int) -> list[str]:
    """The ``--slices`` of a family's placements, the first the rule without a model (each plane where it shows the
    most pancreas). ``sagittal``: then up to ``n_positions`` sagittal planes evenly across the pancreas;
    ``sagittal+coronal``: every pair of those sagittal planes with the coronal planes placed the same way across the
    pancreas (up to ``(n_positions + 1) ** 2`` placements)."""
    if family not in FAMILIES:
        raise InputError(f"plane family {family!r}: use one of {', '.join(FAMILIES)}")
    from ..plane_placement import pancreas_slices

    spread = {o: pancreas_slices(model, o, n_positions=n_positions) for o in ("sagittal", "coronal")}
    sag = [prep.label("sagittal", k) for k in spread["sagittal"]]
    if family == "sagittal":
        return sag
    cor = [prep.label("coronal", k) for k in spread["coronal"]]
    return [f"{s},{c}" for s in sag for c in cor]


def plane_features(model, slices, idx: np.ndarray) -> dict:
    """What a user knows of a placement before treatment: per organ the particles on the planes (``idx``), and the
    features of :func:`warpmpm.plane_placement.placement_features` (one code path with ``warpmpm plan-planes``)."""
    from ..plane_placement import Placement, placement_features

    on = np.zeros(model.n, bool)
    on[idx] = True
    out = {f"{o}_on_planes": int(np.sum(on & (model.organ_index == k))) for k, o in enumerate(model.organs)}
    family = "sagittal+coronal" if len(slices) > 1 else "sagittal"
    row = placement_features(model, [Placement(family, tuple(slices))])[0]
    return out | {f: float(v) for f, v in zip(PLACEMENT_FEATURES, row) if f != "n_planes"}


def _case_model(case: dict, particle_step: int):
    """The prepared case and the particle model a sweep task builds for ``case`` (the features' planning model)."""
    from .case import prepare_case
    from .config import CaseConfig
    from .sweep import case_config

    cfg = case_config(CaseConfig(device="cpu", particle_step=int(particle_step)), case)
    prep = prepare_case(cfg)
    return prep, prep.model(cfg.organs)


def refresh_features(out_csv: str, cases: list[dict], particle_step: int = 1, progress=print) -> int:
    """Recompute the feature columns of the rows of ``cases`` in a plane-sweep CSV from their planning scans (after
    the features changed; the truths and errors are kept) and rewrite it whole with today's columns. Returns the
    number of rows refreshed."""
    from ..plane_placement import Placement, placement_features
    from .io import CsvAppender

    if not os.path.exists(out_csv):
        raise InputError(f"plane-sweep CSV {out_csv} not found")
    with CsvAppender(out_csv, PLANE_SWEEP_FIELDS, ("case", "truth_seed", "load", "family", "planes"), "plane-sweep CSV",
                     "make one with `warpmpm sweep-planes`") as out:  # holds the lock: no sweep writes meanwhile
        out.f.close()  # rewritten whole below, not appended to
        rows = read_rows(out_csv)
        n = 0
        for case in cases:
            name = case.get("name", "case")
            mine = [r for r in rows if r["case"] == name]
            if not mine:
                if progress:
                    progress(f"{name}: no row in {out_csv}")
                continue
            prep, model = _case_model(case, particle_step)
            placements = [Placement(r["family"], tuple(prep.resolve_slices(model, r["planes"]))) for r in mine]
            X = placement_features(model, placements)
            for r, x in zip(mine, X):
                r.update({f: repr(float(v)) for f, v in zip(PLACEMENT_FEATURES, x) if f != "n_planes"})
            n += len(mine)
            if progress:
                progress(f"{name}: {len(mine)} rows refreshed")
        tmp = out_csv + ".part"
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, PLANE_SWEEP_FIELDS, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
        os.replace(tmp, out_csv)
    return n


def plane_sweep_task(case: dict, truth_seed: int, load: str, families: tuple, n_positions: int, done: frozenset = frozenset(),
                     truth_cell_mm: float | None = None, particle_step: int = 1, methods: tuple = METHODS) -> list[dict]:
    """All rows of one (case, truth seed, load) not in ``done``; a plain function of picklable arguments (runs inline,
    in a process pool or on Dask). A placement whose run fails is kept as a row with its ``failure``. ``methods``:
    those of :data:`METHODS` to score (``("initial", "copy")`` skips the completion's set-up)."""
    from ..images import load_case
    from ..phantom import make_phantom
    from ..truth_fem import TruthConfig
    from .case import prepare_case
    from .config import CaseConfig
    from .sweep import case_config

    name = case.get("name", "case")
    cfg0 = case_config(CaseConfig(device="cpu", particle_step=int(particle_step)), case)
    # the truth is made on the whole planning scan (its body outline, spine and diaphragm side), not on the run's crop
    if cfg0.labels is not None:
        whole = load_case(cfg0.labels, cfg0.image, cfg0.preset)
    else:
        whole = make_phantom(seed=cfg0.phantom_seed, resolution=cfg0.phantom_resolution, preset=cfg0.preset)
    tcfg = TruthConfig(loads=tuple(load.split("+")), frames=16, seed=int(truth_seed))
    if truth_cell_mm is not None:
        tcfg = replace(tcfg, cell_mm=float(truth_cell_mm))
    if done:  # a resumed sweep: a task whose placements are all in the CSV is skipped before its truth is made
        prep0 = prepare_case(cfg0)
        model0 = prep0.model(cfg0.organs)
        todo = [label for family in families for label in placement_labels(prep0, model0, family, n_positions)
                if (name, str(truth_seed), load, label) not in done]
        if not todo:
            return []
    work = tempfile.mkdtemp(prefix="warpmpm-plane-sweep-")
    try:
        return _plane_sweep_rows(case, name, cfg0, whole, tcfg, work, truth_seed, load, families, n_positions, done, methods)
    finally:
        import shutil

        shutil.rmtree(work, ignore_errors=True)  # the task's truth and planning files: never left in the temp folder


def _plane_sweep_rows(case, name, cfg0, whole, tcfg, work, truth_seed, load, families, n_positions, done, methods):
    """:func:`plane_sweep_task`'s rows, its files written in ``work``."""
    import time

    from ..fields import write_field
    from ..images import write_case
    from ..solvers.completion import CompletionConfig, CompletionModel, complete
    from ..truth_fem import make_truth
    from .baselines import propagate
    from .case import prepare_case
    from .fem_cases import peak_frame
    from .organs import baseline_positions, organ_scores
    from .target_kinds import run_targets
    from .truth import gt_for_model, make_ground_truth

    image, labels = cfg0.image, cfg0.labels
    if labels is None:  # a phantom: its planning image is written for the field run
        image, labels = os.path.join(work, "image.nii.gz"), os.path.join(work, "labels.nii.gz")
        write_case(whole, labels, image)
    series = make_truth(whole, cfg0.preset, tcfg)
    frame = peak_frame(series)
    field = os.path.join(work, "truth.nii.gz")
    write_field(series.field(frame), whole.geometry, field)
    cfg = replace(cfg0, image=image, labels=labels, phantom_seed=0, protocol="field", truth_field=field, targets="gt-inplane")
    prep = prepare_case(cfg)
    gt = make_ground_truth(prep, cfg)
    model = prep.model(cfg.organs)
    gt_pos = gt_for_model(gt, model)
    bad = sorted(set(methods) - set(METHODS))
    if bad:
        raise InputError(f"methods {', '.join(bad)}: use {', '.join(METHODS)}")
    completion = CompletionModel(prep.case, cfg.preset, model, CompletionConfig()) if "completion" in methods else None
    rows = []
    for family in families:
        for k, label in enumerate(placement_labels(prep, model, family, n_positions)):
            if (name, str(truth_seed), load, label) in done:
                continue
            row = {"case": name, "truth_seed": int(truth_seed), "load": load, "family": family, "planes": label, "rule": k == 0,
                   "frame": frame}
            t0 = time.perf_counter()
            try:
                slices = prep.resolve_slices(model, label)
                tg = run_targets(prep, gt, model, gt_pos, slices, replace(cfg, slices=label))
                idx, targets, axes = tg.idx, tg.targets_mm, tg.drive.axes
                copy = tg.combined_mm if tg.combined_mm is not None else propagate(
                    model, slices[0], tg.affines[0], prep.centre_mm, tg.organ_affines.get(slices[0]))
                positions = {"initial": model.positions_mm, "copy": copy}
                if "rigid" in methods:
                    positions["rigid"] = baseline_positions(model, idx, targets, axes)["rigid"]
                if completion is not None:
                    positions["completion"] = complete(completion, idx, targets, axes, copy).positions_mm
                positions = {m: v for m, v in positions.items() if m in methods}
            except (InputError, SimulationError) as exc:
                rows.append(row | {"failure": str(exc)})
                continue
            on = np.zeros(model.n, bool)
            on[idx] = True
            for m, pos in positions.items():
                scores = organ_scores(model, pos, gt_pos, on)
                row |= {f"{m}_{o}_mm": scores[o]["error_mm"] for o in model.organs}
            rows.append(row | plane_features(model, slices, idx) | {"wall_s": time.perf_counter() - t0, "failure": ""})
    return rows


def sweep_planes(cases: list[dict], truth_seeds, loads, families=FAMILIES, n_positions: int = 5, out_csv: str = "planes.csv", *,
                 truth_cell_mm: float | None = None, particle_step: int = 1, scheduler: str | None = None, workers: int = 1,
                 progress=print) -> tuple[list[dict], list[tuple]]:
    """The plane-placement sweep; one CSV row per placement, resumable. ``cases``: dicts of
    :class:`~warpmpm.experiment.config.CaseConfig` fields with a ``name`` (:func:`warpmpm.experiment.sweep.sweep_cases`).
    Returns every row (old and new) and the failed tasks."""
    for f in families:
        if f not in FAMILIES:
            raise InputError(f"plane family {f!r}: use one of {', '.join(FAMILIES)}")
    if int(n_positions) < 1:
        raise InputError(f"--positions must be >= 1, got {n_positions}")
    from ..truth_fem import TruthConfig

    for load in loads:  # every load and seed is checked before any task starts
        TruthConfig(loads=tuple(load.split("+")))
    for seed in truth_seeds:
        TruthConfig(seed=int(seed))
    with CsvAppender(out_csv, PLANE_SWEEP_FIELDS, ("case", "truth_seed", "load", "family", "planes"), "plane-sweep CSV",
                     "resume a CSV of `warpmpm sweep-planes`, or name a new --out") as out:
        rows = read_rows(out_csv)
        done = frozenset(_row_key(r) for r in rows)
        args = [(c, int(s), load, tuple(families), int(n_positions), done, truth_cell_mm, int(particle_step)) for c in cases
                for s in truth_seeds
                for load in loads]

        def keep(task_rows):
            out.write(task_rows)
            for row in task_rows:
                rows.append({k: str(v) for k, v in row.items()})
                if progress:
                    msg = (f"failed: {row['failure']}" if row.get("failure") else
                           f"pancreas copy {row['copy_pancreas_mm']:.2f} / completion {row['completion_pancreas_mm']:.2f} mm")
                    progress(f"{row['case']} truth seed {row['truth_seed']} {row['load']} {row['planes']}: {msg}")

        failed = run_tasks(plane_sweep_task, args, keep, workers=workers, scheduler=scheduler)
        report_failures(failed, len(args), "truth seed")
    return rows, failed
