"""The paper's multi-direction validation: axial + sagittal and/or coronal driving slices chosen by the
selection models, organs psdl, GT targets, the particles on every driving slice left out of the metrics."""

from __future__ import annotations

import numpy as np

from ..metrics import evaluate
from ..selection import ConditionSelector
from ..slices import driven_indices
from .baselines import volume_registration
from .case import prepare_case
from .config import CaseConfig
from .io import CsvAppender, read_rows
from .run import run_prepared
from .sweep import case_config
from .tables import MULTI_CONDITIONS
from .tasks import report_failures, run_tasks
from .truth import gt_for_model, make_ground_truth

__all__ = ["MULTI_FIELDS", "multi_direction_task", "multi_direction"]

MULTI_FIELDS = ["case", "protocol", "deformation", "condition", "pick", "slices", "n_driven", "n_excluded_pancreas",
                "error_mm", "dice", "initial_error_mm", "initial_dice", "volume_registration_error_mm", "volume_registration_dice",
                "steps", "wall_s", "converged"]


def multi_direction_task(case: dict, deformation: int, selector_path: str, plane_selector_path: str, base: CaseConfig,
                         top: int = 3) -> list[dict]:
    """The paper's multi-direction validation for one (case, deformation), organs psdl, GT targets.

    The axial slice is the psdl slice the axial selector ranks best; the sagittal and coronal
    candidates are the ``top`` slices the plane selector (Dice rank from particle counts) ranks best.
    Conditions: ``a`` (axial only), ``ac`` and ``as`` (axial + each of the ``top`` candidates), ``asc``
    (axial + every sagittal x coronal pair of candidates). Particles on any driving slice are excluded
    from the metrics, as in the paper; the baselines (no motion, 3D affine registration of the planning
    volume to the GT volume) are scored with the same exclusion. Each condition gives two rows: ``pick=top1`` (the first-ranked
    candidates, what a user would get without a ground truth) and ``pick=best_of_{top}`` (the best
    run among the candidates judged against the GT: the paper's rule).
    """
    axial_model = ConditionSelector.load(selector_path)
    plane_model = ConditionSelector.load(plane_selector_path)
    name = case.get("name", "case")
    cfg0 = case_config(base, case, deformation=int(deformation), organs="psdl", targets="gt", exclude_driven=True, baselines=("initial",))
    prep = prepare_case(cfg0)
    full = prep.full_model
    ranked_axial, _ = axial_model.rank(full, ("axial",), combinations=("psdl",), k=1)
    ax = prep.label(*ranked_axial[0][0][:2])
    cand = {o: [prep.label(*key[:2]) for key, _ in plane_model.rank(full, (o,), combinations=("psdl",), k=top)[0]]
            for o in ("sagittal", "coronal")}
    runs = {"a": [[ax]],
            "ac": [[ax, c] for c in cand["coronal"]],
            "as": [[ax, s] for s in cand["sagittal"]],
            "asc": [[ax, s, c] for s in cand["sagittal"] for c in cand["coronal"]]}
    gt = make_ground_truth(prep, cfg0)
    model = prep.model("psdl")
    pancreas = model.organ_slice("pancreas")
    gt_pos = gt_for_model(gt, model)
    vr_pos, _ = volume_registration(prep, gt, model)  # the 3D affine baseline, scored per condition below
    rows = []
    for cond in MULTI_CONDITIONS:
        outs = []
        for slices in runs[cond]:
            text = ",".join(slices)
            out = run_prepared(prep, gt, case_config(cfg0, {}, slices=text))
            r = out.results
            idx = driven_indices(model, prep.resolve_slices(model, text))
            excl = np.zeros(model.n, dtype=bool)
            excl[idx] = True
            vr = evaluate(vr_pos[pancreas], gt_pos[pancreas], model.particle_grid, excl[pancreas], model.sampling_step)
            outs.append({"case": name, "protocol": cfg0.protocol, "deformation": int(deformation), "condition": cond,
                         "slices": ",".join(out.slices), "n_driven": out.n_driven, "n_excluded_pancreas": int(np.sum(pancreas[idx])),
                         "error_mm": r["estimate"].error_mm, "dice": r["estimate"].dice,
                         "initial_error_mm": r["initial"].error_mm, "initial_dice": r["initial"].dice,
                         "volume_registration_error_mm": vr["error_mm"], "volume_registration_dice": vr["dice"],
                         "steps": out.estimate.steps, "wall_s": out.estimate.wall_s, "converged": out.estimate.converged})
        rows.append(outs[0] | {"pick": "top1"})
        rows.append(min(outs, key=lambda o: o["error_mm"]) | {"pick": f"best_of_{top}"})
    return rows


def multi_direction(cases: list[dict], deformations, selector_path: str, plane_selector_path: str, out_csv: str, *,
                    base: CaseConfig | None = None, top: int = 3, workers: int = 1, scheduler: str | None = None,
                    progress=print) -> tuple[list[dict], list[tuple]]:
    """:func:`multi_direction_task` over cases x deformations (as :func:`~warpmpm.experiment.sweep.sweep`'s
    tasks: here, in a local process pool, or on Dask), written to ``out_csv`` as tasks finish; resumable
    (finished (case, deformation) pairs are skipped). Returns every row and the failed tasks."""
    for path in (selector_path, plane_selector_path):
        ConditionSelector.load(path)  # fail early, naming the missing model
    base = base or CaseConfig(estimator="slice-driven")
    with CsvAppender(out_csv, MULTI_FIELDS, ("case",), "multi-direction CSV",
                     "resume a CSV of `warpmpm multi`, or name a new --out") as out:
        rows = read_rows(out_csv)
        done = {(r["case"], str(r["deformation"])) for r in rows}
        args = [(c, int(d), selector_path, plane_selector_path, base, top) for c in cases for d in deformations
                if (c.get("name", "case"), str(d)) not in done]

        def keep(task_rows):
            out.write(task_rows)
            rows.extend({k: str(v) for k, v in row.items()} for row in task_rows)
            if progress and task_rows:
                progress(f"{task_rows[0]['case']} def{task_rows[0]['deformation']}: " + ", ".join(
                    f"{r['condition']} {r['error_mm']:.2f}" for r in task_rows if r["pick"] == "top1"))

        failed = run_tasks(multi_direction_task, args, keep, workers=workers, scheduler=scheduler)
        report_failures(failed, len(args))
    return rows, failed
