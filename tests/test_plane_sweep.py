"""The plane-placement sweep (:mod:`warpmpm.experiment.plane_sweep`) on a coarse phantom's finite-element truth: every
placement scored for every method and organ beside its features, the rule placement first, resumable, and the copy of
what the planes see far better than no motion on the pancreas they cross."""

import csv

import pytest

from warpmpm.errors import InputError
from warpmpm.experiment.plane_sweep import METHODS, sweep_planes

PHANTOM = {"name": "phantom0", "phantom_seed": 0, "phantom_resolution": 3.0}


def read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_a_sweep_scores_every_placement_and_resumes(tmp_path):
    out = str(tmp_path / "planes.csv")
    rows, failed = sweep_planes([PHANTOM], [0], ["breathing"], ("sagittal", "sagittal+coronal"), 2, out, truth_cell_mm=12.0,
                                progress=None)
    assert not failed
    table = read(out)
    assert len(table) == len(rows) >= 4
    for family in ("sagittal", "sagittal+coronal"):
        fam = [r for r in table if r["family"] == family]
        assert fam[0]["rule"] == "True" and all(r["rule"] == "False" for r in fam[1:])
    sag = [r for r in table if r["family"] == "sagittal"]
    pairs = [r for r in table if r["family"] == "sagittal+coronal"]
    # the rule's plane shows the most pancreas of the sagittal positions; the pairs hold it with every coronal plane
    assert int(sag[0]["pancreas_on_planes"]) == max(int(r["pancreas_on_planes"]) for r in sag)
    assert pairs[0]["planes"].split(",")[0] == sag[0]["planes"]
    assert len(pairs) == len(sag) * len({r["planes"].split(",")[1] for r in pairs})
    for r in table:
        assert r["failure"] == ""
        for m in METHODS:
            for o in ("pancreas", "stomach", "duodenum", "left_kidney"):
                assert float(r[f"{m}_{o}_mm"]) >= 0.0
        # a breathing truth moves the pancreas ~10 mm; copying the true in-plane motion of the planes that cross it
        # recovers most of it
        assert float(r["initial_pancreas_mm"]) > 5.0
        if int(r["pancreas_on_planes"]) >= 10:
            assert float(r["copy_pancreas_mm"]) < 0.25 * float(r["initial_pancreas_mm"])
    # resumable: a second run finds every placement done and writes nothing
    rows2, _ = sweep_planes([PHANTOM], [0], ["breathing"], ("sagittal", "sagittal+coronal"), 2, out, truth_cell_mm=12.0,
                            progress=None)
    assert len(read(out)) == len(table) == len(rows2)
    # refreshing the features from the planning scan gives what the sweep wrote (one code path), errors untouched
    from warpmpm.experiment.plane_sweep import refresh_features
    from warpmpm.plane_placement import FEATURES

    (tmp_path / "old.csv").write_text(open(out).read())
    assert refresh_features(out, [PHANTOM], 1, progress=None) == len(table)
    again = read(out)
    for a, b in zip(table, again):
        assert a["planes"] == b["planes"] and a["copy_pancreas_mm"] == b["copy_pancreas_mm"]
        for f in FEATURES[1:]:
            assert float(b[f]) == pytest.approx(float(a[f]), abs=1e-5, nan_ok=True), f


def test_bad_sweep_options_are_refused(tmp_path):
    with pytest.raises(InputError, match="plane family 'axial'"):
        sweep_planes([PHANTOM], [0], ["breathing"], ("axial",), 2, str(tmp_path / "p.csv"))
    with pytest.raises(InputError, match="--positions must be >= 1"):
        sweep_planes([PHANTOM], [0], ["breathing"], ("sagittal",), 0, str(tmp_path / "p.csv"))
    assert not (tmp_path / "p.csv").exists()


def test_an_unknown_load_or_a_negative_truth_seed_is_refused_before_any_task(tmp_path):
    with pytest.raises(InputError, match="load"):
        sweep_planes([PHANTOM], [0], ["breathing+sneeze"], ("sagittal",), 2, str(tmp_path / "p.csv"))
    with pytest.raises(InputError, match="seed"):
        sweep_planes([PHANTOM], [-1], ["breathing"], ("sagittal",), 2, str(tmp_path / "p.csv"))


def test_the_command_writes_the_table_and_refuses_bad_seeds(tmp_path, capsys):
    from warpmpm.cli import main

    out = tmp_path / "planes.csv"
    assert main(["sweep-planes", "--phantom-resolution", "3", "--families", "sagittal", "--positions", "1",
                 "--truth-cell-mm", "12", "--out", str(out)]) == 0
    table = read(out)
    assert table and table[0]["rule"] == "True" and "placements scored" in capsys.readouterr().out
    assert main(["sweep-planes", "--truth-seeds", "x", "--out", str(tmp_path / "q.csv")]) == 2
    assert "--truth-seeds must be comma-separated integers" in capsys.readouterr().err
    assert not (tmp_path / "q.csv").exists()


def test_positions_spread_over_the_slices_that_hold_pancreas_even_with_a_sampling_step():
    """With every other voxel sampled, half the slices across the pancreas hold no particle: the positions are drawn
    among those that do, so a sweep gets the positions it asked for."""
    from warpmpm.experiment.case import prepare_case
    from warpmpm.experiment.config import CaseConfig
    from warpmpm.experiment.plane_sweep import placement_labels

    prep = prepare_case(CaseConfig(device="cpu", phantom_resolution=2.0, particle_step=2))
    model = prep.model("psdl")
    pan = model.subset(("pancreas",))
    for family, orientation in (("sagittal", "sagittal"), ("sagittal+coronal", "coronal")):
        labels = placement_labels(prep, model, family, 4)
        ks = sorted({s.index for lab in labels for s in prep.resolve_slices(model, lab) if s.orientation == orientation})
        assert len(ks) >= 4  # the four positions asked for (and the rule's, when it is not one of them)
        assert all(pan.slice_counts(orientation)[k, 0] > 0 for k in ks)
