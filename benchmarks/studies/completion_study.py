"""Study (2026-12-03; answer in docs/decisions/2026-12-03-completion-solve.md): variants of the completion solve's config against the copies on finite-element truths (one case,
one load, plane sets); the figures quoted in docs/decisions/2026-12-03-completion-solve.md.

    python benchmarks/studies/completion_study.py --case mr --loads breathing \
        --planes sagittal+coronal,sagittal --variants default,off10

"""

import argparse
import os
import time

import numpy as np

from warpmpm.experiment import raw_numbers as raw
from warpmpm.experiment.fem_cases import field_run, load, peak_frame


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--case", default="mr")
    p.add_argument("--loads", default="breathing")
    p.add_argument("--planes", default="sagittal+coronal,sagittal")
    p.add_argument("--variants", default="default")
    a = p.parse_args()
    from warpmpm.experiment.organs import baseline_positions, organ_scores
    from warpmpm.fields import write_field
    from warpmpm.images import write_case
    from warpmpm.solvers.completion import CompletionConfig, CompletionModel, complete
    from warpmpm.truth_fem import TruthConfig, make_truth
    import tempfile

    case, preset, img, lab = load(a.case)
    work = tempfile.mkdtemp()
    if img is None:
        img, lab = os.path.join(work, "i.nii.gz"), os.path.join(work, "l.nii.gz")
        write_case(case, lab, img)
    series = make_truth(case, preset, TruthConfig(loads=tuple(a.loads.split("+")), frames=16, seed=0))
    n = peak_frame(series)
    path = os.path.join(work, "t.nii.gz")
    write_field(series.field(n), case.geometry, path)
    variants = {"default": {}, "elastic_only": {"observed_first": False}, "no_off": {"off_plane_stiffness": 0.0},
                "off1": {"off_plane_stiffness": 1.0}, "off10": {"off_plane_stiffness": 10.0}, "cell6": {"cell_mm": 6.0},
                "cell10": {"cell_mm": 10.0}, "paper": {"materials": "paper"}, "wall": {"hold_posterior_wall": True},
                "trans": {"off_plane_motion": "translation"}, "u0": {"unseen_direction_stiffness": 0.0},
                "u1e-3": {"unseen_direction_stiffness": 1e-3}, "t1": {"tissue_stiffness": 1.0}, "t10": {"tissue_stiffness": 10.0},
                "t100": {"tissue_stiffness": 100.0}}
    out = []
    for label in a.planes.split(","):
        cfg, prep, model, gt_pos, slices, tg, copy = field_run(img, lab, preset, path, a.case, label)
        idx, targets, axes = tg.idx, tg.targets_mm, tg.drive.axes
        on = np.zeros(model.n, bool)
        on[idx] = True
        rows = {"initial": model.positions_mm, "copy": copy}
        rows |= baseline_positions(model, idx, targets, axes)
        for v in a.variants.split(","):
            t0 = time.perf_counter()
            cm = CompletionModel(prep.case, preset, model, CompletionConfig(**variants[v]))
            from warpmpm.slices import in_plane_axes
            from warpmpm.solvers.completion import slice_tissue_motion

            tm = slice_tissue_motion(model.geometry, slices, tg.affines, lambda o: in_plane_axes(model, o), prep.centre_mm,
                                     0.5 * cm.dx / 2)
            r = complete(cm, idx, targets, axes, copy, tissue_motion=tm)
            print(f"  {v}: build {cm.build_s:.1f} s, {cm.summary()['unknowns']} unknowns, setup {r.info['setup_s']:.1f} s, solve "
                  f"{r.wall_s:.2f} s, {r.iterations} it, residual {r.residual:.1e}, rms on {r.on_plane_rms_mm:.2f} off {r.off_plane_rms_mm:.2f}, "
                  f"total {time.perf_counter() - t0:.1f} s", flush=True)
            rows["C:" + v] = r.positions_mm
        print(f"{a.case} {a.loads} {label} ({cfg.slices}), frame {n}")
        print("method".ljust(22) + "".join(o[:10].rjust(11) for o in model.organs) + "   dist-err s/d/k")
        scores = {}
        for name, pos in rows.items():
            sc = scores[name] = organ_scores(model, pos, gt_pos, on)
            dist = " ".join(f"{sc[o]['distance_error_mm']:+.1f}" for o in model.organs if "distance_error_mm" in sc[o])
            print(name.ljust(22) + "".join(f"{sc[o]['error_mm']:11.2f}" for o in model.organs) + "   " + dist
                  + "   seen " + "".join(o[0] for o in model.organs if sc[o]["seen"])
                  + "   lr/ap/si " + " ".join(f"{sc[o]['lr_mm']:.1f}/{sc[o]['ap_mm']:.1f}/{sc[o]['si_mm']:.1f}" for o in model.organs))
        out.append({"case": a.case, "loads": a.loads, "planes": label, "slices": cfg.slices, "frame": n, "scores": scores})
    raw.save(__file__, out, run=f"{a.case}_{a.loads}".replace("+", "-"))


if __name__ == "__main__":
    main()
