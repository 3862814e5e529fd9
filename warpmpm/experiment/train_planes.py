"""Train and report the plane-placement model from ``warpmpm sweep-planes`` CSVs (``warpmpm train-planes``).

    warpmpm sweep-planes --phantom-seeds 0,1,2,3,4,5,6,7 --positions 4 --workers 2 --out runs/planes.csv
    warpmpm train-planes runs/planes.csv --test-cases totalseg_mr,totalseg_ct,phantom7 --out runs/plane_placement.json

Every figure is split by case (the anatomy: a phantom seed or a labelled scan; the truths of one case never sit on
both sides):

* **held-out cases**: the model is tuned (Optuna, folds by case) and trained on the other cases and scored on these;
* **leave one case out**: with the tuned parameters, one model per case trained on all the others and scored on it
  (every case is a test case once).

Scores: R2 of the fraction of the pancreas's motion missed (the model's target) and of the pancreas error in mm
(the predicted fraction times the truth's motion: the error a user gets once the breathing amplitude is known); the
Spearman correlation of predicted and measured pancreas error among the placements of one choice; and the regret
(mm above the best placement in hindsight) of the model's pick, of the rule without a model (each plane where it
shows the most pancreas) and of a random pick, per family, judged by the pancreas error and by the mean error of the
pancreas and its organs at risk (the model then ranks by the mean predicted fraction over the four organs). The model saved is the held-out one.
"""

from __future__ import annotations

import json
import os

import numpy as np

from ..errors import InputError, strict_json
from ..images import ORGANS
from ..plane_placement import FEATURES, PlacementTable, is_rule, placement_regret, train_placement_model
from ..selection import r2_score

__all__ = ["OBJECTIVES", "read_sweep_rows", "evaluate", "evaluate_simulated", "train_planes"]

#: what a choice is judged by: the pancreas alone (the target), or the mean error of the pancreas and its organs at risk
OBJECTIVES = {"pancreas": ("pancreas",), "all_organs": tuple(ORGANS)}


def read_sweep_rows(paths) -> list[dict]:
    from .io import read_csv

    rows = []
    for path in paths:
        rows += read_csv(path, "plane-sweep CSV", ("case", "family", "planes"), "make one with `warpmpm sweep-planes`")
    return rows


def _spearman(a, b) -> float:
    from ..selection import percentile_rank

    ra, rb = percentile_rank(a), percentile_rank(b)
    return float(np.corrcoef(ra, rb)[0, 1]) if ra.std() > 0 and rb.std() > 0 else float("nan")


def evaluate(table: PlacementTable, predicted: dict, mask: np.ndarray) -> dict:
    """The held-out scores of ``predicted`` (organ -> fraction missed, every row) on the rows of ``mask``."""
    out = {"n_rows": int(mask.sum()), "cases": sorted(set(table.cases[mask].tolist()))}
    for o in ORGANS:
        y, p = table.missed[o][mask], predicted[o][mask]
        out[f"{o}_r2_fraction"] = r2_score(y, p)
        out[f"{o}_r2_mm"] = r2_score(table.error_mm[o][mask], p * table.motion_mm[o][mask])
    rho = [_spearman(table.error_mm["pancreas"][mask & (table.groups == g)], predicted["pancreas"][mask & (table.groups == g)])
           for g in np.unique(table.groups[mask]) if np.sum(mask & (table.groups == g)) > 2]
    out["pancreas_spearman_within_choice"] = float(np.nanmean(rho)) if rho else float("nan")
    for objective, organs in OBJECTIVES.items():
        reg = placement_regret(table, predicted, mask, organs)
        sub = out[objective] = {"organs": list(organs), "regret": reg}
        for family in ("sagittal", "sagittal+coronal"):
            rs = [v for g, v in reg.items() if g.endswith("|" + family)]
            if rs:
                sub[f"mean_regret_mm_{family}"] = {k: float(np.nanmean([r[k] for r in rs])) for k in ("model", "rule", "random")}
                sub[f"max_regret_mm_{family}"] = {k: float(np.nanmax([r[k] for r in rs])) for k in ("model", "rule", "random")}
                sub[f"spread_mm_{family}"] = float(np.mean([r["worst_mm"] - r["best_mm"] for r in rs]))
    return out


def evaluate_simulated(rows: list[dict], method: str = "copy") -> dict:
    """The simulated selector (``plan-planes --simulate``), which fits nothing: for every case with two or more truth
    seeds, the placements are ranked by their errors on one truth and judged on another of the same scan (every
    ordered pair of seeds). Returns the R2 of each organ's error on the judging truth predicted by that on the
    choosing truth (as fractions of the organ's motion, and in mm with the judging truth's motion known), and the
    regret of the simulated pick, of the rule and of a random pick, per family and objective (:data:`OBJECTIVES`)."""
    by: dict = {}
    for r in rows:
        if not r.get("failure") and r.get(f"{method}_pancreas_mm") not in (None, ""):
            by.setdefault((r["case"], r["load"], r["family"], r["truth_seed"]), {})[r["planes"]] = r
    pairs = [(k, k2) for k in by for k2 in by if k[:3] == k2[:3] and k[3] != k2[3]]
    out = {"cases": sorted({k[0] for k, _ in pairs}), "n_pairs": len(pairs)}
    if not pairs:
        return out
    pred, true = {o: [] for o in ORGANS}, {o: [] for o in ORGANS}
    pred_mm, true_mm = {o: [] for o in ORGANS}, {o: [] for o in ORGANS}
    regrets: dict = {}
    for a, b in pairs:
        common = [p for p in by[a] if p in by[b]]
        for o in ORGANS:
            fa = np.array([float(by[a][p][f"{method}_{o}_mm"]) / float(by[a][p][f"initial_{o}_mm"]) for p in common])
            mb = np.array([float(by[b][p][f"initial_{o}_mm"]) for p in common])
            eb = np.array([float(by[b][p][f"{method}_{o}_mm"]) for p in common])
            pred[o] += list(fa)
            true[o] += list(eb / mb)
            pred_mm[o] += list(fa * mb)
            true_mm[o] += list(eb)
        for objective, organs in OBJECTIVES.items():
            ea = np.array([np.mean([float(by[a][p][f"{method}_{o}_mm"]) for o in organs]) for p in common])
            eb = np.array([np.mean([float(by[b][p][f"{method}_{o}_mm"]) for o in organs]) for p in common])
            rule = [i for i, p in enumerate(common) if is_rule(by[b][p])]
            regrets.setdefault((objective, a[2]), []).append(
                {"simulated": float(eb[np.argmin(ea)] - eb.min()), "rule": float(eb[rule[0]] - eb.min()) if rule else float("nan"),
                 "random": float(eb.mean() - eb.min()), "spread": float(eb.max() - eb.min())})
    for o in ORGANS:
        out[f"{o}_r2_fraction"] = r2_score(np.array(true[o]), np.array(pred[o]))
        out[f"{o}_r2_mm"] = r2_score(np.array(true_mm[o]), np.array(pred_mm[o]))
    for (objective, family), rs in regrets.items():
        out.setdefault(objective, {})[family] = {
            k: {"mean": float(np.nanmean([r[k] for r in rs])), "max": float(np.nanmax([r[k] for r in rs]))}
            for k in ("simulated", "rule", "random", "spread")}
    return out


def train_planes(paths, *, test_cases=None, method: str = "copy", out: str | None = None, report: str | None = None,
                 storage: str | None = None, max_trials: int = 60, patience: int = 20, loco: bool = True, progress=print) -> dict:
    """Train, evaluate split by case (module docstring), save the held-out model to ``out`` and the report to
    ``report``; returns the report."""
    for path in (out, report):
        if path and not os.path.isdir(os.path.dirname(os.path.abspath(path))):
            raise InputError(f"output folder {os.path.dirname(os.path.abspath(path))} does not exist")
    rows = read_sweep_rows(paths)
    table = PlacementTable.from_sweep(rows, method)
    cases = sorted(set(table.cases.tolist()))
    if len(cases) < 3:
        raise InputError(f"a split by case needs at least 3 cases in the sweep, found {len(cases)}: {', '.join(cases)}")
    if test_cases:
        unknown = sorted(set(test_cases) - set(cases))
        if unknown:
            raise InputError(f"test cases {', '.join(unknown)} are not in the sweep (cases: {', '.join(cases)})")
        test = np.isin(table.cases, list(test_cases))
    else:
        rng = np.random.default_rng(0)
        test = np.isin(table.cases, rng.choice(cases, max(1, round(0.25 * len(cases))), replace=False))
    if test.all():
        raise InputError("the test cases leave no case to train on")
    progress(f"{len(rows)} sweep rows -> {len(table.cases)} placements from {len(cases)} cases; "
             f"held out: {', '.join(sorted(set(table.cases[test].tolist())))}")
    model, tuning = train_placement_model(table, ~test, max_trials=max_trials, patience=patience, storage=storage)
    pred = model.predict(table.X)
    rep = {"method": method, "features": list(FEATURES), "n_rows": len(table.cases), "cases": cases, "tuning": tuning,
           "held_out": evaluate(table, pred, test)}
    _print_scores("held-out cases", rep["held_out"], progress)
    if loco:
        from ..plane_placement import _fit, _log_missed, organ_inputs

        params = dict(model.params)
        rounds = params.pop("rounds")
        loco_pred = {o: np.zeros(len(table.cases)) for o in ORGANS}
        for c in cases:
            held = table.cases == c
            for o in ORGANS:
                Xo = organ_inputs(table.X, o)
                b = _fit(params, rounds, Xo[~held], _log_missed(table, o)[~held])
                loco_pred[o][held] = np.exp(b.inplace_predict(Xo[held]))
        rep["leave_one_case_out"] = evaluate(table, loco_pred, np.ones(len(table.cases), bool))
        _print_scores("leave one case out", rep["leave_one_case_out"], progress)
    rep["simulated"] = sim = evaluate_simulated(rows, method)
    if sim.get("n_pairs"):
        progress(f"simulated selector (no fitting; ranked on one finite-element truth of a scan, judged on another; "
                 f"{len(sim['cases'])} cases, {sim['n_pairs']} truth pairs): pancreas R2 {sim['pancreas_r2_fraction']:.3f} "
                 f"(fraction missed), {sim['pancreas_r2_mm']:.3f} (mm)")
        for objective in OBJECTIVES:
            for family, v in sim.get(objective, {}).items():
                progress(f"  {family}, {objective.replace('_', ' ')}: regret mean/max (mm): simulated "
                         f"{v['simulated']['mean']:.3f}/{v['simulated']['max']:.3f}, rule {v['rule']['mean']:.3f}/"
                         f"{v['rule']['max']:.3f}, random {v['random']['mean']:.3f}/{v['random']['max']:.3f}")
    if out:
        held = rep["held_out"]
        model.trained_on |= {"report": os.path.basename(report) if report else None, "method": method,
                             "held_out": {"cases": held["cases"], "pancreas_r2_fraction": held["pancreas_r2_fraction"],
                                          "regret_mm": {obj: {fam: held[obj][f"mean_regret_mm_{fam}"] for fam in
                                                              ("sagittal", "sagittal+coronal") if f"mean_regret_mm_{fam}" in held[obj]}
                                                        for obj in OBJECTIVES}}}
        model.save(out)
        progress(f"saved {out}")
    if report:
        tmp = report + ".part"
        with open(tmp, "w") as f:
            json.dump(strict_json(rep), f, indent=1, allow_nan=False)
        os.replace(tmp, report)
    return rep


def _print_scores(title: str, s: dict, progress) -> None:
    progress(f"{title} ({len(s['cases'])} cases, {s['n_rows']} placements): pancreas R2 {s['pancreas_r2_fraction']:.3f} "
             f"(fraction missed), {s['pancreas_r2_mm']:.3f} (mm, breathing amplitude known); "
             f"Spearman within a choice {s['pancreas_spearman_within_choice']:.3f}")
    for o in ORGANS[1:]:
        progress(f"  {o}: R2 {s[f'{o}_r2_fraction']:.3f} (fraction), {s[f'{o}_r2_mm']:.3f} (mm)")
    for objective in OBJECTIVES:
        sub = s[objective]
        for family in ("sagittal", "sagittal+coronal"):
            if f"mean_regret_mm_{family}" in sub:
                m, x = sub[f"mean_regret_mm_{family}"], sub[f"max_regret_mm_{family}"]
                progress(f"  {family}, {objective.replace('_', ' ')}: regret mean/max (mm): model {m['model']:.3f}/{x['model']:.3f}, "
                         f"rule {m['rule']:.3f}/{x['rule']:.3f}, random {m['random']:.3f}/{x['random']:.3f}; "
                         f"best-to-worst spread {sub[f'spread_mm_{family}']:.3f}")
