"""Brute-force sweep in the paper's form: cases x deformations x organ combinations x driving slices.

    python examples/sweep.py --labels ../shared/data/totalseg_mr/labels.nii.gz \
        --image ../shared/data/totalseg_mr/image.nii.gz --preset totalseg_mr --organs psdl --out runs/mr.csv

Resumable: rows already in ``--out`` are skipped. Prints (and writes beside the CSV as .md) the
summary table: best slice per (case, deformation, combination), mean +- sd, with baselines.
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from warpmpm.images import InputError  # noqa: E402
from warpmpm.runner import COMBINATIONS, CaseConfig, add_sweep_arguments, summarize, sweep, sweep_cases  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_sweep_arguments(p, phantom_resolution=2.0)
    p.add_argument("--organs", default="psdl", help="comma-separated combinations, or 'all'")
    p.add_argument("--orientations", default="axial")
    p.add_argument("--targets", default="affine", choices=["affine", "gt", "registration"])
    p.add_argument("--exclude-driven", action="store_true",
                   help="leave the driven particles out of the metrics (the multi-direction protocol's rule; default: only with several slices)")
    p.add_argument("--slice-stride", type=int, default=1)
    p.add_argument("--max-steps", type=int, default=6000, help="steps per estimate before it is reported not converged")
    p.add_argument("--out", default="runs/sweep.csv")
    a = p.parse_args(argv)
    try:
        if a.slice_stride < 1:
            raise InputError(f"--slice-stride must be at least 1, got {a.slice_stride}")
        cases = sweep_cases(a.labels, a.image, a.preset, a.phantom_seeds, a.phantom_resolution)
        combos = COMBINATIONS if a.organs == "all" else tuple(a.organs.split(","))
        os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
        base = CaseConfig(particle_step=a.particle_step, device=a.device, targets=a.targets, max_steps=a.max_steps,
                          exclude_driven=True if a.exclude_driven else None)
        rows = sweep(cases, [int(d) for d in a.deformations.split(",")], combos, tuple(a.orientations.split(",")), a.out,
                     protocol=a.protocol, slice_stride=a.slice_stride, base=base, scheduler=a.scheduler, workers=a.workers)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    table = summarize(rows)
    print(table)
    with open(os.path.splitext(a.out)[0] + ".md", "w") as f:
        f.write(table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
