"""The paper's multi-direction validation: axial only, axial + coronal, axial + sagittal, all three.

Organs psdl, targets from the GT positions (no registration error), particles on every driving slice
left out of the metrics. The axial slice comes from the axial selection model, the sagittal and
coronal candidates from the plane model's top 3 (see examples/train_selection.py). Prints the table
beside the paper's and writes it beside the CSV (.md).

    python examples/multi_direction.py --axial-model runs/selection_error.json --plane-model runs/selection_planes.json \\
        --phantom-seeds 0,1,10,17,19,24 --phantom-resolution 3 --out runs/multi.csv --workers 2
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from warpmpm.images import InputError  # noqa: E402
from warpmpm.runner import CaseConfig, add_sweep_arguments, multi_direction, summarize_multi, sweep_cases  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--axial-model", required=True, help="axial selection model (error_mm target)")
    p.add_argument("--plane-model", required=True, help="sagittal/coronal Dice-rank model")
    add_sweep_arguments(p, phantom_resolution=3.0)
    p.add_argument("--top", type=int, default=3, help="sagittal and coronal candidates tried")
    p.add_argument("--out", default="runs/multi.csv")
    a = p.parse_args(argv)
    try:
        if a.top < 1:
            raise InputError(f"--top must be at least 1, got {a.top}")
        cases = sweep_cases(a.labels, a.image, a.preset, a.phantom_seeds, a.phantom_resolution)
        d = os.path.dirname(os.path.abspath(a.out))
        if not os.path.isdir(d):
            raise InputError(f"output folder {d} for --out does not exist")
        base = CaseConfig(particle_step=a.particle_step, device=a.device, protocol=a.protocol)
        rows = multi_direction(cases, [int(x) for x in a.deformations.split(",")], a.axial_model, a.plane_model, a.out,
                               base=base, top=a.top, workers=a.workers, scheduler=a.scheduler)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    table = summarize_multi(rows)
    print(table)
    with open(os.path.splitext(a.out)[0] + ".md", "w") as f:
        f.write(table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
