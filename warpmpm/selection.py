"""Choosing the driving slice and organ combination: the condition-selection regression.

Rows are conditions (case, orientation, slice, combination). Features, as the paper's: the slice
position and, per organ, the number of its particles on that slice (0 when the organ is not in the
combination), each standardised per case (z-score over that case's candidate rows). The target is
the estimate's error (or Dice) averaged over the 8 paper deformations, from a brute-force sweep.

An XGBoost regressor (native API) is tuned by Optuna with 5-fold cross-validation, stopping after
``patience`` trials without a better mean R2; the study can live in SQLite so tuning resumes or is
shared. The model saves as XGBoost JSON plus a small JSON of its feature definition.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from .images import ORGANS, InputError, parse_organs
from .model import ParticleModel

COMBINATIONS = ("p", "ps", "pd", "pl", "psd", "psl", "pdl", "psdl")
FEATURES = ("position",) + tuple(f"n_{o}" for o in ORGANS)


def raw_features(slice_index: int, counts_on_slice: dict[str, int], combination: str) -> list[float]:
    """Unstandardised features of one condition."""
    organs = parse_organs(combination)
    return [float(slice_index)] + [float(counts_on_slice.get(o, 0)) if o in organs else 0.0 for o in ORGANS]


def standardise(X: np.ndarray) -> np.ndarray:
    """Column z-scores within one case (constant columns become 0)."""
    X = np.asarray(X, dtype=np.float64)
    sd = X.std(axis=0)
    return (X - X.mean(axis=0)) / np.where(sd > 0, sd, 1.0)


def candidates(model: ParticleModel, orientations=("axial",), combinations=COMBINATIONS) -> tuple[list[tuple], np.ndarray]:
    """Every (orientation, slice, combination) whose slice holds pancreas particles, with standardised features.

    ``model`` must hold every organ that a combination names (build it with ``"psdl"``).
    """
    keys, rows = [], []
    for orientation in orientations:
        counts = model.slice_counts(orientation)
        pan = counts[:, model.organs.index("pancreas")]
        for k in np.nonzero(pan > 0)[0]:
            on = {o: int(counts[k, i]) for i, o in enumerate(model.organs)}
            for combo in combinations:
                if not set(parse_organs(combo)) <= set(model.organs):
                    continue
                keys.append((orientation, int(k), combo))
                rows.append(raw_features(int(k), on, combo))
    if not rows:
        raise InputError("no candidate slice holds pancreas particles")
    return keys, standardise(np.asarray(rows))


def r2_score(y: np.ndarray, pred: np.ndarray) -> float:
    y = np.asarray(y, dtype=np.float64)
    ss = np.sum((y - y.mean()) ** 2)
    return float(1.0 - np.sum((y - pred) ** 2) / ss) if ss > 0 else float("nan")


def rmse(y, pred) -> float:
    return float(np.sqrt(np.mean((np.asarray(y) - np.asarray(pred)) ** 2)))


@dataclass
class TrainingTable:
    """Features, target and case of every condition (from a sweep, averaged over deformations)."""

    X: np.ndarray
    y: np.ndarray
    cases: np.ndarray
    keys: list[tuple]
    target: str

    @staticmethod
    def from_sweep(rows: list[dict], target: str = "error_mm") -> "TrainingTable":
        """Average ``target`` over deformations per (case, orientation, slice, combination); features
        from the per-organ slice counts the sweep recorded, standardised per case."""
        groups: dict[tuple, list] = {}
        feats: dict[tuple, list[float]] = {}
        for r in rows:
            key = (r["case"], r["orientation"], int(float(r["slice"])), r["organs"])
            groups.setdefault(key, []).append(float(r[target]))
            counts = {o: int(float(r[f"count_{o}"])) for o in ORGANS}
            feats[key] = raw_features(int(float(r["slice"])), counts, r["organs"])
        keys = sorted(groups)
        cases = np.array([k[0] for k in keys])
        X = np.asarray([feats[k] for k in keys], dtype=np.float64)
        for c in np.unique(cases):
            X[cases == c] = standardise(X[cases == c])
        y = np.array([np.mean(groups[k]) for k in keys])
        return TrainingTable(X, y, cases, keys, target)


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
class SelectionModel:
    """A trained regressor of a condition's accuracy from its standardised features."""

    booster: object
    target: str
    params: dict = field(default_factory=dict)
    features: tuple = FEATURES

    def predict(self, X: np.ndarray) -> np.ndarray:
        return self.booster.inplace_predict(np.asarray(X, dtype=np.float32))

    @property
    def lower_is_better(self) -> bool:
        return self.target != "dice"

    def save(self, path: str) -> None:
        """``path`` (XGBoost JSON) and ``path + '.meta.json'`` (features, target, standardisation)."""
        self.booster.save_model(path)
        with open(path + ".meta.json", "w") as f:
            json.dump({"target": self.target, "features": list(self.features), "standardisation": "per-case z-score",
                       "params": self.params}, f, indent=1)

    @staticmethod
    def load(path: str) -> "SelectionModel":
        import xgboost as xgb

        if not os.path.exists(path) or not os.path.exists(path + ".meta.json"):
            raise InputError(f"selection model {path} (and its .meta.json) not found; train one with examples/train_selection.py")
        booster = xgb.Booster()
        booster.load_model(path)
        booster.set_param({"nthread": 1})  # ~100 candidate rows: threads cost more than they save
        with open(path + ".meta.json") as f:
            meta = json.load(f)
        return SelectionModel(booster, meta["target"], meta.get("params", {}), tuple(meta["features"]))

    def rank(self, model: ParticleModel, orientations=("axial",), combinations=COMBINATIONS, k: int = 5):
        """Best conditions first: list of ((orientation, slice, combination), predicted value), and the time (s)."""
        t0 = time.perf_counter()
        keys, X = candidates(model, orientations, combinations)
        pred = self.predict(X)
        order = np.argsort(pred if self.lower_is_better else -pred)
        wall = time.perf_counter() - t0
        return [(keys[i], float(pred[i])) for i in order[:k]], wall


def _xgb_train(params: dict, X, y, rounds: int):
    import xgboost as xgb

    d = xgb.DMatrix(np.asarray(X, dtype=np.float32), label=y, feature_names=list(FEATURES))
    return xgb.train({k: v for k, v in params.items()}, d, num_boost_round=rounds)


def _cv_r2(params, rounds, X, y, folds: int, seed: int) -> float:
    import xgboost as xgb

    idx = np.random.default_rng(seed).permutation(len(y))
    scores = []
    for f in range(folds):
        test = idx[f::folds]
        train = np.setdiff1d(idx, test)
        b = _xgb_train(params, X[train], y[train], rounds)
        scores.append(r2_score(y[test], b.predict(xgb.DMatrix(np.asarray(X[test], dtype=np.float32), feature_names=list(FEATURES)))))
    return float(np.nanmean(scores))


def tune_and_train(table: TrainingTable, *, split: str = "case", patience: int = 100, max_trials: int = 1000, folds: int = 5,
                   storage: str | None = None, study_name: str = "warpmpm-selection", seed: int = 0,
                   test_fraction: float = 0.2) -> tuple[SelectionModel, dict]:
    """Tune XGBoost with Optuna (5-fold CV mean R2 on the training rows), train on them, report.

    ``split``: ``case`` (no case on both sides; the honest one) or ``row`` (the paper's random rows).
    Stops after ``patience`` trials without a better mean R2 (or ``max_trials``). ``storage``: an
    Optuna storage URL such as ``sqlite:///selection.db``; an existing study of that name resumes.
    """
    import optuna

    train, test = split_by_case(table.cases, test_fraction, seed) if split == "case" else split_by_row(len(table.y), test_fraction, seed)
    Xtr, ytr = table.X[train], table.y[train]
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="maximize", storage=storage, study_name=study_name, load_if_exists=storage is not None,
                                sampler=optuna.samplers.TPESampler(seed=seed))

    def objective(trial):
        params = {"objective": "reg:squarederror", "max_depth": trial.suggest_int("max_depth", 2, 8),
                  "eta": trial.suggest_float("eta", 0.01, 0.3, log=True), "subsample": trial.suggest_float("subsample", 0.5, 1.0),
                  "colsample_bytree": trial.suggest_float("colsample_bytree", 0.5, 1.0),
                  "min_child_weight": trial.suggest_float("min_child_weight", 1.0, 10.0),
                  "lambda": trial.suggest_float("lambda", 1e-3, 10.0, log=True), "seed": seed, "nthread": 1}
        rounds = trial.suggest_int("rounds", 50, 400)
        return _cv_r2(params, rounds, Xtr, ytr, folds, seed)

    def stop_when_stale(study, trial):
        best = study.best_trial.number
        if trial.number - best >= patience:
            study.stop()

    done_before = len(study.trials)
    study.optimize(objective, n_trials=max(0, max_trials - done_before), callbacks=[stop_when_stale])
    bp = dict(study.best_params)
    rounds = bp.pop("rounds")
    params = {"objective": "reg:squarederror", "seed": seed, "nthread": 1, **bp}
    booster = _xgb_train(params, Xtr, ytr, rounds)
    model = SelectionModel(booster, table.target, {**params, "rounds": rounds})
    ptr, pte = model.predict(Xtr), model.predict(table.X[test])
    gain = booster.get_score(importance_type="gain")
    total = sum(gain.values()) or 1.0
    report = {"split": split, "n_train": int(train.sum()), "n_test": int(test.sum()), "trials": len(study.trials),
              "best_cv_r2": float(study.best_value), "train_r2": r2_score(ytr, ptr), "train_rmse": rmse(ytr, ptr),
              "test_r2": r2_score(table.y[test], pte), "test_rmse": rmse(table.y[test], pte),
              "importance": {f: gain.get(f, 0.0) / total for f in FEATURES},
              "test_cases": sorted(set(table.cases[test])) if split == "case" else None}
    model.test_mask = test
    return model, report


def regret(table: TrainingTable, model: SelectionModel, mask: np.ndarray | None = None) -> dict[str, float]:
    """Per case: true target of the predicted-best condition minus the brute-force best (>= 0, in the target's unit)."""
    mask = np.ones(len(table.y), dtype=bool) if mask is None else mask
    out = {}
    for c in np.unique(table.cases[mask]):
        sel = mask & (table.cases == c)
        pred = model.predict(table.X[sel])
        y = table.y[sel]
        if model.lower_is_better:
            out[str(c)] = float(y[np.argmin(pred)] - y.min())
        else:
            out[str(c)] = float(y.max() - y[np.argmax(pred)])
    return out
