"""Per-deformation table on a real case at the best axial slice of a sweep: the estimate with GT-affine
targets and with registration targets (the whole chain: capture, register, drive), beside the
baselines initial, propagate and volume_registration.

    warpmpm sweep --labels L --image I --preset totalseg_mr --out runs/mr_paper.csv
    python scripts/mr_report.py runs/mr_paper.csv --labels L --image I --preset totalseg_mr
"""

import argparse
import csv
from dataclasses import replace


import numpy as np

from warpmpm.experiment import CaseConfig, make_ground_truth, prepare_case, run_prepared


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("csv")
    p.add_argument("--labels", required=True)
    p.add_argument("--image", required=True)
    p.add_argument("--preset", default="totalseg_mr")
    p.add_argument("--organs", default="psdl")
    p.add_argument("--device", default=None)
    a = p.parse_args(argv)
    with open(a.csv) as f:
        rows = [r for r in csv.DictReader(f) if r["organs"] == a.organs and r["orientation"] == "axial"]
    best = {}
    for r in rows:
        d = int(r["deformation"])
        if d not in best or float(r["error_mm"]) < float(best[d]["error_mm"]):
            best[d] = r
    base = CaseConfig(labels=a.labels, image=a.image, preset=a.preset, organs=a.organs, device=a.device)
    prep = prepare_case(base)
    cols = ["initial", "propagate", "volume_registration", "estimate (GT affine)", "estimate (registration)"]
    print("| deformation | slice | " + " | ".join(f"{c} mm / Dice" for c in cols) + " | registration error mm | registration ms | steps | estimate s |")
    print("|---" * (len(cols) + 6) + "|")
    acc = {c: [] for c in cols}
    reg_err, reg_ms = [], []
    for d in sorted(best):
        cfg = replace(base, deformation=d, slices=f"axial:{best[d]['slice']}")
        gt = make_ground_truth(prep, cfg)
        aff = run_prepared(prep, gt, cfg)
        reg = run_prepared(prep, gt, replace(cfg, targets="registration", baselines=()))
        res = {"initial": aff.results["initial"], "propagate": aff.results["propagate"],
               "volume_registration": aff.results["volume_registration"], "estimate (GT affine)": aff.estimate,
               "estimate (registration)": reg.estimate}
        for c in cols:
            acc[c].append((res[c].error_mm, res[c].dice))
        reg_err.append(reg.registration["error_mm"])
        reg_ms.append(reg.registration["wall_s"] * 1e3)
        cells = " | ".join(f"{res[c].error_mm:.2f} / {res[c].dice:.3f}" for c in cols)
        print(f"| {d} | {best[d]['slice']} | {cells} | {reg_err[-1]:.2f} | {reg_ms[-1]:.0f} | {aff.estimate.steps} | "
              f"{aff.estimate.wall_s:.1f} |", flush=True)
    cells = " | ".join(f"{np.mean([e for e, _ in acc[c]]):.2f} +- {np.std([e for e, _ in acc[c]]):.2f} / "
                       f"{np.mean([x for _, x in acc[c]]):.3f}" for c in cols)
    print(f"| mean | | {cells} | {np.mean(reg_err):.2f} | {np.mean(reg_ms):.0f} | | |")


if __name__ == "__main__":
    main()
