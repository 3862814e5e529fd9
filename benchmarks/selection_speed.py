"""Time of choosing the driving condition with the selection model, against simulating the choices.

For each case (the default phantom at particle step 2, and the real samples when present) this ranks
every (axial slice, organ combination) with the trained axial model and every sagittal/coronal psdl
slice with the plane model, timing the whole call (slice counts, standardisation, prediction; median
of ``--repeats``), and runs ONE simulation of the chosen condition (paper deformation 1, affine
targets) as the peer: the brute force the model replaces costs that times the number of candidates
times 8 deformations. The paper: 1.48 +- 0.151 ms per choice.

    python benchmarks/selection_speed.py --selector runs/selection_error.json --plane-selector runs/selection_planes.json
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np


from warpmpm.experiment import raw_numbers as raw

import warp as wp

from dataclasses import replace

from warpmpm.experiment import CaseConfig, make_ground_truth, prepare_case, run_prepared
from warpmpm.selection import DEFAULT_PLANE_SELECTOR, DEFAULT_SELECTOR, ConditionSelector

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data")


def time_rank(model: ConditionSelector, full, orientations, repeats: int) -> tuple[float, float, int]:
    ts = []
    for _ in range(repeats):
        ranked, wall = model.rank(full, orientations, k=3)
        ts.append(wall * 1e3)
    ts = np.array(ts[max(1, repeats // 20):])  # drop the first calls (caches)
    return float(np.median(ts)), float(np.percentile(ts, 95)), len(model.rank(full, orientations, k=None)[0])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--selector", default=DEFAULT_SELECTOR, help="axial selection model (default: the shipped one)")
    p.add_argument("--plane-selector", default=DEFAULT_PLANE_SELECTOR, help="sagittal/coronal model (default: the shipped one)")
    p.add_argument("--repeats", type=int, default=200)
    p.add_argument("--device", default="cpu")
    a = p.parse_args(argv)
    wp.config.log_level = wp.LOG_ERROR  # no init banner or module-load lines
    axial = ConditionSelector.load(a.selector)
    plane = ConditionSelector.load(a.plane_selector) if a.plane_selector else None
    cases = [("phantom (default, step 2)", CaseConfig(particle_step=2, device=a.device, baselines=()))]
    for name, preset in (("totalseg_mr", "totalseg_mr"), ("totalseg_ct", "totalseg_ct")):
        labels = os.path.join(DATA, name, "labels.nii.gz")
        if os.path.exists(labels):
            cases.append((name, CaseConfig(labels=labels, image=os.path.join(DATA, name, "image.nii.gz"), preset=preset,
                                           device=a.device, baselines=())))
        else:
            print(f"skipping {name}: {labels} is absent")
    print(f"machine: {platform.node()} ({os.cpu_count()} cores), device {a.device}\n")
    print("| case | particles | model | candidates | choice median ms | p95 ms | one simulation s | simulation / choice |")
    print("|---|---|---|---|---|---|---|---|")
    out = []
    for name, cfg in cases:
        prep = prepare_case(cfg)
        full = prep.full_model
        med, p95, n = time_rank(axial, full, ("axial",), a.repeats)
        (orientation, k, combo), _ = axial.rank(full, k=1)[0][0]
        gt = make_ground_truth(prep, cfg)
        t0 = time.perf_counter()
        run_prepared(prep, gt, replace(cfg, organs=combo, slices=prep.label(orientation, k)))
        sim = time.perf_counter() - t0
        print(f"| {name} | {full.n} | axial (slice x combination) | {n} | {med:.2f} | {p95:.2f} | {sim:.2f} | {sim / (med / 1e3):,.0f} |")
        out.append({"case": name, "particles": full.n, "model": "axial", "candidates": n, "median_ms": med, "p95_ms": p95, "simulation_s": sim})
        if plane is not None:
            med, p95, n = time_rank(plane, full, ("sagittal", "coronal"), a.repeats)
            print(f"| {name} | {full.n} | sagittal + coronal (psdl) | {n} | {med:.2f} | {p95:.2f} | | |")
            out.append({"case": name, "particles": full.n, "model": "planes", "candidates": n, "median_ms": med, "p95_ms": p95})
    raw.save(__file__, out)
    print("\npaper: 1.48 +- 0.151 ms per choice (20-35 slices, 3 surrounding organs)")


if __name__ == "__main__":
    main()
