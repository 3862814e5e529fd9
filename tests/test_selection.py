"""Issue 7: features, the regressor, save/load, and the Dask sweep path."""

import csv

import numpy as np
import pytest

from warpmpm.model import build_model
from warpmpm.runner import CaseConfig, sweep
from warpmpm.selection import FEATURES, SelectionModel, TrainingTable, candidates, regret, standardise, tune_and_train


def test_features_match_hand_counts(tiny_model):
    keys, X = candidates(tiny_model, ("axial",), ("p", "psd"))
    m = tiny_model
    raw = []
    for orientation, k, combo in keys:
        on = m.voxel_ijk[:, 2] == k
        row = [k]
        for organ in ("pancreas", "stomach", "duodenum", "left_kidney"):
            n = int(np.sum(on & m.organ_slice(organ)))
            row.append(n if organ[0] in combo else 0)
        raw.append(row)
    raw = np.array(raw, dtype=float)
    assert all(r[1] > 0 for r in raw)  # only slices with pancreas
    np.testing.assert_allclose(X, standardise(raw))
    assert X.shape[1] == len(FEATURES)


def synthetic_table(n_cases=10, seed=0):
    rng = np.random.default_rng(seed)
    rows = []
    for c in range(n_cases):
        for k in range(30):
            for combo in ("p", "ps", "psd", "psdl"):
                counts = {o: int(rng.integers(0, 400)) for o in ("pancreas", "stomach", "duodenum", "left_kidney")}
                counts["pancreas"] += 1
                err = 2.0 + 0.01 * counts["pancreas"] - 0.004 * counts["stomach"] * ("s" in combo) + 0.1 * abs(k - 15) / 3
                rows.append({"case": f"c{c}", "orientation": "axial", "slice": k, "organs": combo, "deformation": 1,
                             "error_mm": err, **{f"count_{o}": v for o, v in counts.items()}})
    return rows


def test_regressor_recovers_known_relation_and_roundtrips(tmp_path):
    table = TrainingTable.from_sweep(synthetic_table())
    model, rep = tune_and_train(table, split="case", patience=5, max_trials=12, storage=f"sqlite:///{tmp_path}/s.db")
    assert rep["test_r2"] > 0.9 and rep["n_test"] > 0
    assert set(rep["test_cases"]).isdisjoint(set(table.cases[~model.test_mask]))
    path = str(tmp_path / "m.json")
    model.save(path)
    back = SelectionModel.load(path)
    np.testing.assert_array_equal(model.predict(table.X), back.predict(table.X))
    r = regret(table, model, model.test_mask)
    assert all(v >= 0 for v in r.values())
    # the study resumes from SQLite
    _, rep2 = tune_and_train(table, split="case", patience=5, max_trials=14, storage=f"sqlite:///{tmp_path}/s.db")
    assert rep2["trials"] >= rep["trials"]


def test_rank_is_fast_and_ordered(tiny_case):
    table = TrainingTable.from_sweep(synthetic_table(4))
    model, _ = tune_and_train(table, split="row", patience=3, max_trials=5)
    full = build_model(tiny_case, "psdl")
    ranked, wall = model.rank(full, k=5)
    preds = [p for _, p in ranked]
    assert preds == sorted(preds) and len(ranked) == 5
    assert wall < 1.0


def test_dask_sweep_matches_local_pool(tmp_path):
    pytest.importorskip("distributed")
    kw = dict(deformations=[1], combinations=("p",), orientations=("axial",), slice_stride=3,
              base=CaseConfig(phantom_resolution=3.0, device="cpu", max_steps=400), progress=None)
    cases = [{"name": "tiny", "phantom_seed": 0}]
    local = sweep(cases, out_csv=str(tmp_path / "a.csv"), workers=2, **kw)
    dask = sweep(cases, out_csv=str(tmp_path / "b.csv"), scheduler="local", workers=1, **kw)
    assert len(local) == len(dask) >= 2
    key = lambda r: (r["organs"], r["slice"])  # noqa: E731
    for a, b in zip(sorted(local, key=key), sorted(dask, key=key)):
        assert a["slice"] == b["slice"] and float(a["error_mm"]) == pytest.approx(float(b["error_mm"]), abs=1e-9)
    # resumable: a re-run adds nothing
    again = sweep(cases, out_csv=str(tmp_path / "a.csv"), workers=1, **kw)
    assert len(again) == len(local)
    with open(tmp_path / "a.csv") as f:
        assert len(list(csv.DictReader(f))) == len(local)
