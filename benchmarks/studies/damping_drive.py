"""Study (2026-11-23; answer in benchmarks/studies/README.md). Damping rule and drive against the same ground truth (issue 17): why the default stop keeps the fixed
damping and the PID drive, and what the settled mode gives on whole-abdomen scenes.

    python benchmarks/studies/damping_drive.py [--paper 1,2,3] [--contact 1,2,3] [--settled-max-steps 3000]

The built-in phantom (particle step 2, registration targets, the default), one ground truth per case
simulated with the defaults; then the estimate with each variant of (damping rule, drive) at the default
stopping rule, and in the settled mode (``wait_settled``: adaptive damping, PD drive, capped at
``--settled-max-steps``). Pancreas error (mm) and steps beside ``propagate``; raw numbers in
``benchmarks/studies/results/damping_drive.json``.
"""

import argparse
import warnings
from dataclasses import replace


from warpmpm.experiment import raw_numbers as raw
import warp as wp

import warpmpm.experiment.run as run
from warpmpm.driving import DriveConfig
from warpmpm.experiment.case import prepare_case
from warpmpm.experiment.config import CaseConfig
from warpmpm.experiment.truth import make_ground_truth
from warpmpm.solvers import ExplicitConfig, SolverConfig

#: (name, damping rule, integral ratio, settled mode); ki None: the drive's default for the stopping rule
VARIANTS = [("fixed, PID (default)", "auto", None, False), ("adaptive, PID", "adaptive", 0.02, False),
            ("adaptive, PD", "adaptive", 0.0, False), ("fixed, PD", "fixed", 0.0, False), ("settled mode", "auto", None, True)]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--paper", default="1,2,3")
    p.add_argument("--contact", default="1,2,3")
    p.add_argument("--settled-max-steps", type=int, default=3000)
    a = p.parse_args(argv)
    wp.config.quiet = True
    warnings.simplefilter("ignore")
    estimator = run.SliceDrivenEstimator
    rows = []
    print("| case | " + " | ".join(v[0] for v in VARIANTS) + " | propagate |")
    print("|---|" + "---|" * (len(VARIANTS) + 1))
    for protocol, cases in (("paper", a.paper), ("contact", a.contact)):
        for d in [int(x) for x in cases.split(",") if x]:
            cfg0 = CaseConfig(estimator="slice-driven", protocol=protocol, deformation=d, device="cpu", particle_step=2, targets="registration",
                              baselines=("initial", "propagate"))
            prep = prepare_case(cfg0)
            gt = make_ground_truth(prep, cfg0)
            row = {"protocol": protocol, "case": d, "gt_steps": gt.steps}
            for name, rule, ki, settle in VARIANTS:
                # the drive is chosen inside run_prepared: give it this variant's integral
                run.SliceDrivenEstimator = lambda *args, _ki=ki, **kw: estimator(*args, drive_config=DriveConfig(ki_ratio=_ki), **kw)
                try:
                    cfg = replace(cfg0, solver=SolverConfig(explicit=ExplicitConfig(damping_rule=rule)), wait_settled=settle,
                                  max_steps=a.settled_max_steps if settle else cfg0.max_steps)
                    res = run.run_prepared(prep, gt, cfg).to_json()["results"]
                finally:
                    run.SliceDrivenEstimator = estimator
                row[name] = res["estimate"]
                row["propagate"] = res["propagate"]
            rows.append(row)
            cells = " | ".join(f"{row[v[0]]['error_mm']:.2f} ({row[v[0]]['steps']})" for v in VARIANTS)
            print(f"| {protocol} {d} | {cells} | {row['propagate']['error_mm']:.2f} |", flush=True)
    raw.save(__file__, rows)


if __name__ == "__main__":
    main()
