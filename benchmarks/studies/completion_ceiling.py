"""How far can the completion reach on what no plane shows, given more than the planes show? (issue 36)

    python benchmarks/studies/completion_ceiling.py [--cases mr,ct,phantom] [--planes sagittal+coronal,sagittal]
    python benchmarks/studies/completion_ceiling.py --load breathing+push --planes sagittal+coronal --raw push

On a finite-element breathing truth (seed 0, the frame of largest pancreas motion; ``warpmpm.truth_fem``), with the
planes where they show the most pancreas, the completion (default :class:`~warpmpm.solvers.completion.CompletionConfig`)
is given, for the organs the planes cross:

- ``planes``: the planes' true in-plane motion (``gt-inplane``), copied off the plane (what a run gives it);
- ``planes_on_global``: the same less the ``global`` baseline's translation, which is added back to every particle;
- ``planes_free_off``: the same with no spring on the seen organs' parts off the planes and nothing overwritten (the
  elasticity alone shapes them: what the physics makes of a local push seen partly on a plane);
- ``inplane_whole``: the true motion of *every* particle of those organs along the directions the planes measure (a
  perfect copy: the ceiling of anything that shapes the seen organs better);
- ``3d_whole``: the true 3D motion of every particle of those organs (the ceiling of the completion model itself: what
  its equilibrium makes of the seen organs' whole motion).

Beside them the same-information baselines (``initial``, ``copy``, ``nearest``, ``global``). The organ on no plane
(the left kidney) and, with one plane, the seen organs' through-plane error (``lr_mm`` for a sagittal plane) are
what is read. Raw numbers: ``benchmarks/studies/results/completion_ceiling.json``.
"""

import argparse
import os
import tempfile

import numpy as np

from warpmpm.experiment import raw_numbers as raw
from warpmpm.experiment.fem_cases import field_run, load_on_disk, peak_frame


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default="mr,ct,phantom")
    p.add_argument("--planes", default="sagittal+coronal,sagittal")
    p.add_argument("--load", default="breathing", help="the truth's loads, e.g. breathing+push")
    p.add_argument("--raw", type=raw.check_name, default="default", help="the run's name in the raw file")
    a = p.parse_args()
    from warpmpm.experiment.organs import baseline_positions, organ_scores, organ_translations
    from warpmpm.fields import write_field
    from warpmpm.solvers.completion import CompletionConfig, CompletionModel, complete, seen_parts
    from warpmpm.truth_fem import TruthConfig, make_truth

    rows, work = [], tempfile.mkdtemp(prefix="completion-ceiling-")
    for name in a.cases.split(","):
        loaded = load_on_disk(name, os.path.join(work, name))
        if loaded is None:
            continue
        case, preset, img, lab = loaded
        series = make_truth(case, preset, TruthConfig(loads=tuple(a.load.split("+")), frames=16, seed=0))
        n = peak_frame(series)
        path = os.path.join(work, f"{name}_{n}.nii.gz")
        write_field(series.field(n), case.geometry, path)
        for label in a.planes.split(","):
            cfg, prep, model, gt_pos, slices, tg, copy = field_run(img, lab, preset, path, name, label)
            idx, targets, axes = tg.idx, tg.targets_mm, tg.drive.axes
            on = np.zeros(model.n, bool)
            on[idx] = True
            methods = {"initial": model.positions_mm, "copy": copy}
            methods |= baseline_positions(model, idx, targets, axes)
            cm = CompletionModel(prep.case, preset, model)
            methods["planes"] = complete(cm, idx, targets, axes, copy).positions_mm
            # the same, solved for the observation less the global translation (the ``global`` baseline's motion), which
            # is then added to every particle: organs far from the seen ones keep the global motion, not none
            b = organ_translations(model, idx, targets, axes)["_all"]
            methods["planes_on_global"] = complete(cm, idx, targets - b, axes, copy - b).positions_mm + b
            # the seen organs' parts off the planes left to the elasticity (no spring to the copy there, the on-plane
            # particles not overwritten): what the physics itself makes of a local push seen partly on a plane
            free = CompletionModel(prep.case, preset, model, CompletionConfig(off_plane_stiffness=0.0, observed_first=False))
            methods["planes_free_off"] = complete(free, idx, targets, axes, copy).positions_mm
            parts = seen_parts(model, idx, axes)
            whole = np.concatenate([np.nonzero(model.organ_index == model.organ_index[idx[sel[0]]])[0] for sel, _, _ in parts])
            P = np.concatenate([np.broadcast_to(Pk, (int(np.sum(model.organ_index == model.organ_index[idx[sel[0]]])), 3, 3))
                                for sel, _, Pk in parts])
            methods["inplane_whole"] = complete(cm, whole, gt_pos[whole], P, gt_pos).positions_mm
            methods["3d_whole"] = complete(cm, whole, gt_pos[whole], None, gt_pos).positions_mm
            scores = {m: organ_scores(model, pos, gt_pos, on) for m, pos in methods.items()}
            seen = [o for o in model.organs if scores["rigid"][o]["seen"]]
            rows.append({"case": name, "load": a.load, "planes": label, "slices": cfg.slices, "frame": n, "seen": seen,
                         "truth_made_by": series.record["made_by"], "scores": scores})
            raw.save(__file__, rows, run=a.raw, quiet=True)
            print(f"\n{name}, {label} ({cfg.slices}), frame {n}; seen: {', '.join(seen)}; mean error mm (LR | AP | SI)")
            print("| method | " + " | ".join(model.organs) + " |\n|---|" + "---|" * len(model.organs))
            for m, sc in scores.items():
                cells = [f"{sc[o]['error_mm']:.2f} ({sc[o]['lr_mm']:.2f} | {sc[o]['ap_mm']:.2f} | {sc[o]['si_mm']:.2f})"
                         if (m not in ("nearest", "global") or o not in seen) else "" for o in model.organs]
                print(f"| {m} | " + " | ".join(cells) + " |", flush=True)
    raw.save(__file__, rows, run=a.raw)


if __name__ == "__main__":
    main()
