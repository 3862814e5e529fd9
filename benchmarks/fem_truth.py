"""Accuracy on finite-element truths (``warpmpm make-truth``), every organ, with the copying baselines beside the
estimate; and the truth's own mesh convergence.

    python benchmarks/fem_truth.py --table        [--cases mr,ct,phantom] [--loads breathing,breathing+push]
    python benchmarks/fem_truth.py --convergence  [--cases mr,ct,phantom] [--cell-mm 5]

``--table``: for each case and load, a 16-frame truth (seed 0) is made by the finite-element solver (not the MPM) and
the frame where the pancreas moves most is the truth of the runs. Plane sets, each plane where it shows the most of the
pancreas: one sagittal (MRIdian-like), sagittal + coronal (Unity-like, interleaved), one axial, axial + sagittal +
coronal. The estimate is driven by the true in-plane motion of its planes (``gt-inplane``: the ceiling of any 2D
registration); the baselines copy the same information (``propagate`` / ``propagate_planes``, ``rigid``, and for
organs on no plane ``nearest`` / ``global``). Every organ's mean error (mm) is printed; the raw numbers hold the whole
JSON of every run (p95, on/off-plane split, LR/AP/SI, distances to the pancreas).

``--convergence``: the truth at ``cell_mm`` against ``cell_mm / 2`` (breathing + push, the coarse series' frame of the
largest motion): the relative L2 difference of the pancreas's displacement (target: within 5 %), and of every organ's.
"""

import argparse
import os
import tempfile
import time
from dataclasses import replace

import numpy as np

from warpmpm.experiment import raw_numbers as raw
from warpmpm.experiment.fem_cases import PLANES, load, peak_frame, slices_through_pancreas

def table(a):
    from warpmpm.experiment.config import CaseConfig
    from warpmpm.experiment.run import run_case
    from warpmpm.fields import write_field
    from warpmpm.images import write_case
    from warpmpm.truth_fem import TruthConfig, make_truth

    rows, runs = [], []
    work = tempfile.mkdtemp(prefix="fem-truth-")
    for name in a.cases.split(","):
        case, preset, img, lab = load(name)
        if name == "phantom":
            print("phantom: seed 1 (not the default seed 0 the code was developed on), particle step 2", flush=True)
        if img is None:  # the phantom: written out so that the run reads the same planning case
            img, lab = os.path.join(work, "phantom_image.nii.gz"), os.path.join(work, "phantom_labels.nii.gz")
            write_case(case, lab, img)
        for loads in a.loads.split(","):
            t0 = time.perf_counter()
            series = make_truth(case, preset, TruthConfig(loads=tuple(loads.split("+")), frames=16, seed=0))
            n = peak_frame(series)
            path = os.path.join(work, f"{name}_{loads}_{n}.nii.gz")
            write_field(series.field(n), case.geometry, path)
            truth_s = time.perf_counter() - t0
            print(f"{name}, {loads}: truth in {truth_s:.0f} s, frame {n}, pancreas moved "
                  f"{series.record['frames'][n]['pancreas_mean_mm']:.2f} mm", flush=True)
            if "+" in loads:  # what the aperiodic load adds to breathing at that frame
                alone = make_truth(case, preset, TruthConfig(loads=("breathing",), frames=n + 1, seed=0))
                pan = case.labels == case.label_map["pancreas"]
                extra = np.linalg.norm(series.field(n)[pan] - alone.field(n)[pan], axis=1)
                print(f"  the {loads.split('+', 1)[1]} load moves the pancreas {extra.mean():.2f} mm on average, "
                      f"{extra.max():.2f} mm at most, beyond breathing", flush=True)
            for label, planes in PLANES.items():
                cfg = CaseConfig(estimator="slice-driven", image=img, labels=lab, preset=preset, protocol="field", truth_field=path, targets="gt-inplane",
                                 device="cpu", particle_step=2 if name == "phantom" else 1, baselines=("initial", "propagate", "rigid"))
                cfg = replace(cfg, slices=slices_through_pancreas(cfg, planes))
                out = run_case(cfg)
                j = out.to_json()
                runs.append({"case": name, "load": loads, "planes": label, "slices": cfg.slices, "frame": n,
                             "truth_record": {k: series.record[k] for k in ("made_by", "materials", "mesh", "loads")},
                             "truth_frame": series.record["frames"][n], "result": j})
                for method, r in j["results"].items():
                    if "organs" not in r:
                        continue
                    rows.append({"case": name, "load": loads, "planes": label, "method": method,
                                 **{o: s["error_mm"] for o, s in r["organs"].items()},
                                 "seen": "".join(o[0] for o, s in r["organs"].items() if s["seen"]),
                                 "settled": r.get("settled", "")})
                raw.save(__file__, {"rows": rows, "runs": runs}, run=a.raw or "table", quiet=True)  # kept as it goes
                est = j["results"]["estimate"]
                print(f"  {label}: estimate {est['error_mm']:.2f} mm ({est['steps']} steps, settled {est['settled']})", flush=True)
    organs = ("pancreas", "stomach", "duodenum", "left_kidney")
    lines = ["| case | load | planes | method | pancreas | stomach | duodenum | left kidney | seen |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = " | ".join(f"{r[o]:.2f}" if o in r else "" for o in organs)
        lines.append(f"| {r['case']} | {r['load']} | {r['planes']} | {r['method']} | {cells} | {r['seen']} |")
    print("\nmean error mm per organ, driven particles included (true in-plane motion of the planes):")
    print("\n".join(lines))
    raw.save(__file__, {"rows": rows, "runs": runs}, run=a.raw or "table")


def report(path: str, loads: str | None = None, planes: str | None = None, run: str = "table") -> str:
    """Markdown from a ``--table`` raw file: one row per (case, load, planes, organ), each method's mean error (mm);
    the copy is ``propagate_planes`` with several planes, else ``propagate``; ``nearest`` / ``global`` only for organs
    on no plane."""
    runs = raw.load(path, run)["runs"]
    lines = ["| case | load | planes | organ | seen | initial | copy of the planes | rigid | nearest | global | estimate |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        if (loads and r["load"] not in loads.split(",")) or (planes and r["planes"] not in planes.split(",")):
            continue
        res = r["result"]["results"]
        copy = res.get("propagate_planes") or res["propagate"]
        for organ, s in res["initial"]["organs"].items():
            def cell(m):
                return f"{res[m]['organs'][organ]['error_mm']:.2f}" if m in res and organ in res[m].get("organs", {}) else ""
            est = res["estimate"]["organs"][organ]["error_mm"]
            lines.append(f"| {r['case']} | {r['load']} | {r['planes']} | {organ} | {'yes' if res['rigid']['organs'][organ]['seen'] else 'no'} | "
                         f"{s['error_mm']:.2f} | {copy['organs'][organ]['error_mm']:.2f} | {cell('rigid')} | {cell('nearest')} | "
                         f"{cell('global')} | {est:.2f} |")
    return "\n".join(lines)


def convergence(a):
    """The truth at ``cell_mm`` and ``cell_mm / 2``, at the coarse series' frame of largest pancreas motion (the fine
    mesh solves that frame only)."""
    from warpmpm.truth_fem import AbdomenModel, TruthConfig, cell_eigenstrain, diaphragm_displacement, draw_loads, make_truth

    out = []
    for name in a.cases.split(","):
        case, preset, _, _ = load(name)
        t0 = time.perf_counter()
        coarse = make_truth(case, preset, TruthConfig(loads=("breathing", "push"), frames=16, seed=0, cell_mm=a.cell_mm))
        t_coarse = time.perf_counter() - t0
        n = peak_frame(coarse)
        t0 = time.perf_counter()
        cfg = TruthConfig(loads=("breathing", "push"), frames=16, seed=0, cell_mm=a.cell_mm / 2)
        model = AbdomenModel(case, preset, cfg)
        loads = draw_loads(model.mesh, cfg)
        t = n / cfg.fps
        inf, ant = diaphragm_displacement(loads, t)
        u, info = model.solve_frame(inf, ant, cell_eigenstrain(model.mesh, loads, t))
        fine = model.field_on_grid(u)
        t_fine = time.perf_counter() - t0
        row = {"case": name, "frame": n, "cell_mm": [a.cell_mm, a.cell_mm / 2], "wall_s": [t_coarse, t_fine],
               "unknowns": [coarse.record["mesh"]["n_unknowns"], int(3 * len(model.active))], "fine_residual": info["residual"]}
        for organ in ("pancreas", "stomach", "duodenum", "left_kidney"):
            if organ not in case.label_map:
                continue
            m = case.labels == case.label_map[organ]
            uc, uf = coarse.field(n)[m].astype(float), fine[m].astype(float)
            row[organ] = float(np.linalg.norm(uc - uf) / max(np.linalg.norm(uf), 1e-12))
            row[organ + "_mean_mm"] = float(np.linalg.norm(uf, axis=1).mean())
            row[organ + "_mean_difference_mm"] = float(np.linalg.norm(uc - uf, axis=1).mean())
        out.append(row)
        print(f"{name}: frame {n}, pancreas h vs h/2 {100 * row['pancreas']:.1f} % (moved {row['pancreas_mean_mm']:.2f} mm, "
              f"{row['pancreas_mean_difference_mm']:.2f} mm apart), "
              + ", ".join(f"{o} {100 * row[o]:.1f} %" for o in ("stomach", "duodenum", "left_kidney") if o in row)
              + f"; {row['unknowns'][0]:,} / {row['unknowns'][1]:,} unknowns, {t_coarse:.0f} s (16 frames) / {t_fine:.0f} s (1 frame)",
              flush=True)
        raw.save(__file__, out, run=a.raw or "convergence", quiet=True)
    print(f"raw numbers: {raw.results_path(__file__)} (run {a.raw or 'convergence'!r})")


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--table", action="store_true")
    p.add_argument("--convergence", action="store_true")
    p.add_argument("--cases", default="mr,ct,phantom")
    p.add_argument("--loads", default="breathing,breathing+push")
    p.add_argument("--cell-mm", type=float, default=5.0)
    p.add_argument("--raw", type=raw.check_name, default=None, help="the run's name in benchmarks/results/fem_truth.json (default: table or convergence)")
    p.add_argument("--report", action="store_true", help="print the per-organ table of run --raw (default table) of results/fem_truth.json and stop")
    p.add_argument("--planes", default=None, help="with --report: only these plane sets (comma-separated)")
    a = p.parse_args()
    if a.report:
        print(report(raw.results_path(__file__), a.loads if a.loads != "breathing,breathing+push" else None, a.planes, a.raw or "table"))
        raise SystemExit(0)
    if not (a.table or a.convergence):
        p.error("choose --table and/or --convergence")
    if a.convergence:
        convergence(a)
    if a.table:
        table(a)
