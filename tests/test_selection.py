"""Issue 7: features, the regressor, save/load, and the Dask sweep path."""

import csv
import os

import numpy as np
import pytest

from warpmpm.model import build_model
from warpmpm.experiment import CaseConfig
from warpmpm.experiment.sweep import sweep
from warpmpm.selection import FEATURES, ConditionSelector, TrainingTable, candidates, regret, standardise, tune_and_train


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
    back = ConditionSelector.load(path)
    np.testing.assert_array_equal(model.predict(table.X), back.predict(table.X))
    # choosing with the model beats choosing at random on the held-out cases (regret in mm)
    from warpmpm.selection import baseline_regret

    r = np.mean(list(regret(table, model, model.test_mask).values()))
    rand = np.mean(list(baseline_regret(table, "random", model.test_mask).values()))
    assert r < 0.25 * rand
    # the study resumes from SQLite: one more trial is appended to the stored ones, which are kept
    import optuna

    storage = f"sqlite:///{tmp_path}/s.db"
    before = [t.params for t in optuna.load_study(study_name="warpmpm-selection", storage=storage).trials]
    _, rep2 = tune_and_train(table, split="case", patience=1000, max_trials=rep["trials"] + 1, storage=storage)
    after = optuna.load_study(study_name="warpmpm-selection", storage=storage).trials
    assert len(before) == rep["trials"] and len(after) == rep2["trials"] == rep["trials"] + 1
    assert [t.params for t in after[: len(before)]] == before


def test_rank_is_fast_and_ordered(tiny_case):
    table = TrainingTable.from_sweep(synthetic_table(4))
    model, _ = tune_and_train(table, split="row", patience=3, max_trials=5)
    full = build_model(tiny_case, "psdl")
    ranked, wall = model.rank(full, k=5)
    preds = [p for _, p in ranked]
    assert preds == sorted(preds) and len(ranked) == 5
    assert wall < 1.0


def test_dask_sweep_matches_local_pool(tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    # the same threads a step in every worker of both schedulers (a step split over two threads adds the grid's sums in
    # another order: float32 rounding, tests/test_parallel.py), so the rows can be compared to the last digit
    monkeypatch.setenv("WARPMPM_CPU_THREADS", "1")
    kw = dict(deformations=[1], combinations=("p",), orientations=("axial",), slice_stride=3,
              base=CaseConfig(phantom_resolution=3.0, device="cpu", max_steps=400), progress=None)
    cases = [{"name": "tiny", "phantom_seed": 0}]
    local, failed = sweep(cases, out_csv=str(tmp_path / "a.csv"), workers=2, **kw)
    dask, _ = sweep(cases, out_csv=str(tmp_path / "b.csv"), scheduler="local", workers=1, **kw)
    assert len(local) == len(dask) >= 2 and not failed
    key = lambda r: (r["organs"], r["slice"])  # noqa: E731
    for a, b in zip(sorted(local, key=key), sorted(dask, key=key)):
        assert a["slice"] == b["slice"] and float(a["error_mm"]) == pytest.approx(float(b["error_mm"]), abs=1e-9)
    # resumable: a re-run adds nothing
    again, _ = sweep(cases, out_csv=str(tmp_path / "a.csv"), workers=1, **kw)
    assert len(again) == len(local)
    with open(tmp_path / "a.csv") as f:
        assert len(list(csv.DictReader(f))) == len(local)


def test_percentile_rank_known_values():
    from warpmpm.selection import percentile_rank

    np.testing.assert_allclose(percentile_rank(np.array([0.3, 0.9, 0.1, 0.5])), [1 / 3, 1.0, 0.0, 2 / 3])
    np.testing.assert_allclose(percentile_rank(np.array([0.2, 0.2, 0.8])), [0.25, 0.25, 1.0])  # ties share the mean rank


def synthetic_plane_table(n_cases=10, seed=1):
    """Sagittal/coronal psdl rows whose Dice rises with the pancreas count and falls with the stomach's."""
    rng = np.random.default_rng(seed)
    rows = []
    for c in range(n_cases):
        for orientation in ("sagittal", "coronal"):
            for k in range(25):
                counts = {o: int(rng.integers(0, 300)) for o in ("pancreas", "stomach", "duodenum", "left_kidney")}
                counts["pancreas"] += 1
                dice = 0.5 + 4e-4 * counts["pancreas"] - 2e-4 * counts["stomach"] + rng.normal(0, 0.003)
                for d in (1, 2):
                    rows.append({"case": f"c{c}", "orientation": orientation, "slice": k, "organs": "psdl", "deformation": d,
                                 "dice": dice, **{f"count_{o}": v for o, v in counts.items()}})
    return rows


def test_plane_ranker_learns_dice_rank_within_case(tmp_path):
    from warpmpm.selection import COUNT_FEATURES

    table = TrainingTable.from_sweep(synthetic_plane_table(), "dice_rank")
    assert table.features == COUNT_FEATURES and table.X.shape[1] == 4
    for g in np.unique(table.groups):  # the target is a rank within each (case, orientation)
        y = np.sort(table.y[table.groups == g])
        assert y[0] == 0.0 and y[-1] == 1.0
    model, rep = tune_and_train(table, split="case", patience=5, max_trials=12)
    assert rep["test_r2"] > 0.9 and not model.lower_is_better
    from warpmpm.selection import baseline_regret

    top1 = regret(table, model, model.test_mask, top=1)
    assert all("|" in k for k in top1)  # one group per case and orientation
    assert np.mean(list(top1.values())) < 0.05  # within 0.05 Dice of the brute-force best slice
    rand = np.mean(list(baseline_regret(table, "random", model.test_mask).values()))
    assert np.mean(list(top1.values())) < 0.5 * rand  # and far better than a slice at random
    path = str(tmp_path / "planes.json")
    model.save(path)
    back = ConditionSelector.load(path)
    assert back.features == COUNT_FEATURES and back.orientations == ("coronal", "sagittal") and back.combinations == ("psdl",)


def test_partial_cases_are_dropped():
    rows = [r for r in synthetic_plane_table(3) if not (r["case"] == "c1" and r["deformation"] == 2 and r["slice"] == 3)]
    table = TrainingTable.from_sweep(rows, "dice")
    assert set(table.cases) == {"c0", "c2"}
    assert len(set(TrainingTable.from_sweep(rows, "dice", complete_only=False).cases)) == 3


def test_multi_direction_protocol_on_tiny_phantom(tmp_path, tiny_case):
    """One (case, deformation) of the multi-direction protocol, with models trained on synthetic tables:
    more GT-driven directions must not make the estimate worse, and the driven particles are left out."""
    from warpmpm.experiment.multi_direction import multi_direction_task
    from warpmpm.experiment.tables import MULTI_CONDITIONS, summarize_multi

    ax, _ = tune_and_train(TrainingTable.from_sweep(synthetic_table(4)), split="row", patience=2, max_trials=3)
    pl, _ = tune_and_train(TrainingTable.from_sweep(synthetic_plane_table(4), "dice_rank"), split="row", patience=2, max_trials=3)
    ax.save(str(tmp_path / "ax.json"))
    pl.save(str(tmp_path / "pl.json"))
    rows = multi_direction_task({"name": "tiny", "phantom_seed": 0, "phantom_resolution": 3.0}, 1, str(tmp_path / "ax.json"),
                                str(tmp_path / "pl.json"), CaseConfig(device="cpu", max_steps=1500), top=1)
    by = {r["condition"]: r for r in rows if r["pick"] == "top1"}
    assert set(by) == set(MULTI_CONDITIONS)
    assert [len(by[c]["slices"].split(",")) for c in MULTI_CONDITIONS] == [1, 2, 2, 3]
    assert 0 < by["a"]["n_excluded_pancreas"] < by["asc"]["n_excluded_pancreas"]
    for c in ("ac", "as", "asc"):  # (one axial slice alone may do worse than no motion when the slice is poor)
        assert by[c]["error_mm"] < by[c]["initial_error_mm"]
    assert by["asc"]["error_mm"] < by["a"]["error_mm"]
    assert all(np.isfinite(r["volume_registration_error_mm"]) for r in rows)
    assert "axial + sagittal + coronal" in summarize_multi(rows)


def test_baseline_regret_by_hand():
    from warpmpm.selection import baseline_regret

    # one case, slices 0..4, two combinations; error = |k - 1| (+1 for "p"); the pancreas peaks on slice 3
    rows = []
    for k in range(5):
        for combo in ("p", "psdl"):
            counts = {"pancreas": 10 + 5 * (k == 3), "stomach": k, "duodenum": 1, "left_kidney": 1}
            rows.append({"case": "c", "orientation": "axial", "slice": k, "organs": combo, "deformation": 1,
                         "error_mm": abs(k - 1) + (combo == "p"), **{f"count_{o}": v for o, v in counts.items()}})
    table = TrainingTable.from_sweep(rows)
    assert baseline_regret(table, "middle") == {"c": 1.0}        # psdl on slice 2 vs psdl on slice 1
    assert baseline_regret(table, "max_pancreas") == {"c": 2.0}  # psdl on slice 3
    assert baseline_regret(table, "random")["c"] == pytest.approx(np.mean([abs(k - 1) + e for k in range(5) for e in (0, 1)]))


def test_run_case_slices_auto_uses_the_top_ranked_condition(tmp_path, capsys):
    import json

    from warpmpm.cli import run_main as main
    from warpmpm.experiment import CaseConfig as C
    from warpmpm.experiment import prepare_case

    model, _ = tune_and_train(TrainingTable.from_sweep(synthetic_table(4)), split="row", patience=2, max_trials=3)
    path = str(tmp_path / "sel.json")
    model.save(path)
    prep = prepare_case(C(phantom_resolution=3.0, particle_step=1, organs="p"))
    (orientation, k, combo), _ = model.rank(prep.full_model, k=1)[0][0]
    out_json = str(tmp_path / "out.json")
    rc = main(["--phantom-resolution", "3", "--particle-step", "1", "--slices", "auto", "--selector", path, "--device", "cpu",
               "--no-volume-registration", "--max-steps", "800", "--json", out_json])
    assert rc == 0
    out = json.load(open(out_json))
    assert out["organs"] == combo and out["slices"] == [prep.label("axial", k)]
    assert out["selection"]["top"][0][0] == ["axial", k, combo]
    assert "selected" in capsys.readouterr().out
    # a missing model is a clear error, not a traceback
    assert main(["--phantom-resolution", "3", "--slices", "auto", "--selector", str(tmp_path / "nope.json")]) == 2
    assert main(["--phantom-resolution", "3", "--slices", "auto:zz", "--selector", path]) == 2  # unknown auto mode
    # axial + the plane model's best sagittal slice, psdl
    pl, _ = tune_and_train(TrainingTable.from_sweep(synthetic_plane_table(4), "dice_rank"), split="row", patience=2, max_trials=3)
    pl.save(str(tmp_path / "pl.json"))
    (o2, k2, _), _ = pl.rank(prep.full_model, ("sagittal",), k=1)[0][0]
    rc = main(["--phantom-resolution", "3", "--particle-step", "1", "--slices", "auto:as", "--selector", path, "--plane-selector",
               str(tmp_path / "pl.json"), "--device", "cpu", "--no-volume-registration", "--max-steps", "800", "--json", out_json])
    out = json.load(open(out_json))
    assert rc == 0 and out["organs"] == "psdl" and len(out["slices"]) == 2 and not out["excluded_driven"]  # every particle scored, whatever the plane count
    assert out["slices"][1] == prep.label("sagittal", k2)


def test_within_case_scores_ignore_case_offsets():
    from warpmpm.selection import within_group_scores

    table = TrainingTable.from_sweep(synthetic_table(3))
    offset = np.array([{"c0": 0.0, "c1": 5.0, "c2": -3.0}[c] for c in table.cases])
    mask = np.ones(len(table.y), dtype=bool)
    s = within_group_scores(table, table.y + offset, mask)  # right order within each case, wrong level
    assert s["test_within_case_r2"] == pytest.approx(1.0) and s["test_spearman"] == pytest.approx(1.0)
    s = within_group_scores(table, -table.y, mask)
    assert s["test_spearman"] == pytest.approx(-1.0)



def test_bad_selection_cli_values_are_clear_errors(tmp_path):
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

    def run(*args):
        return subprocess.run([sys.executable, "-m", "warpmpm.cli", *args], capture_output=True, text=True, cwd=tmp_path,
                              env=dict(os.environ, PYTHONPATH=root))

    r = run("train", str(tmp_path / "missing.csv"))
    assert r.returncode == 2 and "missing.csv not found" in r.stderr
    r = run("sweep", "--slice-stride", "0", "--out", str(tmp_path / "s.csv"))
    assert r.returncode == 2 and "--slice-stride" in r.stderr and not (tmp_path / "s.csv").exists()
    r = run("multi", "--selector", "a.json", "--plane-selector", "p.json", "--top", "0")
    assert r.returncode == 2 and "--top" in r.stderr
    r = run("multi", "--selector", "a.json", "--plane-selector", "p.json", "--out", str(tmp_path / "m.csv"))
    assert r.returncode == 2 and "a.json" in r.stderr and not (tmp_path / "m.csv").exists()


def test_model_save_to_a_missing_folder_writes_nothing(tmp_path):
    from warpmpm.images import InputError

    model, _ = tune_and_train(TrainingTable.from_sweep(synthetic_table(3)), split="row", patience=1, max_trials=2)
    with pytest.raises(InputError, match="does not exist"):
        model.save(str(tmp_path / "nope" / "m.json"))
    model.save(str(tmp_path / "m.json"))
    assert sorted(os.listdir(tmp_path)) == ["m.json", "m.json.meta.json"]
