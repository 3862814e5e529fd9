"""The completion solve (``warpmpm.solvers.completion``) against the copies of what the planes see, on finite-element
truths (``warpmpm.truth_fem``, not made by anything the estimator uses), every organ.

    python benchmarks/completion.py [--cases mr,ct,phantom] [--loads breathing,breathing+push] [--planes sagittal+coronal,sagittal]

For each case and load, a 16-frame truth (seed 0) and its frame of largest pancreas motion; each plane set where it
shows the most of the pancreas; targets: the true in-plane motion of the planes' particles (``gt-inplane``, the ceiling
of any 2D registration). Methods, all with the same information: ``copy`` (``propagate_planes``, or ``propagate`` with
one plane), ``rigid`` (each seen organ's observed translation), ``nearest`` / ``global`` (organs on no plane),
``completion`` (default config) and ``completion_paper`` (the seed paper's organ materials). The slice-driven
estimator of the same truths is run ``table`` of ``results/fem_truth.json`` (``benchmarks/fem_truth.py --table``):
it is not re-run here (minutes a run). Prints one table per (case, load, planes); raw numbers: run ``table`` (or
``series``) of ``benchmarks/results/completion.json``, with every organ's JSON scores and the solve's report.
"""

import argparse
import os
import tempfile
import time

import numpy as np

from warpmpm.experiment import raw_numbers as raw
from warpmpm.experiment.fem_cases import field_run, load_on_disk, peak_frame


def report(path: str, estimate_path: str | None = None, run: str = "table") -> str:
    """Markdown from a raw file: per (case, load, planes) each organ's copy, best same-information baseline for organs
    on no plane (``nearest`` / ``global``), ``completion``, and the slice-driven estimate of the same truth and planes
    from run ``table`` of ``results/fem_truth.json`` where it has the row."""
    rows = raw.load(path, run)
    est = {}
    if estimate_path and os.path.exists(estimate_path):
        for r in raw.load(estimate_path, "table")["runs"]:
            est[(r["case"], r["load"], r["planes"])] = r["result"]["results"]["estimate"]["organs"]
    organs = ("pancreas", "stomach", "duodenum", "left_kidney")
    head = "| case | load | planes | " + " | ".join(f"{o.replace('_', ' ')}: copy / other / completion / estimate" for o in organs) + " |"
    lines = [head, "|---|---|---|" + "---|" * len(organs)]
    for r in rows:
        sc = r["scores"]
        e = est.get((r["case"], r["load"], r["planes"]), {})
        cells = []
        for o in organs:
            if o not in sc["copy"]:
                cells.append("")
                continue
            other = (f"{min(sc['nearest'][o]['error_mm'], sc['global'][o]['error_mm']):.2f}" if o not in r["seen"] and "nearest" in sc
                     else f"{sc['rigid'][o]['error_mm']:.2f}")
            mark = "" if o in r["seen"] else "*"
            cells.append(f"{mark}{sc['copy'][o]['error_mm']:.2f} / {other} / **{sc['completion'][o]['error_mm']:.2f}** / "
                         + (f"{e[o]['error_mm']:.2f}" if o in e else "-"))
        lines.append(f"| {r['case']} | {r['load']} | {r['planes']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def series_run(a):
    """Every frame of a 16-frame truth (breathing) in order, the completion warm-started from the last frame (the plane
    set fixed: its system and multigrid built once): each frame's solve time and the pancreas's and kidney's error
    beside the copy's. The frame's registration is not in it (true in-plane motion)."""
    from warpmpm.experiment.baselines import propagate
    from warpmpm.experiment.organs import organ_scores
    from warpmpm.experiment.target_kinds import run_targets
    from warpmpm.fields import sample_field
    from warpmpm.solvers.completion import CompletionModel, ReducedCompletion, complete
    from warpmpm.truth_fem import TruthConfig, make_truth

    out = []
    work = tempfile.mkdtemp(prefix="completion-series-")
    for name in a.cases.split(","):
        loaded = load_on_disk(name, os.path.join(work, name))
        if loaded is None:
            continue
        case, preset, img, lab = loaded
        tr = make_truth(case, preset, TruthConfig(loads=("breathing",), frames=16, seed=0))
        n0 = peak_frame(tr)
        path = os.path.join(work, f"{name}_{n0}.nii.gz")
        from warpmpm.fields import write_field

        write_field(tr.field(n0), case.geometry, path)
        for label in a.planes.split(","):
            cfg, prep, model, _, slices, _, _ = field_run(img, lab, preset, path, name, label)
            cm = CompletionModel(prep.case, preset, model)
            rows = []
            reduced = None
            for n in range(16):
                gt_pos = model.positions_mm + sample_field(tr.field(n), case.geometry, model.positions_mm)
                tg = run_targets(prep, None, model, gt_pos, slices, cfg)
                copy = tg.combined_mm if tg.combined_mm is not None else propagate(
                    model, slices[0], tg.affines[0], prep.centre_mm, tg.organ_affines.get(slices[0]))
                r = complete(cm, tg.idx, tg.targets_mm, tg.drive.axes, copy)
                if reduced is None:
                    reduced = ReducedCompletion(CompletionModel(prep.case, preset, model), tg.idx, tg.drive.axes)
                    print(f"{name} {label}: reduced completion set up in {reduced.setup_s:.1f} s ({reduced.R.shape[-1]} responses)")
                rr = reduced.complete(tg.targets_mm, copy)
                on = np.zeros(model.n, bool)
                on[tg.idx] = True
                sc, sc_copy = organ_scores(model, r.positions_mm, gt_pos, on), organ_scores(model, copy, gt_pos, on)
                sc_red = organ_scores(model, rr.positions_mm, gt_pos, on)
                rows.append({"frame": n, "wall_s": r.wall_s, "iterations": r.iterations, "converged": r.converged,
                             "reduced_wall_s": rr.wall_s, **{f"{o}_reduced_mm": sc_red[o]["error_mm"] for o in model.organs},
                             **{f"{o}_mm": sc[o]["error_mm"] for o in model.organs},
                             **{f"{o}_copy_mm": sc_copy[o]["error_mm"] for o in model.organs}})
                print(f"{name} {label} frame {n:2d}: {r.wall_s:.2f} s, {r.iterations} CG iterations, pancreas {sc['pancreas']['error_mm']:.2f} "
                      f"(copy {sc_copy['pancreas']['error_mm']:.2f}), left kidney {sc['left_kidney']['error_mm']:.2f} "
                      f"(copy {sc_copy['left_kidney']['error_mm']:.2f}); reduced {1e3 * rr.wall_s:.0f} ms, pancreas "
                      f"{sc_red['pancreas']['error_mm']:.2f}, left kidney {sc_red['left_kidney']['error_mm']:.2f}", flush=True)
            t = np.array([r["wall_s"] for r in rows[1:]])  # frame 0 builds the system
            tr_ = np.array([r["reduced_wall_s"] for r in rows])
            summary = {"case": name, "planes": label, "first_frame_s": rows[0]["wall_s"], "median_s": float(np.median(t)),
                       "reduced_setup_s": reduced.setup_s, "reduced_median_s": float(np.median(tr_)),
                       "reduced_p95_s": float(np.percentile(tr_, 95)),
                       "p95_s": float(np.percentile(t, 95)), "unknowns": cm.summary()["unknowns"], "frames": rows}
            print(f"{name} {label}: first frame {rows[0]['wall_s']:.2f} s (system and multigrid built), then median "
                  f"{summary['median_s']:.2f} s, p95 {summary['p95_s']:.2f} s a frame; reduced: set up in {reduced.setup_s:.1f} s, "
                  f"then median {1e3 * summary['reduced_median_s']:.0f} ms, p95 {1e3 * summary['reduced_p95_s']:.0f} ms a frame", flush=True)
            out.append(summary)
            raw.save(__file__, out, run=a.raw, quiet=True)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default="mr,ct,phantom")
    p.add_argument("--loads", default="breathing,breathing+push")
    p.add_argument("--planes", default="sagittal+coronal,sagittal")
    p.add_argument("--raw", type=raw.check_name, default="table", help="the run's name in benchmarks/results/completion.json")
    p.add_argument("--series", action="store_true", help="every frame of a breathing truth in order, warm-started: time a frame")
    p.add_argument("--report", action="store_true", help="print the markdown table of run --raw of results/completion.json and stop")
    a = p.parse_args()
    if a.report:
        print(report(raw.results_path(__file__), raw.results_path(os.path.join(os.path.dirname(os.path.abspath(__file__)), "fem_truth.py")), a.raw))
        return
    if a.series:
        if a.raw == "table":
            a.raw = "series"
        series_run(a)
        return
    from warpmpm.experiment.organs import baseline_positions, organ_scores, true_distances
    from warpmpm.fields import write_field
    from warpmpm.solvers.completion import CompletionConfig, CompletionModel, complete
    from warpmpm.truth_fem import TruthConfig, make_truth

    rows = []
    work = tempfile.mkdtemp(prefix="completion-")
    for name in a.cases.split(","):
        loaded = load_on_disk(name, os.path.join(work, name))
        if loaded is None:
            continue
        case, preset, img, lab = loaded
        for loads in a.loads.split(","):
            series = make_truth(case, preset, TruthConfig(loads=tuple(loads.split("+")), frames=16, seed=0))
            n = peak_frame(series)
            path = os.path.join(work, f"{name}_{loads}_{n}.nii.gz")
            write_field(series.field(n), case.geometry, path)
            for label in a.planes.split(","):
                cfg, prep, model, gt_pos, slices, tg, copy = field_run(img, lab, preset, path, name, label)
                idx, targets, axes = tg.idx, tg.targets_mm, tg.drive.axes
                on = np.zeros(model.n, bool)
                on[idx] = True
                methods = {"initial": (model.positions_mm, {}), "copy": (copy, {})}
                methods |= {k: (v, {}) for k, v in baseline_positions(model, idx, targets, axes).items()}
                for variant, c_cfg in (("completion", CompletionConfig()), ("completion_paper", CompletionConfig(materials="paper"))):
                    t0 = time.perf_counter()
                    cm = CompletionModel(prep.case, preset, model, c_cfg)
                    r = complete(cm, idx, targets, axes, copy)
                    methods[variant] = (r.positions_mm, {"wall_s": time.perf_counter() - t0, "build_s": cm.build_s, "solve_s": r.wall_s,
                                                         "converged": r.converged, "iterations": r.iterations, "residual": r.residual,
                                                         **cm.summary()})
                truth_d = true_distances(model, gt_pos)
                scores = {m: organ_scores(model, pos, gt_pos, on, truth_distances=truth_d) for m, (pos, _) in methods.items()}
                seen = [o for o in model.organs if scores["rigid"][o]["seen"]]
                row = {"case": name, "load": loads, "planes": label, "slices": cfg.slices, "frame": n, "seen": seen,
                       "truth_made_by": series.record["made_by"], "scores": scores, "info": {m: i for m, (_, i) in methods.items()}}
                rows.append(row)
                raw.save(__file__, rows, run=a.raw, quiet=True)
                print(f"\n{name}, {loads}, {label} ({cfg.slices}), frame {n}; seen: {', '.join(seen)}; "
                      f"completion {methods['completion'][1]['wall_s']:.1f} s, {methods['completion'][1]['unknowns']:,} unknowns, "
                      f"converged {methods['completion'][1]['converged']}")
                print("| method | " + " | ".join(model.organs) + " |")
                print("|---|" + "---|" * len(model.organs))
                for m, sc in scores.items():
                    cells = [f"{sc[o]['error_mm']:.2f}" if (m not in ("nearest", "global") or o not in seen) else "" for o in model.organs]
                    print(f"| {m} | " + " | ".join(cells) + " |", flush=True)
    raw.save(__file__, rows, run=a.raw)


if __name__ == "__main__":
    main()
