"""Train the condition-selection regressor from sweep CSVs and report it in the paper's form.

    python examples/sweep.py --phantom-seeds 0,1,2,3,4,5 --organs all --out runs/train.csv --workers 2
    python examples/train_selection.py runs/train.csv --out selection_model.json --storage sqlite:///runs/selection.db

Reports train/test R2 and RMSE for a split by case (no case on both sides) and by row (the paper's),
feature importance, the selection time, and the regret on the held-out cases.
"""

import argparse
import csv
import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import numpy as np  # noqa: E402

from warpmpm.selection import TrainingTable, regret, tune_and_train  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("csv", nargs="+")
    p.add_argument("--target", default="error_mm", choices=["error_mm", "dice"])
    p.add_argument("--patience", type=int, default=100)
    p.add_argument("--max-trials", type=int, default=1000)
    p.add_argument("--storage", default=None, help="Optuna storage, e.g. sqlite:///runs/selection.db")
    p.add_argument("--out", default="selection_model.json")
    p.add_argument("--report", default=None, help="write the report as JSON here")
    a = p.parse_args(argv)
    rows = []
    for path in a.csv:
        with open(path) as f:
            rows += list(csv.DictReader(f))
    table = TrainingTable.from_sweep(rows, a.target)
    print(f"{len(rows)} simulations -> {len(table.y)} conditions from {len(set(table.cases))} cases")
    out = {}
    for split in ("case", "row"):
        model, rep = tune_and_train(table, split=split, patience=a.patience, max_trials=a.max_trials,
                                    storage=a.storage, study_name=f"selection-{a.target}-{split}")
        if split == "case":
            rep["regret_mm"] = regret(table, model, model.test_mask)
            model.save(a.out)
        out[split] = rep
        print(f"split by {split}: trials {rep['trials']}, CV R2 {rep['best_cv_r2']:.3f}, train R2 {rep['train_r2']:.3f} "
              f"RMSE {rep['train_rmse']:.3f}, test R2 {rep['test_r2']:.3f} RMSE {rep['test_rmse']:.3f}")
        print("  importance: " + ", ".join(f"{k} {v:.2f}" for k, v in rep["importance"].items()))
        if split == "case":
            print(f"  regret on held-out cases: {rep['regret_mm']} (mean {np.mean(list(rep['regret_mm'].values())):.3f})")
    print(f"saved {a.out}")
    if a.report:
        with open(a.report, "w") as f:
            json.dump(out, f, indent=1, default=str)


if __name__ == "__main__":
    main()
