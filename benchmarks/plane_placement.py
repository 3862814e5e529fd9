"""Where to image: the plane-placement model's choice, its time against the rule without a model, and its accuracy.

Part 1 (time): for the default phantom and the real samples when present, ``warpmpm plan-planes``'s ranking of every
placement (each sagittal plane across the pancreas; each pair of a sagittal and a coronal plane across it), timed
over the whole call (placements, features, prediction; median and p95 of ``--repeats``), beside the rule without a
model (each plane where it shows the most pancreas: slice counts and an argmax) in the same run. The issue's target:
a choice in under 100 ms on 2 cores.

With ``--simulate``, each case's ``plan-planes --method simulate`` (a finite-element truth of the scan and a grid of
placements scored by the copy) is timed too, in seconds (minutes, once at planning).

Part 2 (accuracy): the shipped model's report (``warpmpm/selectors/report_plane_placement.json``, written by
``warpmpm train-planes`` on the finite-element plane sweep): split by case, the pancreas R2 and the regret of the
model's pick against the rule's and a random pick's, per family.

    python benchmarks/plane_placement.py [--repeats 50]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from warpmpm.experiment import raw_numbers as raw

DATA = os.environ.get("WARPMPM_SAMPLE_DATA", os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data"))
REPORT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "warpmpm", "selectors", "report_plane_placement.json")


def rule_time(model, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        pan = model.organs.index("pancreas")
        _ = [int(model.slice_counts(o)[:, pan].argmax()) for o in ("sagittal", "coronal")]
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts[1:]) * 1e3)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=50)
    p.add_argument("--simulate", action="store_true", help="also time the simulated ranking of each case (minutes)")
    p.add_argument("--raw", type=raw.check_name, default="default")
    a = p.parse_args(argv)
    from warpmpm.images import ORGANS, load_case
    from warpmpm.model import build_model
    from warpmpm.phantom import make_phantom
    from warpmpm.plane_placement import PlacementModel

    pm = PlacementModel.load()
    cases = [("phantom (default, step 2)", lambda: build_model(make_phantom(), tuple(ORGANS), sampling_step=2))]
    for name in ("totalseg_mr", "totalseg_ct"):
        lab = os.path.join(DATA, name, "labels.nii.gz")
        if os.path.exists(lab):
            cases.append((name, lambda lab=lab, name=name: build_model(load_case(lab, os.path.join(os.path.dirname(lab), "image.nii.gz"),
                                                                                   name), tuple(ORGANS))))
        else:
            print(f"skipping {name}: {lab} is absent (set WARPMPM_SAMPLE_DATA)")
    m = raw.machine()
    print(f"machine: {m}\n")
    print("| case | particles | placements | model choice median ms | p95 ms | rule ms | model / rule |")
    print("|---|---|---|---|---|---|---|")
    out = {"timing": []}
    for name, make in cases:
        model = make()
        ts = []
        for _ in range(a.repeats):
            ranked, wall = pm.rank(model)
            ts.append(wall * 1e3)
        ts = np.array(ts[1:])
        rule = rule_time(model, a.repeats)
        med, p95 = float(np.median(ts)), float(np.percentile(ts, 95))
        print(f"| {name} | {model.n} | {len(ranked)} | {med:.1f} | {p95:.1f} | {rule:.2f} | {med / rule:.0f} |")
        out["timing"].append({"case": name, "particles": model.n, "placements": len(ranked), "median_ms": med, "p95_ms": p95,
                              "rule_ms": rule, "best": ranked[0][0].label()})
    if a.simulate:
        import contextlib
        import io
        import tempfile

        from warpmpm.cli import main as cli

        print("\n| case | simulated placements | simulated ranking s | best (pancreas) | its error mm | rule's error mm |")
        print("|---|---|---|---|---|---|")
        for name, _ in cases:
            args = ["plan-planes"] if name.startswith("phantom") else [
                "plan-planes", "--labels", os.path.join(DATA, name, "labels.nii.gz"),
                "--image", os.path.join(DATA, name, "image.nii.gz"), "--preset", name]
            path = os.path.join(tempfile.mkdtemp(), "rank.json")
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()):
                cli(args + ["--json", path])
            wall = time.perf_counter() - t0
            with open(path) as f:
                doc = json.load(f)
            best = doc["placements"][0]
            rule = doc["placements"][doc["rule"]["sagittal+coronal"]["rank"] - 1]
            print(f"| {name} | {len(doc['placements'])} | {wall:.0f} | {best['planes']} | "
                  f"{best['simulated_error_mm']['pancreas']:.2f} | {rule['simulated_error_mm']['pancreas']:.2f} |")
            out.setdefault("simulate", []).append({"case": name, "wall_s": wall, "placements": len(doc["placements"]),
                                                   "best": best, "rule": rule})
    if os.path.exists(REPORT):
        with open(REPORT) as f:
            rep = json.load(f)
        print(f"\naccuracy, split by case (the shipped model's report; truths: finite-element, {rep['n_rows']} placements "
              f"of {len(rep['cases'])} cases; error of the method {rep['method']!r})\n")
        sim = rep.get("simulated", {})
        if sim.get("n_pairs"):
            print(f"simulated selector ({len(sim['cases'])} cases, {sim['n_pairs']} truth pairs; ranked on one truth of a scan, "
                  f"judged on another): pancreas R2 {sim['pancreas_r2_fraction']:.3f} (fraction), {sim['pancreas_r2_mm']:.3f} (mm)\n")
            print("| judged by | family | regret simulated mm (mean / max) | rule | random | best-to-worst |")
            print("|---|---|---|---|---|---|")
            for objective in ("pancreas", "all_organs"):
                for fam, v in sim.get(objective, {}).items():
                    print(f"| {objective.replace('_', ' ')} | {fam} | {v['simulated']['mean']:.3f} / {v['simulated']['max']:.3f} | "
                          f"{v['rule']['mean']:.3f} / {v['rule']['max']:.3f} | {v['random']['mean']:.3f} / {v['random']['max']:.3f} | "
                          f"{v['spread']['mean']:.2f} |")
            print()
        print("| evaluation | cases | pancreas R2 (fraction) | pancreas R2 (mm) | judged by | family | regret model mm | rule | "
              "random | best-to-worst |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for key in ("held_out", "leave_one_case_out"):
            s = rep.get(key)
            if not s:
                continue
            for objective in ("pancreas", "all_organs"):
                for fam in ("sagittal", "sagittal+coronal"):
                    r = s.get(objective, {}).get(f"mean_regret_mm_{fam}")
                    if r:
                        print(f"| {key.replace('_', ' ')} | {len(s['cases'])} | {s['pancreas_r2_fraction']:.3f} | "
                              f"{s['pancreas_r2_mm']:.3f} | {objective.replace('_', ' ')} | {fam} | {r['model']:.3f} | "
                              f"{r['rule']:.3f} | {r['random']:.3f} | {s[objective][f'spread_mm_{fam}']:.3f} |")
        out["report"] = {k: rep[k] for k in ("held_out", "leave_one_case_out", "simulated") if k in rep}
    raw.save(__file__, out, run=a.raw)


if __name__ == "__main__":
    main()
