"""Train the condition-selection models from sweep CSVs and report them in the paper's form (``warpmpm train``).

The paper's first model (axial slice and organ combination; target: error or Dice averaged over the
8 deformations; features: slice position and per-organ particle counts):

    warpmpm sweep --phantom-seeds 0,1,2,3,4,5 --phantom-resolution 3 --organs all --out runs/train_axial.csv --workers 2
    warpmpm train runs/train_axial.csv --out runs/selection_error.json --storage sqlite:///runs/selection.db

Its second model (sagittal and coronal slices, psdl, GT targets, driven particles excluded; target:
the Dice rank within a case and orientation; features: particle counts only):

    warpmpm sweep --phantom-seeds 2,3,4 --phantom-resolution 3 --organs psdl --orientations sagittal,coronal \\
        --targets gt --exclude-driven --out runs/train_planes.csv --workers 2
    warpmpm train runs/train_planes.csv --target dice_rank --out runs/selection_planes.json

Reports train/test R2 and RMSE for a split by case (no case on both sides; the model saved is this
one) and by row (the paper's random split), feature importance, the selection time, and the regret
on the held-out cases (top-1 pick, and best of the top 3 as the paper's plane rule).
"""

from __future__ import annotations

import json
import os

import numpy as np

from ..errors import InputError, strict_json
from ..selection import TrainingTable, baseline_regret, regret, tune_and_train

__all__ = ["selection_time_ms", "train"]


def selection_time_ms(model, repeats: int = 200) -> dict:
    """Time of ranking every candidate of the default phantom (built once), as a user's pre-treatment step."""
    from .case import prepare_case
    from .config import CaseConfig

    full = prepare_case(CaseConfig(organs="p", device="cpu", particle_step=2)).full_model
    times = []
    for _ in range(repeats):
        ranked, wall = model.rank(full, k=3)
        times.append(wall * 1e3)
    t = np.array(times[5:])
    return {"mean_ms": float(t.mean()), "sd_ms": float(t.std()), "median_ms": float(np.median(t)), "n_candidates": len(model.rank(full, k=None)[0])}


def train(a) -> int:
    """Run ``warpmpm train`` with its parsed options ``a`` (see :func:`warpmpm.cli.build_parser`)."""
    from .io import check_output_path, read_csv

    rows = []
    for path in a.csv:
        rows += read_csv(path, "sweep CSV", ("case", "organs", "orientation", "slice"), "make one with `warpmpm sweep`")
    for out_path, option in ((a.out, "--out"), (a.report, "--report")):
        if out_path:
            check_output_path(out_path, option, inputs=[("CSV", p) for p in a.csv])
    orientations = tuple(a.orientations.split(",")) if a.orientations else (
        ("sagittal", "coronal") if a.target == "dice_rank" else ("axial",))
    table = TrainingTable.from_sweep(rows, a.target, orientations=orientations)
    for out_path in (a.out, a.report):
        if out_path and not os.path.isdir(os.path.dirname(os.path.abspath(out_path))):
            raise InputError(f"output folder {os.path.dirname(os.path.abspath(out_path))} does not exist")
    print(f"{len(rows)} simulations -> {len(table.y)} conditions ({', '.join(orientations)}) from {len(set(table.cases))} cases")
    test_cases = a.test_cases.split(",") if a.test_cases else None
    out = {"n_simulations": len(rows), "n_conditions": len(table.y), "cases": sorted(set(table.cases)), "orientations": orientations}
    for i, split in enumerate(a.splits.split(",")):
        model, rep = tune_and_train(table, split=split, patience=a.patience, max_trials=a.max_trials, storage=a.storage,
                                    study_name=f"selection-{a.target}-{split}", test_cases=test_cases if split == "case" else None)
        print(f"split by {split}: trials {rep['trials']} ({rep['tuning_s']:.0f} s), CV R2 {rep['best_cv_r2']:.3f}, "
              f"train R2 {rep['train_r2']:.3f} RMSE {rep['train_rmse']:.4f}, test R2 {rep['test_r2']:.3f} RMSE {rep['test_rmse']:.4f}")
        print(f"  test, within each case: R2 {rep['test_within_case_r2']:.3f}, Spearman {rep['test_spearman']:.3f}")
        print("  importance: " + ", ".join(f"{k} {v:.3f}" for k, v in rep["importance"].items()))
        if split == "case":
            for top in (1, 3):
                r = regret(table, model, model.test_mask, top=top)
                rep[f"regret_top{top}"] = r
                rep[f"mean_regret_top{top}"] = float(np.mean(list(r.values())))
                unit = "Dice" if a.target in ("dice", "dice_rank") else "mm"
                print(f"  regret on held-out cases, best of top {top} ({unit}): mean {rep[f'mean_regret_top{top}']:.4f}; "
                      + ", ".join(f"{k} {v:.3f}" for k, v in r.items()))
            for rule in ("random", "middle", "max_pancreas"):  # choices made without the model, same held-out cases
                r = baseline_regret(table, rule, model.test_mask)
                rep[f"mean_regret_{rule}"] = float(np.mean(list(r.values()))) if r else float("nan")
                print(f"  baseline regret, {rule}: mean {rep[f'mean_regret_{rule}']:.4f}")
        if i == 0:
            model.save(a.out)
            out["selection_time"] = rep["selection_time"] = selection_time_ms(model)
            print(f"  selection time: {rep['selection_time']['mean_ms']:.2f} +- {rep['selection_time']['sd_ms']:.2f} ms "
                  f"over {rep['selection_time']['n_candidates']} candidates (default phantom)")
        out[split] = rep
    print(f"saved {a.out}")
    if a.report:
        tmp = a.report + ".part"
        with open(tmp, "w") as f:
            json.dump(strict_json(out), f, indent=1, allow_nan=False)
        os.replace(tmp, a.report)
    return 0

