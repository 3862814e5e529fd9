"""Choosing where to image (:mod:`warpmpm.plane_placement`): the features against a direct count, the rule without a
model first, a model that recovers a known relation between features and error on cases it never saw, the regret
by hand, and ``warpmpm plan-planes`` on the built-in phantom with the shipped model."""

import json

import numpy as np
import pytest

from warpmpm.errors import InputError
from warpmpm.images import ORGANS
from warpmpm.model import build_model
from warpmpm.phantom import make_phantom
from warpmpm.plane_placement import (DEFAULT_PLACEMENT_MODEL, FEATURES, Placement, PlacementModel, PlacementTable,
                                     enumerate_placements, placement_features, placement_regret, train_placement_model)
from warpmpm.slices import DrivingSlice


def coarse_model(seed=0):
    return build_model(make_phantom(seed=seed, resolution=3.0), tuple(ORGANS))


def test_features_match_a_direct_count_of_the_particles_on_the_planes():
    model = coarse_model()
    pan = model.organs.index("pancreas")
    ks = {o: np.nonzero(model.slice_counts(o)[:, pan])[0] for o in ("sagittal", "coronal")}
    placements = [Placement("sagittal", (DrivingSlice("sagittal", int(ks["sagittal"][1])),)),
                  Placement("sagittal+coronal", (DrivingSlice("sagittal", int(ks["sagittal"][-1])),
                                                 DrivingSlice("coronal", int(ks["coronal"][len(ks["coronal"]) // 2]))))]
    X = placement_features(model, placements)
    col = {f: i for i, f in enumerate(FEATURES)}
    x = model.positions_mm
    axis = {"sagittal": 0, "coronal": 1}  # the phantom's image axes are the world axes
    for row, p in zip(X, placements):
        assert row[col["n_planes"]] == len(p.slices)
        coords = {s.orientation: x[model.slice_mask(s.orientation, s.index)][:, axis[s.orientation]].mean() for s in p.slices}
        for k, o in enumerate(model.organs):
            sel = model.organ_index == k
            c = x[sel].mean(0)
            for orientation, a in axis.items():
                if orientation not in coords:
                    assert row[col[f"{o}_section_{orientation}"]] == 0.0 and np.isnan(row[col[f"{o}_position_{orientation}"]])
                    continue
                s = next(s for s in p.slices if s.orientation == orientation)
                on_plane = np.sum(sel & model.slice_mask(orientation, s.index))
                largest = max(np.sum(sel & model.slice_mask(orientation, j)) for j in range(model.geometry.size[a]))
                assert row[col[f"{o}_section_{orientation}"]] == pytest.approx(on_plane / largest)
                half = 0.5 * (x[sel, a].max() - x[sel, a].min())
                assert row[col[f"{o}_position_{orientation}"]] == pytest.approx((coords[orientation] - c[a]) / half, abs=1e-6)
            d = min(abs(c[axis[q]] - v) for q, v in coords.items())
            assert row[col[f"{o}_distance_to_planes_mm"]] == pytest.approx(d, abs=1e-6)


def test_each_family_starts_with_the_rule_and_every_plane_cuts_the_pancreas():
    model = coarse_model()
    pan = model.organs.index("pancreas")
    placements = enumerate_placements(model)
    counts = {o: model.slice_counts(o)[:, pan] for o in ("sagittal", "coronal")}
    for family in ("sagittal", "sagittal+coronal"):
        fam = [p for p in placements if p.family == family]
        assert all(counts[s.orientation][s.index] == counts[s.orientation].max() for s in fam[0].slices)
        assert all(counts[s.orientation][s.index] > 0 for p in fam for s in p.slices)
    n_sag = int(np.sum(counts["sagittal"] > 0))
    assert len(placements) == n_sag + n_sag * int(np.sum(counts["coronal"] > 0))
    with pytest.raises(InputError, match="plane family 'axial'"):
        enumerate_placements(model, ("axial",))


def synthetic_table(n_cases=6):
    """Real placement features of coarse phantoms (one case per seed) with a known error: the pancreas misses the
    motion its planes do not show, the kidney what lies far from them."""
    X, cases, groups, rule, labels = [], [], [], [], []
    for seed in range(n_cases):
        model = coarse_model(seed)
        ps = enumerate_placements(model, stride=2)
        X.append(placement_features(model, ps))
        cases += [f"phantom{seed}"] * len(ps)
        groups += [f"phantom{seed}|0|breathing|{p.family}" for p in ps]
        first = {p.family: i for i, p in reversed(list(enumerate(ps)))}
        rule += [first[p.family] == i for i, p in enumerate(ps)]
        labels += [p.label() for p in ps]
    X = np.vstack(X)
    col = {f: i for i, f in enumerate(FEATURES)}

    def seen(o):
        return np.maximum(X[:, col[f"{o}_section_sagittal"]], X[:, col[f"{o}_section_coronal"]])

    missed = {o: 0.05 + 0.5 * (1.0 - seen(o)) ** 2 for o in ORGANS}
    missed["pancreas"] = (0.02 + 0.3 * (1.0 - seen("pancreas")) ** 2
                          + 0.05 * np.minimum(np.abs(X[:, col["pancreas_position_sagittal"]]), 2.0))
    motion = {o: np.full(len(X), 10.0) for o in ORGANS}
    return PlacementTable(X, missed, {o: missed[o] * 10.0 for o in ORGANS}, motion, np.array(cases), np.array(groups),
                          np.array(rule), labels)


def test_the_model_learns_a_known_error_on_cases_it_never_saw():
    table = synthetic_table()
    test = np.isin(table.cases, ["phantom4", "phantom5"])
    model, tuning = train_placement_model(table, ~test, max_trials=6, patience=6, folds=3)
    assert model.trained_on["cases"] == [f"phantom{s}" for s in range(4)]
    pred = model.predict(table.X)
    from warpmpm.selection import r2_score

    assert r2_score(table.missed["pancreas"][test], pred["pancreas"][test]) > 0.8
    reg = placement_regret(table, pred, test)
    assert np.mean([r["model"] for r in reg.values()]) < 0.5 * np.mean([r["random"] for r in reg.values()])


def test_regret_is_the_chosen_error_above_the_best(tmp_path):
    err = np.array([1.0, 0.7, 0.9, 2.0])
    table = PlacementTable(np.zeros((4, len(FEATURES))), {o: err / 10 for o in ORGANS}, {o: err for o in ORGANS},
                           {o: np.full(4, 10.0) for o in ORGANS}, np.array(["a"] * 4), np.array(["a|0|b|sagittal"] * 4),
                           np.array([True, False, False, False]), ["s:1", "s:2", "s:3", "s:4"])
    pred = {o: np.array([0.3, 0.2, 0.1, 0.4]) for o in ORGANS}  # the model picks the third placement
    r = placement_regret(table, pred, np.ones(4, bool), ("pancreas",))["a|0|b|sagittal"]
    assert r["model"] == pytest.approx(0.2) and r["rule"] == pytest.approx(0.3) and r["random"] == pytest.approx(0.45)
    # judged by two organs: the mean of their errors; the stomach is best seen by the fourth placement
    table.error_mm["stomach"] = np.array([3.0, 3.0, 3.0, 0.0])
    pred["stomach"] = np.array([0.3, 0.3, 0.3, 0.0])
    r = placement_regret(table, pred, np.ones(4, bool), ("pancreas", "stomach"))["a|0|b|sagittal"]
    # means: 2.0, 1.85, 1.95, 1.0; the model's mean scores 0.3, 0.25, 0.2, 0.2 (a tie: the first, the third)
    assert r["best_mm"] == pytest.approx(1.0) and r["model"] == pytest.approx(0.95) and r["rule"] == pytest.approx(1.0)


def test_a_saved_model_predicts_the_same_and_a_wrong_file_is_refused(tmp_path):
    table = synthetic_table(3)
    model, _ = train_placement_model(table, table.cases != "phantom2", max_trials=2, patience=2, folds=2)
    path = str(tmp_path / "m.json")
    model.save(path)
    again = PlacementModel.load(path)
    for o in ORGANS:
        np.testing.assert_allclose(again.predict(table.X)[o], model.predict(table.X)[o], rtol=1e-6)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"kind": "something else"}))
    with pytest.raises(InputError, match="not a plane-placement model"):
        PlacementModel.load(str(bad))
    with pytest.raises(InputError, match="not found"):
        PlacementModel.load(str(tmp_path / "none.json"))


def test_plan_planes_ranks_the_phantom_with_the_shipped_model(tmp_path, capsys):
    from warpmpm.cli import main

    assert PlacementModel.load(DEFAULT_PLACEMENT_MODEL).organs == tuple(ORGANS)
    out = tmp_path / "rank.json"
    assert main(["plan-planes", "--method", "model", "--phantom-resolution", "3", "--top", "3", "--json", str(out),
                 "--picture", str(tmp_path / "planes.png")]) == 0
    text = capsys.readouterr().out
    assert "the rule without a model" in text and "placements ranked in" in text
    doc = json.loads(out.read_text())
    ranked = doc["placements"]
    assert [p["rank"] for p in ranked] == list(range(1, len(ranked) + 1))
    scores = [p["predicted_fraction_missed"]["pancreas"] for p in ranked]
    assert scores == sorted(scores) and 0.0 <= scores[0] < 1.0
    assert set(doc["rule"]) == {"sagittal", "sagittal+coronal"}
    assert (tmp_path / "planes.png").stat().st_size > 10_000
    # bad input: one error line, nothing written
    assert main(["plan-planes", "--method", "model", "--phantom-resolution", "3", "--families", "axial", "--json", str(tmp_path / "x.json")]) == 2
    assert "--families 'axial'" in capsys.readouterr().err and not (tmp_path / "x.json").exists()
    assert main(["plan-planes", "--method", "model", "--phantom-resolution", "3", "--rank-by", "liver"]) == 2
    assert "rank by organs of the model" in capsys.readouterr().err


def write_sweep_csv(table, path):
    """The synthetic table as ``warpmpm sweep-planes`` rows (the copy's errors; no motion = 10 mm)."""
    import csv

    from warpmpm.experiment.plane_sweep import PLANE_SWEEP_FIELDS

    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, PLANE_SWEEP_FIELDS)
        w.writeheader()
        for i in range(len(table.cases)):
            case, seed, load, family = table.groups[i].split("|")
            row = {"case": case, "truth_seed": seed, "load": load, "family": family, "planes": table.labels[i],
                   "rule": bool(table.rule[i]), "failure": ""}
            row |= {fe: table.X[i, k] for k, fe in enumerate(FEATURES) if fe != "n_planes"}
            for o in ORGANS:
                row |= {f"initial_{o}_mm": 10.0, f"copy_{o}_mm": table.error_mm[o][i]}
            w.writerow(row)


def test_train_planes_reports_split_by_case_and_saves_a_model_plan_planes_reads(tmp_path, capsys):
    from warpmpm.cli import main

    import gzip

    write_sweep_csv(synthetic_table(4), tmp_path / "planes.csv")
    sweep = tmp_path / "planes.csv.gz"  # a kept sweep is gzipped (benchmarks/results/plane_sweep.csv.gz)
    sweep.write_bytes(gzip.compress((tmp_path / "planes.csv").read_bytes()))
    model, report = tmp_path / "m.json", tmp_path / "r.json"
    assert main(["train-planes", str(sweep), "--test-cases", "phantom3", "--max-trials", "3", "--patience", "3",
                 "--out", str(model), "--report", str(report)]) == 0
    out = capsys.readouterr().out
    assert "held out: phantom3" in out and "leave one case out (4 cases" in out
    rep = json.loads(report.read_text())
    assert rep["held_out"]["cases"] == ["phantom3"] and PlacementModel.load(str(model)).trained_on["cases"] == [
        "phantom0", "phantom1", "phantom2"]
    assert rep["held_out"]["pancreas_r2_fraction"] > 0.5
    assert main(["plan-planes", "--method", "model", "--phantom-resolution", "3", "--model", str(model), "--top", "1"]) == 0
    # refused: too few cases, an unknown test case, a CSV that is not a plane sweep
    few = tmp_path / "few.csv"
    write_sweep_csv(synthetic_table(2), few)
    assert main(["train-planes", str(few), "--out", str(tmp_path / "n.json")]) == 2
    assert "needs at least 3 cases" in capsys.readouterr().err and not (tmp_path / "n.json").exists()
    assert main(["train-planes", str(sweep), "--test-cases", "phantom9", "--out", str(tmp_path / "n.json")]) == 2
    assert "phantom9 are not in the sweep" in capsys.readouterr().err
    other = tmp_path / "other.csv"
    other.write_text("case,protocol\nx,paper\n")
    assert main(["train-planes", str(other)]) == 2
    assert "not a plane-sweep CSV" in capsys.readouterr().err


def test_plan_planes_ranks_by_the_error_on_a_truth_of_the_scan(tmp_path, capsys):
    """The default (``--method simulate``): a finite-element breathing truth of the (coarse) phantom; every placement of the grid scored by
    the copy of its planes' true in-plane motion, best first; the best sees the pancreas's motion far better than no
    motion, and the rule without a model is named."""
    from warpmpm.cli import main

    out = tmp_path / "sim.json"
    assert main(["plan-planes", "--phantom-resolution", "3", "--positions", "1", "--families", "sagittal",
                 "--truth-cell-mm", "12", "--json", str(out)]) == 0
    assert "placements simulated in" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    errs = [p["simulated_error_mm"]["pancreas"] for p in doc["placements"]]
    assert len(errs) >= 2 and errs == sorted(errs)
    assert errs[0] < 0.25 * doc["motion_mm"]["pancreas"] and doc["motion_mm"]["pancreas"] > 5.0
    assert doc["rule"]["sagittal"]["rank"] >= 1
    assert main(["plan-planes", "--positions", "0"]) == 2
    assert "--positions must be >= 1" in capsys.readouterr().err


def test_the_simulated_selector_is_judged_on_another_truth_of_the_same_scan():
    from warpmpm.experiment.train_planes import evaluate_simulated

    rows = []
    for seed, scale in ((0, 1.0), (1, 2.0)):  # the second truth moves twice as far; its errors double
        for k, (err, rule) in enumerate(((1.0, True), (0.5, False), (2.0, False))):
            row = {"case": "a", "load": "breathing", "family": "sagittal", "truth_seed": str(seed), "planes": f"sagittal:{k}",
                   "rule": str(rule), "failure": ""}
            for o in ORGANS:
                row |= {f"initial_{o}_mm": 10.0 * scale, f"copy_{o}_mm": err * scale}
            rows.append(row)
    sim = evaluate_simulated(rows)
    assert sim["n_pairs"] == 2 and sim["pancreas_r2_fraction"] == pytest.approx(1.0)
    v = sim["pancreas"]["sagittal"]
    assert v["simulated"]["max"] == 0.0 and v["rule"]["mean"] == pytest.approx(0.75)  # (0.5 + 1.0) / 2


def test_plan_planes_refuses_a_scan_without_all_four_organs(tmp_path, capsys):
    from warpmpm.cli import main
    from warpmpm.images import write_case

    case = make_phantom(resolution=3.0)
    case.labels[case.labels == case.label_map["left_kidney"]] = 0
    write_case(case, str(tmp_path / "labels.nii.gz"), str(tmp_path / "image.nii.gz"))
    assert main(["plan-planes", "--method", "model", "--labels", str(tmp_path / "labels.nii.gz"),
                 "--image", str(tmp_path / "image.nii.gz"), "--json", str(tmp_path / "r.json")]) == 2
    assert "lack left_kidney" in capsys.readouterr().err and not (tmp_path / "r.json").exists()
