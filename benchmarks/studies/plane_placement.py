"""Study (2026-12-03; answer in benchmarks/studies/README.md). How much does the error change with where the cine planes
are placed, on finite-element truths? The ceiling of what choosing the placement (the plane-selection model) can gain.

    python benchmarks/studies/plane_placement.py [--cases mr,phantom] [--load breathing] [--positions 7]

For each case, the 16-frame finite-element truth (seed 0) at its frame of largest pancreas motion; the planes take the
true in-plane motion of their particles (``gt-inplane``: the ceiling of any 2D registration). Placements: one sagittal
plane at ``--positions`` positions across the pancreas; the same with a coronal plane at its most-pancreas position;
a coronal plane across the pancreas with the sagittal at its most-pancreas position. Methods, all with the same
information: the copy of the planes' motion (``propagate`` / ``propagate_planes``), ``rigid`` (each seen organ's
observed translation) and the completion solve (default config). Every organ's mean error (mm). Printed per family:
the best and worst placement, and the rule without a model (each plane where it shows the most pancreas) with its
regret against the best in hindsight.
"""

import argparse
import os
import tempfile
from dataclasses import replace

import numpy as np

from warpmpm.experiment import raw_numbers as raw
from warpmpm.experiment.fem_cases import load, peak_frame


def placements(prep, model, n_positions: int) -> dict:
    """Plane labels by family: ``sagittal``, ``sagittal+coronal`` (coronal at its most-pancreas plane) and
    ``coronal+sagittal`` (sagittal at its most-pancreas plane); each family's list starts with the most-pancreas rule."""
    pan = model.subset(("pancreas",))
    best, spread = {}, {}
    for o in ("sagittal", "coronal"):
        counts = pan.slice_counts(o)[:, 0]
        on = np.nonzero(counts > 0)[0]
        best[o] = int(np.argmax(counts))
        picks = np.unique(np.round(np.linspace(on.min(), on.max(), n_positions)).astype(int))
        spread[o] = [best[o]] + [int(k) for k in picks if k != best[o]]
    lab = prep.label
    return {"sagittal": [lab("sagittal", k) for k in spread["sagittal"]],
            "sagittal+coronal": [f"{lab('sagittal', k)},{lab('coronal', best['coronal'])}" for k in spread["sagittal"]],
            "coronal+sagittal": [f"{lab('sagittal', best['sagittal'])},{lab('coronal', k)}" for k in spread["coronal"]]}


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default="mr,phantom")
    p.add_argument("--load", default="breathing")
    p.add_argument("--positions", type=int, default=7)
    p.add_argument("--raw", type=raw.check_name, default="default")
    a = p.parse_args()
    from warpmpm.errors import InputError
    from warpmpm.experiment.baselines import propagate
    from warpmpm.experiment.case import prepare_case
    from warpmpm.experiment.config import CaseConfig
    from warpmpm.experiment.organs import baseline_positions, organ_scores
    from warpmpm.experiment.target_kinds import run_targets
    from warpmpm.experiment.truth import gt_for_model, make_ground_truth
    from warpmpm.fields import write_field
    from warpmpm.images import write_case
    from warpmpm.solvers.completion import CompletionConfig, CompletionModel, complete
    from warpmpm.truth_fem import TruthConfig, make_truth

    work = tempfile.mkdtemp(prefix="plane_placement-")
    rows = []
    for name in a.cases.split(","):
        try:
            case, preset, img, lab = load(name)
        except SystemExit as e:
            print(e)
            continue
        if img is None:
            img, lab = os.path.join(work, "phantom_image.nii.gz"), os.path.join(work, "phantom_labels.nii.gz")
            write_case(case, lab, img)
        series = make_truth(case, preset, TruthConfig(loads=tuple(a.load.split("+")), frames=16, seed=0))
        n = peak_frame(series)
        field = os.path.join(work, f"{name}_{n}.nii.gz")
        write_field(series.field(n), case.geometry, field)
        cfg = CaseConfig(estimator="slice-driven", image=img, labels=lab, preset=preset, protocol="field", truth_field=field, targets="gt-inplane",
                         device="cpu", particle_step=2 if name == "phantom" else 1)
        prep = prepare_case(cfg)
        gt = make_ground_truth(prep, cfg)
        model = prep.model(cfg.organs)
        gt_pos = gt_for_model(gt, model)
        cm = CompletionModel(prep.case, preset, model, CompletionConfig())
        for family, labels in placements(prep, model, a.positions).items():
            for k, label in enumerate(labels):
                c = replace(cfg, slices=label)
                try:
                    slices = prep.resolve_slices(model, label)
                    tg = run_targets(prep, gt, model, gt_pos, slices, c)
                except InputError as e:  # a plane between the particle layers of a sampled model
                    print(f"{name} {family:17s} {label:28s} skipped: {e}")
                    continue
                idx, targets, axes = tg.idx, tg.targets_mm, tg.drive.axes
                copy = tg.combined_mm if tg.combined_mm is not None else propagate(
                    model, slices[0], tg.affines[0], prep.centre_mm, tg.organ_affines.get(slices[0]))
                comp = complete(cm, idx, targets, axes, copy)
                on = np.zeros(model.n, bool)
                on[idx] = True
                methods = {"copy": copy, "rigid": baseline_positions(model, idx, targets, axes)["rigid"], "completion": comp.positions_mm}
                scores = {m: organ_scores(model, pos, gt_pos, on) for m, pos in methods.items()}
                pan_on = int(np.sum(on & (model.organ_index == model.organs.index("pancreas"))))
                row = {"case": name, "load": a.load, "family": family, "planes": label, "rule": k == 0, "frame": n,
                       "pancreas_on_planes": pan_on, "seen": [o for o in model.organs if scores["rigid"][o]["seen"]],
                       "errors_mm": {m: {o: s[o]["error_mm"] for o in model.organs} for m, s in scores.items()}}
                rows.append(row)
                raw.save(__file__, rows, run=a.raw, quiet=True)
                e = row["errors_mm"]
                print(f"{name} {family:17s} {label:28s} pancreas on planes {pan_on:5d}  pancreas copy {e['copy']['pancreas']:.2f} "
                      f"rigid {e['rigid']['pancreas']:.2f} completion {e['completion']['pancreas']:.2f}  "
                      f"kidney copy {e['copy']['left_kidney']:.2f} completion {e['completion']['left_kidney']:.2f}"
                      + ("  (rule)" if k == 0 else ""), flush=True)
    raw.save(__file__, rows, run=a.raw)
    print("\n| case | placements | method | organ | rule (most pancreas) | best | worst | regret of the rule |")
    print("|---|---|---|---|---|---|---|---|")
    for name in dict.fromkeys(r["case"] for r in rows):
        for family in dict.fromkeys(r["family"] for r in rows):
            fam = [r for r in rows if r["case"] == name and r["family"] == family]
            for m in ("copy", "completion"):
                for o in ("pancreas", "left_kidney"):
                    v = np.array([r["errors_mm"][m][o] for r in fam])
                    rule = next(r["errors_mm"][m][o] for r in fam if r["rule"])
                    print(f"| {name} | {family} ({len(fam)}) | {m} | {o} | {rule:.2f} | {v.min():.2f} | {v.max():.2f} | "
                          f"{rule - v.min():.2f} |")


if __name__ == "__main__":
    main()
