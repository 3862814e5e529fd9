"""Train the condition-selection models from sweep CSVs and report them in the paper's form.

The paper's first model (axial slice and organ combination; target: error or Dice averaged over the
8 deformations; features: slice position and per-organ particle counts):

    python examples/sweep.py --phantom-seeds 0,1,2,3,4,5 --phantom-resolution 3 --organs all --out runs/train_axial.csv --workers 2
    python examples/train_selection.py runs/train_axial.csv --out runs/selection_error.json --storage sqlite:///runs/selection.db

Its second model (sagittal and coronal slices, psdl, GT targets, driven particles excluded; target:
the Dice rank within a case and orientation; features: particle counts only):

    python examples/sweep.py --phantom-seeds 2,3,4 --phantom-resolution 3 --organs psdl --orientations sagittal,coronal \\
        --targets gt --exclude-driven --out runs/train_planes.csv --workers 2
    python examples/train_selection.py runs/train_planes.csv --target dice_rank --out runs/selection_planes.json

Reports train/test R2 and RMSE for a split by case (no case on both sides; the model saved is this
one) and by row (the paper's random split), feature importance, the selection time, and the regret
on the held-out cases (top-1 pick, and best of the top 3 as the paper's plane rule).
"""

import argparse
import csv
import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import numpy as np  # noqa: E402

from warpmpm.images import InputError  # noqa: E402
from warpmpm.selection import TrainingTable, baseline_regret, regret, tune_and_train  # noqa: E402


def selection_time_ms(model, repeats: int = 200) -> dict:
    """Time of ranking every candidate of the default phantom (built once), as a user's pre-treatment step."""
    from warpmpm.runner import CaseConfig, prepare_case

    full = prepare_case(CaseConfig(organs="p", device="cpu", particle_step=2)).full_model
    times = []
    for _ in range(repeats):
        ranked, wall = model.rank(full, k=3)
        times.append(wall * 1e3)
    t = np.array(times[5:])
    return {"mean_ms": float(t.mean()), "sd_ms": float(t.std()), "median_ms": float(np.median(t)), "n_candidates": len(model.rank(full, k=None)[0])}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("csv", nargs="+")
    p.add_argument("--target", default="error_mm", choices=["error_mm", "dice", "dice_rank"])
    p.add_argument("--orientations", default=None, help="keep only these orientations (default: axial, or sagittal,coronal for dice_rank)")
    p.add_argument("--patience", type=int, default=100, help="stop tuning after this many trials without a better CV R2")
    p.add_argument("--max-trials", type=int, default=1000)
    p.add_argument("--test-cases", default=None, help="comma-separated cases to hold out (default: a random 20 %% of the cases)")
    p.add_argument("--storage", default=None, help="Optuna storage, e.g. sqlite:///runs/selection.db (tuning resumes from it)")
    p.add_argument("--splits", default="case,row", help="which splits to tune and report; the model saved is the first")
    p.add_argument("--out", default="selection_model.json")
    p.add_argument("--report", default=None, help="write the report as JSON here")
    a = p.parse_args(argv)
    try:
        rows = []
        for path in a.csv:
            if not os.path.exists(path):
                raise InputError(f"sweep CSV {path} not found")
            with open(path) as f:
                rows += list(csv.DictReader(f))
        orientations = tuple(a.orientations.split(",")) if a.orientations else (
            ("sagittal", "coronal") if a.target == "dice_rank" else ("axial",))
        table = TrainingTable.from_sweep(rows, a.target, orientations=orientations)
        for out_path in (a.out, a.report):
            if out_path and not os.path.isdir(os.path.dirname(os.path.abspath(out_path))):
                raise InputError(f"output folder {os.path.dirname(os.path.abspath(out_path))} does not exist")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
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
            json.dump(out, f, indent=1, default=str)
        os.replace(tmp, a.report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
