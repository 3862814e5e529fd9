"""The library's track session (:func:`warpmpm.track`) and its pluggable outputs: what ``warpmpm track`` runs."""

import csv
import json
import os

import numpy as np
import pytest

import warpmpm
from warpmpm.cli import main
from warpmpm.errors import InputError
from warpmpm.outputs import OUTPUTS, TrackOutput, make_outputs


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("session") / "series")
    assert main(["make-cine", "--phantom-resolution", "3", "--frames", "3", "--plane", "sagittal,coronal", "--out", out]) == 0
    return out


def _plan(series):
    return os.path.join(series, "planning", "image.nii.gz"), os.path.join(series, "planning", "labels.nii.gz")


class Centroids(TrackOutput):
    """An output of a user's: the pancreas centroid of every frame (mm), kept in memory and written as a CSV."""

    name = "pancreas-centroids"
    writes = "pancreas_centroid.csv: the pancreas centroid per frame, mm, world LPS"

    def __init__(self):
        self.rows, self.closed = [], None

    def frame(self, tracker, out_dir, n, frame, positions_mm, labels, field_mm):
        self.rows.append(positions_mm[tracker.model.organ_slice("pancreas")].mean(0))

    def end(self, tracker, out_dir, rows):
        np.savetxt(os.path.join(out_dir, "pancreas_centroid.csv"), np.asarray(self.rows), delimiter=",")

    def close(self, ok):
        self.closed = ok


def test_a_python_track_equals_the_command_and_takes_an_output_of_the_users(series, tmp_path):
    """``warpmpm.track`` writes what ``warpmpm track`` writes (the same track.csv to the digit: the command is a call
    into it), hands every frame to a user's output (its pancreas centroids are those of particles.npz), records the
    estimator, the outputs and the configuration in track.json, and an unknown output is refused by name."""
    image, labels = _plan(series)
    mine = Centroids()
    res = warpmpm.track(image, os.path.join(series, "cine"), str(tmp_path / "lib"), labels=labels,
                        outputs=("labels", "displacement", mine))
    assert len(res.rows) == 3 and mine.closed is True and len(mine.rows) == 3
    assert res.record["estimator"] == "copy" and res.record["outputs"] == ["labels", "displacement", "pancreas-centroids"]
    assert json.load(open(tmp_path / "lib" / "track.json")) == res.record
    p = np.load(tmp_path / "lib" / "particles.npz")
    pan = p["organ_index"] == list(p["organs"]).index("pancreas")
    assert np.allclose(np.loadtxt(tmp_path / "lib" / "pancreas_centroid.csv", delimiter=","),
                       p["estimate_mm"][:, pan].mean(1), atol=1e-9)
    assert sorted(os.listdir(tmp_path / "lib" / "displacement")) == [f"frame_{n:04d}.nii.gz" for n in range(3)]
    assert main(["track", "--image", image, "--labels", labels, "--cine", os.path.join(series, "cine"),
                 "--out", str(tmp_path / "cli"), "--displacement"]) == 0
    got = [list(csv.DictReader(open(tmp_path / d / "track.csv"))) for d in ("lib", "cli")]
    keys = [k for k in got[0][0] if not k.endswith("_ms") and k not in ("wall_s", "latency_s")]  # times differ
    assert [[r[k] for k in keys] for r in got[0]] == [[r[k] for k in keys] for r in got[1]]
    with pytest.raises(InputError, match="not one of labels, displacement"):
        warpmpm.track(image, os.path.join(series, "cine"), str(tmp_path / "x"), labels=labels, outputs=("label-maps",))
    with pytest.raises(InputError, match="dose=PATH"):  # an output with inputs is made from track's own argument
        make_outputs(["dose"])
    assert not os.path.exists(tmp_path / "x")
    assert {"labels", "displacement", "dicom", "dose"} <= set(OUTPUTS)


def test_a_failing_output_leaves_nothing_and_is_told_the_track_failed(series, tmp_path):
    """An output that raises mid-series: no track folder appears (nothing half-written) and every output is closed
    with ``ok=False``."""
    image, labels = _plan(series)

    class Breaks(Centroids):
        name = "breaks"

        def frame(self, tracker, out_dir, n, frame, positions_mm, labels, field_mm):
            if n == 1:
                raise InputError("this output cannot go on")
            super().frame(tracker, out_dir, n, frame, positions_mm, labels, field_mm)

    mine, other = Breaks(), Centroids()
    with pytest.raises(InputError, match="cannot go on"):
        warpmpm.track(image, os.path.join(series, "cine"), str(tmp_path / "t"), labels=labels, outputs=(other, mine))
    assert not os.path.exists(tmp_path / "t") and mine.closed is False and other.closed is False
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no work folder, no lock
