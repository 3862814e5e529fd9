"""Choosing the driving slice and organ combination: the condition-selection regression.

Rows are conditions (case, orientation, slice, combination). The paper's first model (axial slices):
features are the slice position and, per organ, the number of its particles on that slice (0 when
the organ is not in the combination), standardised per case (z-score over that case's candidate
rows); the target is the estimate's error (or Dice) averaged over the 8 paper deformations, from a
brute-force sweep. Its second model (sagittal and coronal slices, psdl, GT targets): features are the
particle counts only, the target the percentile rank of the mean Dice among the slices of the same
case and orientation (``target="dice_rank"``); the top 3 slices are the candidates.

An XGBoost regressor (native API) is tuned by Optuna with 5-fold cross-validation, stopping after
``patience`` trials without a better mean R2; the study can live in SQLite so tuning resumes or is
shared. The model saves as XGBoost JSON plus a small JSON of its features, target, orientations and
combinations. :func:`regret` scores a model by what choosing with it costs against the brute-force
best; :func:`baseline_regret` gives the same for choices made without it.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError, optional
from .images import COMBINATIONS, ORGANS, parse_organs
from .model import ParticleModel

__all__ = ["SELECTOR_DIR", "DEFAULT_SELECTOR", "DEFAULT_PLANE_SELECTOR", "FEATURES", "COUNT_FEATURES",
           "HIGHER_IS_BETTER", "raw_features", "standardise", "candidates", "r2_score", "rmse", "TrainingTable",
           "percentile_rank", "split_by_case", "split_by_row", "ConditionSelector", "suggest_xgb_params", "stop_when_stale",
           "tune_and_train", "within_group_scores", "regret", "baseline_regret"]

#: The selectors behind the figures of docs/results.md, shipped with the package: the axial slice and combination
#: model (error target) and the sagittal/coronal Dice-rank model (their training reports lie beside them).
SELECTOR_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "selectors")
DEFAULT_SELECTOR = os.path.join(SELECTOR_DIR, "selection_error.json")
DEFAULT_PLANE_SELECTOR = os.path.join(SELECTOR_DIR, "selection_planes.json")

FEATURES = ("position",) + tuple(f"n_{o}" for o in ORGANS)
#: The second model's features (sagittal and coronal slices): organ particle counts only, as the paper's.
COUNT_FEATURES = tuple(f"n_{o}" for o in ORGANS)
#: Targets where a larger value is better.
HIGHER_IS_BETTER = ("dice", "dice_rank")


def raw_features(slice_index: int, counts_on_slice: dict[str, int], combination: str, features=FEATURES) -> list[float]:
    """Unstandardised features of one condition, in the order of ``features``."""
    organs = parse_organs(combination)
    counts = [float(counts_on_slice.get(o, 0)) if o in organs else 0.0 for o in ORGANS]
    return ([float(slice_index)] if "position" in features else []) + counts


def standardise(X: np.ndarray) -> np.ndarray:
    """Column z-scores within one case (constant columns become 0)."""
    X = np.asarray(X, dtype=np.float64)
    sd = X.std(axis=0)
    return (X - X.mean(axis=0)) / np.where(sd > 0, sd, 1.0)


def candidates(model: ParticleModel, orientations=("axial",), combinations=COMBINATIONS,
               features=FEATURES) -> tuple[list[tuple], np.ndarray]:
    """Every (orientation, slice, combination) whose slice holds pancreas particles, with standardised features.

    ``model`` must hold every organ that a combination names (build it with ``"psdl"``). Features are
    standardised per orientation over the candidate rows, as in :meth:`TrainingTable.from_sweep`, so
    ``combinations`` must be the ones the model was trained with.
    """
    keys, rows = [], []
    for orientation in orientations:
        counts = model.slice_counts(orientation)
        pan = counts[:, model.organs.index("pancreas")]
        block = []
        for k in np.nonzero(pan > 0)[0]:
            on = {o: int(counts[k, i]) for i, o in enumerate(model.organs)}
            for combo in combinations:
                if not set(parse_organs(combo)) <= set(model.organs):
                    continue
                keys.append((orientation, int(k), combo))
                block.append(raw_features(int(k), on, combo, features))
        if block:
            rows.append(standardise(np.asarray(block)))
    if not rows:
        raise InputError("no candidate slice holds pancreas particles")
    return keys, np.vstack(rows)


def r2_score(y: np.ndarray, pred: np.ndarray) -> float:
    y = np.asarray(y, dtype=np.float64)
    ss = np.sum((y - y.mean()) ** 2)
    return float(1.0 - np.sum((y - pred) ** 2) / ss) if ss > 0 else float("nan")


def rmse(y, pred) -> float:
    return float(np.sqrt(np.mean((np.asarray(y) - np.asarray(pred)) ** 2)))


@dataclass
class TrainingTable:
    """Features, target and case of every condition (from a sweep, averaged over deformations).

    ``value`` is the mean of the measured metric (equal to ``y`` except for ``dice_rank``, where ``y``
    is the within-(case, orientation) rank of ``value``); regret is computed on ``value``.
    """

    X: np.ndarray
    y: np.ndarray
    cases: np.ndarray
    keys: list[tuple]
    target: str
    features: tuple = FEATURES
    value: np.ndarray | None = None

    @property
    def groups(self) -> np.ndarray:
        """(case, orientation) of every row as one string: the unit of standardisation, ranking and regret."""
        return _group_labels(self.keys)

    @staticmethod
    def from_sweep(rows: list[dict], target: str = "error_mm", orientations=None, combinations=None,
                   complete_only: bool = True) -> "TrainingTable":
        """Average the metric over deformations per (case, orientation, slice, combination); features
        from the per-organ slice counts the sweep recorded, standardised per (case, orientation).

        ``target``: ``error_mm`` or ``dice`` (the paper's first model: slice position and counts), or
        ``dice_rank`` (its second model, for sagittal and coronal slices: counts only; the target is the
        percentile rank of the mean Dice among the slices of the same case and orientation, 1 = best).
        ``orientations`` / ``combinations``: keep only these rows. A condition with a failed
        simulation (non-finite metric) is left out whole. ``complete_only``: drop the cases
        where some condition has fewer deformations than the most complete condition (an interrupted
        sweep), so that every target is a mean over the same deformations.
        """
        if target not in ("error_mm", "dice", "dice_rank"):
            raise InputError(f"unknown selection target {target!r}; use error_mm, dice or dice_rank")
        features = COUNT_FEATURES if target == "dice_rank" else FEATURES
        metric = "dice" if target == "dice_rank" else target
        groups: dict[tuple, list] = {}
        feats: dict[tuple, list[float]] = {}
        failed: set[tuple] = set()
        for r in rows:
            if orientations is not None and r["orientation"] not in orientations:
                continue
            if combinations is not None and r["organs"] not in combinations:
                continue
            key = (r["case"], r["orientation"], int(float(r["slice"])), r["organs"])
            v = float(r[metric]) if r.get(metric) not in (None, "") else float("nan")
            if not np.isfinite(v):  # a simulation that failed (diverged): the condition is left out
                failed.add(key)
            groups.setdefault(key, []).append(v)
            counts = {o: int(float(r[f"count_{o}"])) for o in ORGANS}
            feats[key] = raw_features(int(float(r["slice"])), counts, r["organs"], features)
        groups = {k: v for k, v in groups.items() if k not in failed}
        if groups and complete_only:
            full = max(len(v) for v in groups.values())
            partial = {k[0] for k, v in groups.items() if len(v) < full}
            groups = {k: v for k, v in groups.items() if k[0] not in partial}
        if not groups:
            raise InputError("no sweep rows left for this table (check the orientations, combinations and completeness)")
        keys = sorted(groups)
        cases = np.array([k[0] for k in keys])
        X = np.asarray([feats[k] for k in keys], dtype=np.float64)
        value = np.array([np.mean(groups[k]) for k in keys])
        y = value.copy()
        unit = _group_labels(keys)
        for g in np.unique(unit):
            sel = unit == g
            X[sel] = standardise(X[sel])
            if target == "dice_rank":
                y[sel] = percentile_rank(value[sel])
        return TrainingTable(X, y, cases, keys, target, features, value)


def _group_labels(keys: list[tuple]) -> np.ndarray:
    return np.array([f"{k[0]}|{k[1]}" for k in keys])


def percentile_rank(v: np.ndarray) -> np.ndarray:
    """Rank of each value among ``v`` scaled to [0, 1] (0 = smallest, 1 = largest; ties share the mean rank)."""
    v = np.asarray(v, dtype=np.float64)
    if len(v) == 1:
        return np.ones(1)
    order = np.argsort(v, kind="stable")
    ranks = np.empty(len(v))
    ranks[order] = np.arange(len(v), dtype=np.float64)
    for u in np.unique(v):  # ties
        ranks[v == u] = ranks[v == u].mean()
    return ranks / (len(v) - 1)


def split_by_case(cases: np.ndarray, test_fraction: float = 0.2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Boolean train/test masks with no case on both sides (at least one case in each)."""
    uniq = np.unique(cases)
    if len(uniq) < 2:
        raise InputError("a split by case needs at least two cases")
    rng = np.random.default_rng(seed)
    n_test = max(1, int(round(test_fraction * len(uniq))))
    test_cases = rng.choice(uniq, n_test, replace=False)
    test = np.isin(cases, test_cases)
    return ~test, test


def split_by_row(n: int, test_fraction: float = 0.2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    test = np.zeros(n, dtype=bool)
    test[rng.choice(n, max(1, int(round(test_fraction * n))), replace=False)] = True
    return ~test, test


@dataclass
class ConditionSelector:
    """A trained regressor of a condition's accuracy from its standardised features (the paper's selection model)."""

    booster: object
    target: str
    params: dict = field(default_factory=dict)
    features: tuple = FEATURES
    combinations: tuple = COMBINATIONS
    orientations: tuple = ("axial",)

    def predict(self, X: np.ndarray) -> np.ndarray:
        return self.booster.inplace_predict(np.asarray(X, dtype=np.float32))

    @property
    def lower_is_better(self) -> bool:
        return self.target not in HIGHER_IS_BETTER

    def save(self, path: str) -> None:
        """``path`` (XGBoost JSON) and ``path + '.meta.json'`` (features, target, standardisation).

        Both are written beside their final names and renamed only when both are complete."""
        folder = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(folder):
            raise InputError(f"output folder {folder} for the selection model does not exist")
        tmp_model, tmp_meta = path + ".part.json", path + ".meta.part.json"  # XGBoost picks the format from ".json"
        self.booster.save_model(tmp_model)
        with open(tmp_meta, "w") as f:
            json.dump({"target": self.target, "features": list(self.features), "standardisation": "per-(case, orientation) z-score",
                       "combinations": list(self.combinations), "orientations": list(self.orientations),
                       "params": self.params}, f, indent=1)
        os.replace(tmp_model, path)
        os.replace(tmp_meta, path + ".meta.json")

    @staticmethod
    def load(path: str) -> "ConditionSelector":
        xgb = optional("xgboost", "a selection model (--slices auto)")

        if not os.path.exists(path) or not os.path.exists(path + ".meta.json"):
            raise InputError(f"selection model {path} (and its .meta.json) not found; train one with `warpmpm train`")
        fix = "give a model made by `warpmpm train` (the model file and its .meta.json beside it)"
        try:
            booster = xgb.Booster()
            booster.load_model(path)
            booster.set_param({"nthread": 1})  # ~100 candidate rows: threads cost more than they save
            with open(path + ".meta.json", encoding="utf-8") as f:
                meta = json.load(f)
            return ConditionSelector(booster, meta["target"], meta.get("params", {}), tuple(meta["features"]),
                                     tuple(meta.get("combinations", COMBINATIONS)), tuple(meta.get("orientations", ("axial",))))
        except (OSError, ValueError, KeyError, TypeError, AttributeError, xgb.core.XGBoostError) as exc:
            raise InputError(f"selection model {path} cannot be read ({type(exc).__name__}: {str(exc)[:120]}); {fix}") from None

    def rank(self, model: ParticleModel, orientations=None, combinations=None, k: int | None = 5):
        """Best conditions first: list of ((orientation, slice, combination), predicted value), and the time (s).

        Candidates are built (and standardised) over the combinations the model was trained with;
        ``combinations`` then keeps only those in the answer. ``k=None``: every candidate.
        """
        t0 = time.perf_counter()
        orientations = tuple(orientations or self.orientations)
        keys, X = candidates(model, orientations, self.combinations, self.features)
        pred = self.predict(X)
        order = np.argsort(pred if self.lower_is_better else -pred, kind="stable")
        if combinations is not None:
            order = [i for i in order if keys[i][2] in combinations]
        wall = time.perf_counter() - t0
        return [(keys[i], float(pred[i])) for i in list(order)[:k]], wall


def _xgb_train(params: dict, X, y, rounds: int, features=FEATURES):
    xgb = optional("xgboost", "training a selection model")

    d = xgb.DMatrix(np.asarray(X, dtype=np.float32), label=y, feature_names=list(features))
    return xgb.train({k: v for k, v in params.items()}, d, num_boost_round=rounds)


def _cv_r2(params, rounds, X, y, folds: int, seed: int, features=FEATURES) -> float:
    idx = np.random.default_rng(seed).permutation(len(y))
    scores = []
    for f in range(folds):
        test = idx[f::folds]
        train = np.setdiff1d(idx, test)
        b = _xgb_train(params, X[train], y[train], rounds, features)
        scores.append(r2_score(y[test], b.inplace_predict(np.asarray(X[test], dtype=np.float32))))
    return float(np.nanmean(scores))


def suggest_xgb_params(trial, seed: int, *, max_depth=(2, 8), min_child_weight=(1.0, 10.0), rounds=(50, 400),
                       nthread: int = 1) -> tuple[dict, int]:
    """An Optuna trial's XGBoost parameters (squared error; depth, learning rate, row and column sampling, child weight,
    L2) and boosting rounds, within the given ranges."""
    params = {"objective": "reg:squarederror", "max_depth": trial.suggest_int("max_depth", *max_depth),
              "eta": trial.suggest_float("eta", 0.01, 0.3, log=True), "subsample": trial.suggest_float("subsample", 0.5, 1.0),
              "colsample_bytree": trial.suggest_float("colsample_bytree", 0.5, 1.0),
              "min_child_weight": trial.suggest_float("min_child_weight", *min_child_weight),
              "lambda": trial.suggest_float("lambda", 1e-3, 10.0, log=True), "seed": seed, "nthread": nthread}
    return params, trial.suggest_int("rounds", *rounds)


def stop_when_stale(patience: int):
    """An Optuna callback that stops a study ``patience`` trials after its best."""
    def callback(study, trial):
        if trial.number - study.best_trial.number >= patience:
            study.stop()
    return callback


def tune_and_train(table: TrainingTable, *, split: str = "case", patience: int = 100, max_trials: int = 1000, folds: int = 5,
                   storage: str | None = None, study_name: str = "warpmpm-selection", seed: int = 0,
                   test_fraction: float = 0.2, test_cases=None) -> tuple[ConditionSelector, dict]:
    """Tune XGBoost with Optuna (5-fold CV mean R2 on the training rows), train on them, report.

    ``split``: ``case`` (no case on both sides; the honest one) or ``row`` (the paper's random rows).
    ``test_cases``: with ``split="case"``, hold out exactly these cases instead of a random 20 %.
    Stops after ``patience`` trials without a better mean R2 (or ``max_trials``). ``storage``: an
    Optuna storage URL such as ``sqlite:///selection.db``; an existing study of that name resumes.
    """
    optuna = optional("optuna", "tuning a selection model")

    if split == "case" and test_cases is not None:
        test = np.isin(table.cases, list(test_cases))
        if not test.any() or test.all():
            raise InputError(f"test cases {sorted(test_cases)} leave no rows on one side of the split")
        train = ~test
    elif split == "case":
        train, test = split_by_case(table.cases, test_fraction, seed)
    elif split == "row":
        train, test = split_by_row(len(table.y), test_fraction, seed)
    else:
        raise InputError(f"unknown split {split!r}; use case or row")
    Xtr, ytr = table.X[train], table.y[train]
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="maximize", storage=storage, study_name=study_name, load_if_exists=storage is not None,
                                sampler=optuna.samplers.TPESampler(seed=seed))

    def objective(trial):
        params, rounds = suggest_xgb_params(trial, seed)
        return _cv_r2(params, rounds, Xtr, ytr, folds, seed, table.features)

    done_before = len(study.trials)
    t0 = time.perf_counter()
    study.optimize(objective, n_trials=max(0, max_trials - done_before), callbacks=[stop_when_stale(patience)])
    tuning_s = time.perf_counter() - t0
    bp = dict(study.best_params)
    rounds = bp.pop("rounds")
    params = {"objective": "reg:squarederror", "seed": seed, "nthread": 1, **bp}
    booster = _xgb_train(params, Xtr, ytr, rounds, table.features)
    orientations = tuple(sorted({k[1] for k in table.keys}))
    combos = tuple(c for c in COMBINATIONS if c in {k[3] for k in table.keys})
    model = ConditionSelector(booster, table.target, {**params, "rounds": rounds}, tuple(table.features), combos, orientations)
    ptr, pte = model.predict(Xtr), model.predict(table.X[test])
    gain = booster.get_score(importance_type="gain")
    total = sum(gain.values()) or 1.0
    report = {"target": table.target, "split": split, "n_train": int(train.sum()), "n_test": int(test.sum()),
              "n_cases": int(len(np.unique(table.cases))), "trials": len(study.trials), "tuning_s": tuning_s,
              "best_cv_r2": float(study.best_value), "train_r2": r2_score(ytr, ptr), "train_rmse": rmse(ytr, ptr),
              "test_r2": r2_score(table.y[test], pte), "test_rmse": rmse(table.y[test], pte),
              "importance": {f: gain.get(f, 0.0) / total for f in table.features},
              "test_cases": sorted(set(table.cases[test])) if split == "case" else None}
    report |= within_group_scores(table, pte, test)
    model.test_mask = test
    return model, report


def within_group_scores(table: TrainingTable, pred: np.ndarray, mask: np.ndarray) -> dict:
    """How well ``pred`` (for the rows in ``mask``) orders conditions WITHIN each (case, orientation):
    the R2 after removing each group's mean from target and prediction (features are standardised
    per case, so a case's overall level cannot be predicted and does not matter for choosing), and
    the mean Spearman rank correlation over the groups."""
    y, groups = table.y[mask], table.groups[mask]
    yc, pc, rho = y.astype(np.float64).copy(), np.asarray(pred, dtype=np.float64).copy(), []
    for g in np.unique(groups):
        sel = groups == g
        yc[sel] -= yc[sel].mean()
        pc[sel] -= pc[sel].mean()
        if sel.sum() > 2:
            a, b = percentile_rank(y[sel]), percentile_rank(pred[sel])
            if a.std() > 0 and b.std() > 0:
                rho.append(float(np.corrcoef(a, b)[0, 1]))
    return {"test_within_case_r2": r2_score(yc, pc), "test_spearman": float(np.mean(rho)) if rho else float("nan")}


def _regret_groups(table: TrainingTable, mask: np.ndarray | None):
    """(name, row mask, values) per (case, orientation) group in ``mask``; names are ``case`` when the
    table has one orientation, else ``case|orientation``."""
    mask = np.ones(len(table.y), dtype=bool) if mask is None else mask
    value = table.value if table.value is not None else table.y
    groups = table.groups
    one_orientation = len({k[1] for k in table.keys}) == 1
    for g in np.unique(groups[mask]):
        sel = mask & (groups == g)
        yield (g.split("|")[0] if one_orientation else g), sel, value[sel]


def _shortfall(table: TrainingTable, chosen: float, values: np.ndarray) -> float:
    """How much worse ``chosen`` is than the best of ``values`` (>= 0, in the metric's unit)."""
    return float(chosen - values.min()) if table.target not in HIGHER_IS_BETTER else float(values.max() - chosen)


def regret(table: TrainingTable, model: ConditionSelector, mask: np.ndarray | None = None, top: int = 1) -> dict[str, float]:
    """Per (case, orientation) group: how much worse the predicted-best condition is than the brute-force
    best, in the measured metric's unit (mm for error, Dice points for Dice; >= 0).

    ``top > 1``: the best of the ``top`` predicted conditions (the paper tries the top 3 sagittal and
    coronal slices). Groups are named ``case`` when the table has one orientation, else ``case|orientation``.
    """
    lower = table.target not in HIGHER_IS_BETTER
    out = {}
    for name, sel, v in _regret_groups(table, mask):
        pred = model.predict(table.X[sel])
        picked = v[np.argsort(pred if model.lower_is_better else -pred, kind="stable")[:top]]
        out[name] = _shortfall(table, picked.min() if lower else picked.max(), v)
    return out


def baseline_regret(table: TrainingTable, rule: str, mask: np.ndarray | None = None, combination: str = "psdl") -> dict[str, float]:
    """Regret of a choice made without the model, per (case, orientation) group, as :func:`regret`.

    ``rule``: ``random`` (the expected regret of a condition drawn at random), ``middle`` (the
    ``combination`` at the middle slice of the pancreas: the runner's default), ``max_pancreas``
    (the ``combination`` on the slice with the most pancreas particles).
    """
    if rule not in ("random", "middle", "max_pancreas"):
        raise InputError(f"unknown baseline rule {rule!r}; use random, middle or max_pancreas")
    combo = np.array([k[3] for k in table.keys])
    slices = np.array([k[2] for k in table.keys])
    n_pan = table.X[:, table.features.index("n_pancreas")]  # standardised within the group: same order as the counts
    out = {}
    for name, sel, v in _regret_groups(table, mask):
        if rule == "random":
            out[name] = _shortfall(table, v.mean(), v)
            continue
        own = sel[sel] & (combo[sel] == combination)
        if not own.any():
            continue
        if rule == "middle":
            ks = slices[sel][own]
            i = np.argmin(np.abs(ks - np.median(ks)))
        else:
            i = np.argmax(n_pan[sel][own])
        out[name] = _shortfall(table, v[own][i], v)
    return out
