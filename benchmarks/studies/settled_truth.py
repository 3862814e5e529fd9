"""Study (2026-11-23; answer in benchmarks/studies/README.md). The settled mode against a settled truth (issue 17): the contact protocol with its ground truth run until
the whole body has settled (``--gt-wait-settled``), scored for the default estimate (stops on the driven
slice) and the settled mode (``--wait-settled``: adaptive damping, PD drive, runs until the body has
settled), beside ``propagate`` (the slice's motion copied to every particle of its organ) and ``initial``.

    python benchmarks/studies/settled_truth.py [--cases phantom:1,phantom:2,phantom:3] [--max-steps 8000] [--targets registration]

A case is ``phantom:N`` (the built-in phantom, particle step 2, scenario N) or ``mr:N`` / ``ct:N`` (the
samples in ../shared/data, particle step 1; skipped with a message when absent). Pancreas error in mm (mean
over particles), steps, whether each simulation settled; raw numbers in ``benchmarks/studies/results/settled_truth.json``.
"""

import argparse
import os
import sys
import time
import warnings
from dataclasses import replace


from warpmpm.experiment import raw_numbers as raw
import warp as wp

from warpmpm.experiment.case import prepare_case
from warpmpm.experiment.config import CaseConfig
from warpmpm.experiment.run import run_prepared
from warpmpm.experiment.truth import make_ground_truth

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data")
SAMPLES = {"mr": ("totalseg_mr", "totalseg_mr"), "ct": ("totalseg_ct", "totalseg_ct")}


def case_config(name: str, scenario: int, targets: str, max_steps: int) -> CaseConfig | None:
    base = dict(protocol="contact", deformation=scenario, device="cpu", targets=targets, baselines=("initial", "propagate"),
                gt_wait_settled=True, max_steps=max_steps)
    if name == "phantom":
        return CaseConfig(estimator="slice-driven", particle_step=2, **base)
    folder, preset = SAMPLES[name]
    labels, image = os.path.join(DATA, folder, "labels.nii.gz"), os.path.join(DATA, folder, "image.nii.gz")
    if not (os.path.exists(labels) and os.path.exists(image)):
        print(f"skipped {name}:{scenario}: sample data not found in {os.path.normpath(DATA)}", file=sys.stderr)
        return None
    return CaseConfig(estimator="slice-driven", labels=labels, image=image, preset=preset, **base)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default="phantom:1,phantom:2,phantom:3")
    p.add_argument("--max-steps", type=int, default=8000, help="cap of the settled truth and the settled estimate")
    p.add_argument("--targets", default="registration")
    a = p.parse_args(argv)
    wp.config.quiet = True
    warnings.simplefilter("ignore")
    rows = []
    print("| case | truth steps (settled) | default estimate mm (steps) | settled mode mm (steps, settled) | propagate mm | initial mm |")
    print("|---|---|---|---|---|---|")
    for item in a.cases.split(","):
        name, scenario = item.split(":")
        cfg = case_config(name, int(scenario), a.targets, a.max_steps)
        if cfg is None:
            continue
        prep = prepare_case(cfg)
        t0 = time.perf_counter()
        gt = make_ground_truth(prep, cfg)
        gt_wall = time.perf_counter() - t0
        row = {"case": item, "truth_steps": gt.steps, "truth_settled": gt.params.get("gt_settled"), "truth_wall_s": gt_wall}
        for mode, settle in (("default", False), ("settled", True)):
            res = run_prepared(prep, gt, replace(cfg, wait_settled=settle)).to_json()["results"]
            row[mode] = res["estimate"]
            row["propagate"], row["initial"] = res["propagate"], res["initial"]
        rows.append(row)
        d, s = row["default"], row["settled"]
        print(f"| {item} | {gt.steps} ({'yes' if row['truth_settled'] else 'no'}) | {d['error_mm']:.2f} ({d['steps']}) | "
              f"{s['error_mm']:.2f} ({s['steps']}, {'yes' if s.get('settled') else 'no'}) | {row['propagate']['error_mm']:.2f} | "
              f"{row['initial']['error_mm']:.2f} |", flush=True)
    raw.save(__file__, rows)


if __name__ == "__main__":
    main()
