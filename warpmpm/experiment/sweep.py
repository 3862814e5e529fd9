"""The brute-force sweep of the paper: cases x deformations x organ combinations x driving slices.

One CSV row per simulation (:data:`SWEEP_FIELDS`), resumable (finished rows are skipped), the work
split into one task per (case, deformation) so it runs here, in a process pool or on Dask
(:func:`warpmpm.experiment.tasks.run_tasks`).
"""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np

from ..errors import InputError, SimulationError
from ..images import ORGANS, parse_organs
from ..slices import DrivingSlice, orientation_image_axis
from .case import prepare_case
from .config import CaseConfig
from .io import CsvAppender, read_rows
from .run import run_prepared
from .tasks import report_failures, run_tasks
from .truth import make_ground_truth

__all__ = ["SWEEP_FIELDS", "case_config", "sweep_task", "sweep_cases", "sweep"]

SWEEP_FIELDS = ["case", "protocol", "deformation", "organs", "orientation", "slice", "targets", "excluded_driven", "n_driven", "n_pancreas",
                "error_mm", "p95_mm", "dice", "steps", "wall_s", "converged",
                "initial_error_mm", "initial_dice", "propagate_error_mm", "propagate_dice",
                "count_pancreas", "count_stomach", "count_duodenum", "count_left_kidney", "failure"]


def _row_key(r) -> tuple:
    return (str(r["case"]), str(r["protocol"]), str(r["deformation"]), str(r["organs"]), str(r["orientation"]), str(r["slice"]))


def case_config(base: CaseConfig, case: dict, **changes) -> CaseConfig:
    """``base`` with a case dict's fields (its ``name`` aside) and ``changes``."""
    return replace(base, **{k: v for k, v in case.items() if k != "name"}, **changes)


def sweep_task(case: dict, deformation: int, combinations, orientations, protocol: str, slice_stride: int, base: CaseConfig,
               done: frozenset = frozenset()) -> list[dict]:
    """All rows of one (case, deformation): every combination x orientation x pancreas slice not in ``done``.

    A plain function of picklable arguments, so it runs inline, in a process pool or on a Dask worker.
    A simulation that fails is kept as a row with its ``failure`` (so a re-run does not retry it).
    """
    name = case.get("name", "case")
    cfg0 = case_config(base, case, protocol=protocol, deformation=int(deformation), baselines=("initial", "propagate"))
    prep = prepare_case(cfg0)
    gt = None
    rows = []
    for combo in combinations:
        organs = parse_organs(combo)
        if not set(organs) <= set(prep.full_model.organs):
            continue
        model = prep.full_model.subset(organs)
        for orientation in orientations:
            counts = prep.full_model.slice_counts(orientation)
            axis = orientation_image_axis(model.geometry, orientation)
            ks = np.unique(model.voxel_ijk[model.organ_slice("pancreas"), axis])[::slice_stride]
            for k in ks:
                k_in = prep.to_input(DrivingSlice(orientation, int(k))).index
                label = f"{orientation}:{k_in}"
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
                    out = run_prepared(prep, gt, replace(cfg0, organs=combo, slices=label))
                except SimulationError as exc:
                    rows.append(row | {"error_mm": float("nan"), "dice": float("nan"), "converged": False, "failure": str(exc)})
                    continue
                r = out.results
                rows.append(row | {"excluded_driven": out.excluded_driven, "n_driven": out.n_driven,
                                   "n_pancreas": out.n_particles["pancreas"], "error_mm": r["estimate"].error_mm,
                                   "p95_mm": r["estimate"].p95_mm, "dice": r["estimate"].dice, "steps": out.estimate.steps,
                                   "wall_s": out.estimate.wall_s, "converged": out.estimate.converged,
                                   "initial_error_mm": r["initial"].error_mm, "initial_dice": r["initial"].dice,
                                   "propagate_error_mm": r["propagate"].error_mm, "propagate_dice": r["propagate"].dice})
    return rows


def sweep_cases(labels: str | None, image: str | None, preset: str, phantom_seeds: str, phantom_resolution: float) -> list[dict]:
    """The case dicts of :func:`sweep` from command-line values: one labelled case (named for its
    folder) or a phantom per comma-separated seed (``phantom<seed>``)."""
    if labels:
        return [{"name": os.path.basename(os.path.dirname(os.path.abspath(labels))), "labels": labels, "image": image, "preset": preset}]
    try:
        seeds = [int(s) for s in phantom_seeds.split(",")]
    except ValueError:
        raise InputError(f"--phantom-seeds must be comma-separated integers, got {phantom_seeds!r}") from None
    cases = [{"name": f"phantom{s}", "phantom_seed": s, "phantom_resolution": phantom_resolution} for s in seeds]
    for c in cases:  # every case is checked before any task starts
        case_config(CaseConfig(), c)
    return cases


def sweep(cases: list[dict], deformations, combinations, orientations=("axial",), out_csv: str = "sweep.csv", *,
          protocol: str = "paper", slice_stride: int = 1, base: CaseConfig | None = None, scheduler: str | None = None,
          workers: int = 1, progress=print) -> tuple[list[dict], list[tuple]]:
    """Brute-force sweep; one CSV row per simulation, resumable (finished rows are skipped).

    ``cases``: dicts of :class:`CaseConfig` fields naming a case (``{"phantom_seed": 3}`` or
    ``{"labels": ..., "image": ..., "preset": ...}``) with a ``name``. Work is split into one task per
    (case, deformation). ``scheduler=None`` runs them here (``workers > 1``: a local process pool);
    ``"local"`` starts a Dask ``LocalCluster`` of ``workers`` processes; any other value is a Dask
    scheduler address (``tcp://host:8786``). Rows are written here as tasks finish.
    Returns every row (old and new) and the failed tasks.
    """
    base = base or CaseConfig(estimator="slice-driven")
    for d in deformations:  # every deformation is checked before any task starts
        replace(base, protocol=protocol, deformation=int(d))
    with CsvAppender(out_csv, SWEEP_FIELDS, ("case", "protocol", "deformation", "organs", "orientation", "slice"), "sweep CSV",
                     "resume a CSV of `warpmpm sweep`, or name a new --out") as out:
        rows = read_rows(out_csv)
        done = frozenset(_row_key(r) for r in rows)
        args = [(c, int(d), tuple(combinations), tuple(orientations), protocol, slice_stride, base, done) for c in cases for d in deformations]

        def keep(task_rows):
            out.write(task_rows)
            for row in task_rows:
                rows.append({k: str(v) for k, v in row.items()})
                if progress:
                    progress(f"{row['case']} def{row['deformation']} {row['organs']} {row['orientation']}:{row['slice']} "
                             f"error {row['error_mm']:.2f} mm")

        failed = run_tasks(sweep_task, args, keep, workers=workers, scheduler=scheduler)
        report_failures(failed, len(args))
    return rows, failed
