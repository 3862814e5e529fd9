"""Where to place the cine planes: a regression of each organ's estimate error on what the planes show.

A *placement* is one sagittal plane (MRIdian-like) or a sagittal and a coronal plane (Unity-like), each a voxel slice
of the planning volume. Before treatment a user knows, for every placement, what each organ shows on the planes; the
:class:`PlacementModel` predicts from that how much of each organ's motion the estimate will miss, so the placements
can be ranked (``warpmpm plan-planes``).

Features of a placement (:data:`FEATURES`), all computed from the planning scan's particle model
(:func:`placement_features`), per organ:

* ``<organ>_section_sagittal`` / ``_coronal``: how much of the organ the plane shows, as its particles on the plane
  over those on the organ's largest section of that orientation (0: the plane misses it or there is no such plane;
  1: the plane cuts its largest section);
* ``<organ>_position_sagittal`` / ``_coronal``: where the plane cuts the organ, as the signed distance from the organ's
  centroid along the world axis (LPS: sagittal + toward the patient's left, coronal + toward the posterior) over the
  organ's half-extent along it (0 at the centroid, +-1 at its edges; missing without such a plane);
* ``<organ>_distance_to_planes_mm``: the distance from its centroid to the nearest plane;

and ``n_planes`` (1 or 2). Particle counts and fractions of the organ are left out on purpose: they scale with the
voxel size, the sampling step and the slice thickness, which differ between the cases a model is trained on and the
scan it is used on; sections relative to the organ's largest and positions relative to its extent do not.

Target (per organ): the fraction of the organ's motion the estimate misses,
``r = error(estimate) / error(no motion)`` (both mean particle errors in mm, on a finite-element truth,
:mod:`warpmpm.experiment.plane_sweep`). It does not depend on how far the patient breathes, which a planning scan does
not tell; a predicted error in mm is ``r`` times the organ's expected motion.

The model is one XGBoost regressor per organ, tuned by Optuna on cross-validation folds that never split a case
(:func:`train_placement_model`), saved as one JSON file holding the boosters and what they were trained on.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError, optional
from .images import ORGANS
from .model import ParticleModel
from .slices import DrivingSlice, orientation_image_axis

__all__ = ["FAMILIES", "ORIENTATIONS", "FEATURES", "ORGAN_INPUTS", "MONOTONE", "organ_inputs", "pancreas_slices", "is_rule", "DEFAULT_PLACEMENT_MODEL", "Placement", "enumerate_placements", "placement_features",
           "PlacementModel", "PlacementTable", "train_placement_model", "placement_regret", "draw_placements"]

#: placement families: one sagittal plane, or a sagittal and a coronal plane
FAMILIES = ("sagittal", "sagittal+coronal")
ORIENTATIONS = ("sagittal", "coronal")
FEATURES = ("n_planes",) + tuple(f"{o}_{k}" for o in ORGANS for k in ("section_sagittal", "section_coronal", "position_sagittal",
                                                                      "position_coronal", "distance_to_planes_mm"))
#: what each organ's regressor reads of a placement: how much of that organ each plane shows, how far from its centroid
#: each plane cuts it (|position|, in half-extents; a plane the placement lacks counts as far away) and the planes' count
ORGAN_INPUTS = ("section_sagittal", "section_coronal", "abs_position_sagittal", "abs_position_coronal", "n_planes")
#: the monotone constraints on them: more of the organ shown, or a second plane, never predicts a larger error; a plane
#: further from the organ's centroid never a smaller one (what keeps a model trained on few cases physical)
MONOTONE = (-1, -1, 1, 1, -1)
_FAR = 10.0  # |position| of a plane the placement lacks (half-extents)
#: the model shipped with the package (trained on the finite-element plane sweep; its report lies beside it)
DEFAULT_PLACEMENT_MODEL = os.path.join(os.path.dirname(os.path.abspath(__file__)), "selectors", "plane_placement.json")
_AXIS = {"sagittal": 0, "coronal": 1}  # the world (LPS) axis each plane's normal is signed along


@dataclass(frozen=True)
class Placement:
    """Cine planes of one placement: ``family`` and its slices (indices of the model's volume)."""

    family: str
    slices: tuple

    def label(self, to_input=None) -> str:
        """``"sagittal:40,coronal:62"``; ``to_input`` maps a slice to the input volume's indices (what users type)."""
        return ",".join(str(to_input(s) if to_input else s) for s in self.slices)


def _plane_geometry(model: ParticleModel, orientation: str):
    """(image axis, world unit normal signed along the orientation's world axis, per-slice plane coordinate along it
    in mm (nan where the slice holds no particle))."""
    axis = orientation_image_axis(model.geometry, orientation)
    normal = np.asarray(model.geometry.axis_world_direction(axis), dtype=np.float64)
    normal = normal / np.linalg.norm(normal)
    w = _AXIS[orientation]
    if normal[w] < 0:
        normal = -normal
    k = model.voxel_ijk[:, axis].astype(np.int64)
    size = model.geometry.size[axis]
    counts = np.bincount(k, minlength=size)
    coord = np.bincount(k, weights=model.positions_mm @ normal, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        coord = np.where(counts > 0, coord / np.maximum(counts, 1), np.nan)
    return axis, normal, coord


def pancreas_slices(model: ParticleModel, orientation: str, n_positions: int | None = None, stride: int = 1) -> list[int]:
    """Slices of ``orientation`` that cut the pancreas, the one with the most pancreas first (the rule without a
    model), then every ``stride``-th such slice or, with ``n_positions``, that many spread evenly over them (with a
    sampling step some slices hold no particle: the positions are drawn among those that do)."""
    counts = model.slice_counts(orientation)[:, model.organs.index("pancreas")]
    on = np.nonzero(counts > 0)[0]
    best = int(np.argmax(counts))
    if n_positions is not None:
        on = np.unique(on[np.round(np.linspace(0, len(on) - 1, max(int(n_positions), 1))).astype(int)])
    else:
        on = on[::int(stride)]
    return [best] + [int(k) for k in on if k != best]


def is_rule(row: dict) -> bool:
    """Whether a plane-sweep row (a CSV row or a fresh one) is its family's rule placement."""
    return str(row["rule"]) in ("True", "true", "1")


def enumerate_placements(model: ParticleModel, families=FAMILIES, stride: int = 1) -> list[Placement]:
    """Every placement whose planes each cut the pancreas (every ``stride``-th such slice); each family's first
    placement is the rule without a model (every plane where it shows the most pancreas)."""
    for f in families:
        if f not in FAMILIES:
            raise InputError(f"plane family {f!r}: use one of {', '.join(FAMILIES)}")
    if "pancreas" not in model.organs:
        raise InputError("choosing the planes needs the pancreas in the planning labels")
    if int(stride) < 1:
        raise InputError(f"the slice stride must be >= 1, got {stride}")
    picks = {o: pancreas_slices(model, o, stride=stride) for o in ORIENTATIONS}
    out = []
    for f in families:
        if f == "sagittal":
            out += [Placement(f, (DrivingSlice("sagittal", k),)) for k in picks["sagittal"]]
        else:
            out += [Placement(f, (DrivingSlice("sagittal", s), DrivingSlice("coronal", c)))
                    for s in picks["sagittal"] for c in picks["coronal"]]
    return out


def placement_features(model: ParticleModel, placements: list[Placement]) -> np.ndarray:
    """(n_placements, len(FEATURES)) features of the placements (module docstring; NaN marks a plane the placement
    does not have); vectorised over placements: one pass over the particles, then array look-ups."""
    if not placements:
        raise InputError("no placement to describe")
    if "pancreas" not in model.organs:
        raise InputError("the placement features need the pancreas in the model")
    n_org = len(model.organs)
    org = model.organ_index.astype(np.int64)
    size_org = np.bincount(org, minlength=n_org)
    if np.any(size_org == 0):
        raise InputError(f"the planning model holds no particle of {', '.join(np.array(model.organs)[size_org == 0])}")
    centroid = np.stack([model.positions_mm[org == i].mean(0) for i in range(n_org)])
    geo = {o: _plane_geometry(model, o) for o in ORIENTATIONS}
    idx = {o: np.full(len(placements), -1) for o in ORIENTATIONS}
    for r, p in enumerate(placements):
        for sl in p.slices:
            if sl.orientation not in geo:
                raise InputError(f"placements are sagittal and coronal planes, not {sl.orientation}")
            coord = geo[sl.orientation][2]
            if not (0 <= sl.index < len(coord)) or not np.isfinite(coord[sl.index]):
                raise InputError(f"{sl} holds no particle of the planning model")
            idx[sl.orientation][r] = sl.index
    X = np.zeros((len(placements), len(FEATURES)))
    col = {f: i for i, f in enumerate(FEATURES)}
    dist = np.full((len(placements), n_org), np.inf)
    for o in ORIENTATIONS:
        _, normal, coord = geo[o]
        counts = model.slice_counts(o).astype(np.float64)
        largest = counts.max(axis=0)
        along = model.positions_mm @ normal
        lo = np.array([along[org == i].min() for i in range(n_org)])
        hi = np.array([along[org == i].max() for i in range(n_org)])
        half = np.maximum(0.5 * (hi - lo), 1e-6)
        has = idx[o] >= 0
        k = idx[o][has]
        dist[has] = np.minimum(dist[has], np.abs((centroid @ normal)[None, :] - coord[k][:, None]))
        for i, name in enumerate(model.organs):
            if name not in ORGANS:
                continue
            sec = np.zeros(len(placements))
            sec[has] = counts[k, i] / largest[i]
            pos = np.full(len(placements), np.nan)
            pos[has] = (coord[k] - centroid[i] @ normal) / half[i]
            X[:, col[f"{name}_section_{o}"]] = sec
            X[:, col[f"{name}_position_{o}"]] = pos
    X[:, col["n_planes"]] = (idx["sagittal"] >= 0).astype(float) + (idx["coronal"] >= 0)
    for i, name in enumerate(model.organs):
        if name in ORGANS:
            X[:, col[f"{name}_distance_to_planes_mm"]] = dist[:, i]
    return X


@dataclass
class PlacementTable:
    """Sweep rows as features, per-organ targets (fraction of the motion missed) and groups."""

    X: np.ndarray
    missed: dict  #: organ -> (n,) fraction of the organ's motion the estimate misses
    error_mm: dict  #: organ -> (n,) the estimate's mean error (mm)
    motion_mm: dict  #: organ -> (n,) the organ's mean motion (mm): the error of no motion
    cases: np.ndarray
    groups: np.ndarray  #: case|truth seed|load|family: the placements one choice is made among
    rule: np.ndarray  #: the rule without a model (each plane where it shows the most pancreas)
    labels: list
    method: str = "copy"

    @staticmethod
    def from_sweep(rows: list[dict], method: str = "copy") -> "PlacementTable":
        """Rows of ``warpmpm sweep-planes`` (failed ones and organs without motion left out)."""
        keep = [r for r in rows if not r.get("failure") and all(r.get(f"{method}_{o}_mm") not in (None, "") for o in ORGANS)]
        if not keep:
            raise InputError(f"no usable sweep row for method {method!r} (every row failed or lacks its errors)")
        X = np.array([[_feature_value(r, f) for f in FEATURES] for r in keep], dtype=np.float64)
        err = {o: np.array([float(r[f"{method}_{o}_mm"]) for r in keep]) for o in ORGANS}
        mot = {o: np.array([float(r[f"initial_{o}_mm"]) for r in keep]) for o in ORGANS}
        missed = {o: err[o] / np.maximum(mot[o], 1e-6) for o in ORGANS}
        groups = np.array([f"{r['case']}|{r['truth_seed']}|{r['load']}|{r['family']}" for r in keep])
        rule = np.array([is_rule(r) for r in keep])
        return PlacementTable(X, missed, err, mot, np.array([r["case"] for r in keep]), groups, rule,
                              [r["planes"] for r in keep], method)


def _feature_value(row: dict, name: str) -> float:
    if name == "n_planes":
        return float(len(str(row["planes"]).split(",")))
    v = row.get(name)
    if v is None:
        raise InputError(f"the plane-sweep rows lack the feature column {name!r}: refresh them with "
                         "`warpmpm sweep-planes --refresh-features` (same case options)")
    return float(v) if v != "" else float("nan")


@dataclass
class PlacementModel:
    """Per-organ regressors of the fraction of the organ's motion the estimate misses (module docstring)."""

    boosters: dict
    method: str = "copy"
    features: tuple = FEATURES
    params: dict = field(default_factory=dict)
    trained_on: dict = field(default_factory=dict)

    @property
    def organs(self) -> tuple:
        return tuple(o for o in ORGANS if o in self.boosters)

    def predict(self, X: np.ndarray) -> dict:
        """organ -> (n,) predicted fraction of its motion missed, from placement features ``X`` (:data:`FEATURES`)."""
        return {o: np.exp(self.boosters[o].inplace_predict(organ_inputs(X, o))) for o in self.organs}

    def rank(self, model: ParticleModel, families=FAMILIES, rank_by=("pancreas",), stride: int = 1):
        """Placements best first by the mean predicted fraction missed over ``rank_by``: a list of
        (placement, features row, {organ: predicted fraction}), and the wall time (s) of enumerating, describing
        and predicting."""
        bad = [o for o in rank_by if o not in self.organs]
        if bad or not rank_by:
            raise InputError(f"rank by organs of the model ({', '.join(self.organs)}), not {', '.join(bad) or 'none'}")
        t0 = time.perf_counter()
        placements = enumerate_placements(model, families, stride)
        X = placement_features(model, placements)
        pred = self.predict(X)
        score = np.mean([pred[o] for o in rank_by], axis=0)
        order = np.argsort(score, kind="stable")
        wall = time.perf_counter() - t0
        return [(placements[i], X[i], {o: float(pred[o][i]) for o in self.organs}) for i in order], wall

    def save(self, path: str) -> None:
        """One JSON file (the boosters as XGBoost JSON inside it), written beside its name and renamed when whole."""
        folder = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(folder):
            raise InputError(f"output folder {folder} for the placement model does not exist")
        doc = {"kind": "warpmpm plane-placement model",
               "target": "natural log of the fraction of each organ's motion the estimate misses",
               "method": self.method, "features": list(self.features), "inputs": list(ORGAN_INPUTS),
               "monotone": list(MONOTONE), "params": self.params, "trained_on": self.trained_on,
               "boosters": {o: bytes(b.save_raw("json")).decode() for o, b in self.boosters.items()}}
        tmp = path + ".part"
        with open(tmp, "w") as f:
            json.dump(doc, f)
        os.replace(tmp, path)

    @staticmethod
    def load(path: str = DEFAULT_PLACEMENT_MODEL) -> "PlacementModel":
        xgb = optional("xgboost", "the plane-placement model (plan-planes --method model)")

        if not os.path.isfile(path):
            raise InputError(f"plane-placement model {path} not found (or not a file); train one with `warpmpm train-planes`")
        fix = "give a model made by `warpmpm train-planes`, or leave --model out for the shipped one"
        try:
            with open(path, encoding="utf-8") as f:
                doc = json.load(f)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"{path} is not a plane-placement model (not JSON: {exc}); {fix}") from None
        if not isinstance(doc, dict) or doc.get("kind") != "warpmpm plane-placement model":
            raise InputError(f"{path} is not a plane-placement model (made by `warpmpm train-planes`); {fix}")
        if tuple(doc.get("features", ())) != FEATURES or tuple(doc.get("inputs", ())) != ORGAN_INPUTS:
            raise InputError(f"{path} was trained on other features than this warpmpm computes; retrain it")
        boosters = {}
        try:
            for o, raw in doc["boosters"].items():
                b = xgb.Booster()
                b.load_model(bytearray(raw.encode()))
                b.set_param({"nthread": 1})
                boosters[o] = b
        except Exception as exc:  # noqa: BLE001 - a hand-edited or cut model: xgboost's own errors
            raise InputError(f"{path}: its boosters cannot be read ({type(exc).__name__}); {fix}") from None
        return PlacementModel(boosters, doc["method"], tuple(doc["features"]), doc.get("params", {}), doc.get("trained_on", {}))


def organ_inputs(X: np.ndarray, organ: str) -> np.ndarray:
    """(n, len(ORGAN_INPUTS)) what ``organ``'s regressor reads of placement features ``X``."""
    X = np.asarray(X, dtype=np.float64)
    col = {f: i for i, f in enumerate(FEATURES)}
    out = np.empty((len(X), len(ORGAN_INPUTS)), dtype=np.float32)
    for j, name in enumerate(ORGAN_INPUTS):
        if name.startswith("abs_"):
            v = np.abs(X[:, col[f"{organ}_{name[4:]}"]])
            out[:, j] = np.where(np.isfinite(v), np.minimum(v, _FAR), _FAR)
        elif name == "n_planes":
            out[:, j] = X[:, col["n_planes"]]
        else:
            out[:, j] = X[:, col[f"{organ}_{name}"]]
    return out


def _fit(params: dict, rounds: int, X, y):
    """One organ's regressor of the log fraction missed ``y`` on its inputs ``X`` (:func:`organ_inputs`)."""
    xgb = optional("xgboost", "training the plane-placement model")

    params = {**params, "monotone_constraints": "(" + ",".join(str(m) for m in MONOTONE) + ")"}
    return xgb.train(params, xgb.DMatrix(np.asarray(X, np.float32), label=y, feature_names=list(ORGAN_INPUTS)),
                     num_boost_round=int(rounds))


def _log_missed(table: "PlacementTable", organ: str) -> np.ndarray:
    return np.log(np.maximum(table.missed[organ], 1e-4))


def _group_folds(cases: np.ndarray, folds: int, seed: int):
    uniq = np.random.default_rng(seed).permutation(np.unique(cases))
    k = min(folds, len(uniq))
    return [np.isin(cases, uniq[f::k]) for f in range(k)]


def train_placement_model(table: PlacementTable, train: np.ndarray, *, organs=ORGANS, max_trials: int = 60,
                          patience: int = 20, folds: int = 5, storage: str | None = None, study_name: str = "plane-placement",
                          seed: int = 0) -> tuple[PlacementModel, dict]:
    """Tune (Optuna: the mean over organs of the R2 of the log fraction missed, on folds that never split a case, of
    the ``train`` rows) and train one regressor per organ with the tuned parameters (each on its own inputs,
    :data:`ORGAN_INPUTS`, under :data:`MONOTONE`). Returns the model and the tuning record."""
    import optuna

    from .selection import r2_score, stop_when_stale, suggest_xgb_params

    if len(np.unique(table.cases[train])) < 2:
        raise InputError("training the placement model needs at least two cases on the training side")
    X, cases = table.X[train], table.cases[train]
    fold_masks = _group_folds(cases, folds, seed)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="maximize", storage=storage, study_name=study_name,
                                load_if_exists=storage is not None, sampler=optuna.samplers.TPESampler(seed=seed))

    def objective(trial):
        params, rounds = suggest_xgb_params(trial, seed, max_depth=(1, 4), min_child_weight=(1.0, 20.0), rounds=(30, 400),
                                            nthread=2)
        scores = []
        for o in organs:  # the mean over organs and folds of the R2 of the log fraction missed
            Xo, y = organ_inputs(X, o), _log_missed(table, o)[train]
            for test in fold_masks:
                b = _fit(params, rounds, Xo[~test], y[~test])
                scores.append(r2_score(y[test], b.inplace_predict(Xo[test])))
        return float(np.nanmean(scores))

    t0 = time.perf_counter()
    study.optimize(objective, n_trials=max(0, max_trials - len(study.trials)), callbacks=[stop_when_stale(patience)])
    bp = dict(study.best_params)
    rounds = bp.pop("rounds")
    params = {"objective": "reg:squarederror", "seed": seed, "nthread": 2, **bp}
    boosters = {o: _fit(params, rounds, organ_inputs(X, o), _log_missed(table, o)[train]) for o in organs}
    model = PlacementModel(boosters, table.method, FEATURES, {**params, "rounds": rounds},
                           {"cases": sorted(set(cases.tolist())), "rows": int(train.sum())})
    return model, {"trials": len(study.trials), "tuning_s": time.perf_counter() - t0, "best_cv_r2": float(study.best_value),
                   "params": model.params}


def placement_regret(table: PlacementTable, predicted: dict, mask: np.ndarray, organs=("pancreas",)) -> dict:
    """Per group in ``mask`` (a case, truth, load and family: the placements one choice is made among), how much worse
    the placement chosen by the model (lowest mean predicted fraction missed over ``organs``), the rule without a model
    (each plane where it shows the most pancreas) and a placement drawn at random (expected) are than the best
    placement in hindsight, in mm of the mean error over ``organs``."""
    out = {}
    err_all = np.mean([table.error_mm[o] for o in organs], axis=0)
    score_all = np.mean([predicted[o] for o in organs], axis=0)
    for g in np.unique(table.groups[mask]):
        sel = np.nonzero(mask & (table.groups == g))[0]
        err, score = err_all[sel], score_all[sel]
        rule = sel[table.rule[sel]]
        out[g] = {"model": float(err[np.argmin(score)] - err.min()),
                  "rule": float(err_all[rule[0]] - err.min()) if len(rule) else float("nan"),
                  "random": float(err.mean() - err.min()), "best_mm": float(err.min()), "worst_mm": float(err.max()),
                  "n_placements": int(len(sel))}
    return out


_COLOURS = {"pancreas": "#d62728", "stomach": "#1f77b4", "duodenum": "#2ca02c", "left_kidney": "#9467bd"}


def draw_placements(model: ParticleModel, ranked: list, path: str, to_input=None, top: int = 3) -> None:
    """A PNG of the organs (particles projected on the axial and coronal planes, world mm, LPS) with the planes of the
    ``top`` ranked placements drawn over them (solid: the first; dashed: the next)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(f"output folder {folder} for the picture does not exist")
    x = model.positions_mm
    step = max(1, model.n // 40000)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    views = (("axial projection (x: R->L, y: A->P)", 0, 1), ("coronal projection (x: R->L, z: I->S)", 0, 2))
    for ax, (title, a, b) in zip(axes, views):
        for o in sorted(model.organs, key=lambda o: o == "pancreas"):  # the pancreas drawn last, over its neighbours
            sel = np.nonzero(model.organ_index == model.organs.index(o))[0][::step]
            ax.scatter(x[sel, a], x[sel, b], s=2, c=_COLOURS.get(o, "grey"), label=o, alpha=0.5, linewidths=0)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel(f"{'xyz'[a]} (mm)")
        ax.set_ylabel(f"{'xyz'[b]} (mm)")
        ax.set_aspect("equal")
        if b == 1:
            ax.invert_yaxis()  # anterior up
    for rank, (p, _, pred) in enumerate(ranked[:top]):
        style = "-" if rank == 0 else "--"
        for s in p.slices:
            axis = orientation_image_axis(model.geometry, s.orientation)
            ijk = np.zeros(3)
            ijk[axis] = s.index
            w = _AXIS[s.orientation]
            coord = {s.index: float(model.geometry.index_to_world(ijk[None, :])[0][w])}  # the slice's plane (mm)
            for ax, (_, a, b) in zip(axes, views):
                if w == a:
                    ax.axvline(coord[s.index], color="k", ls=style, lw=1.2 if rank == 0 else 0.8)
                elif w == b:
                    ax.axhline(coord[s.index], color="k", ls=style, lw=1.2 if rank == 0 else 0.8)
        axes[0].plot([], [], "k" + style, label=f"#{rank + 1} {p.label(to_input)}")
    axes[0].legend(fontsize=7, markerscale=6, loc="best")
    fig.tight_layout()
    tmp = path + ".part.png"
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)
