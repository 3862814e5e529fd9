"""Issue 53 (in part): the tracker's estimators behind one interface and a registry; the default is the measured best."""

import os

import numpy as np
import pytest

from warpmpm.cine import read_cine
from warpmpm.cli import main
from warpmpm.errors import InputError
from warpmpm.estimators import ESTIMATORS, FrameEstimate, TrackingEstimator, get_estimator, register
from warpmpm.images import load_case
from warpmpm.tracker import Tracker, TrackerConfig


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("est") / "series")
    assert main(["make-cine", "--phantom-resolution", "3", "--frames", "4", "--plane", "sagittal,coronal", "--out", out]) == 0
    return out


def _track(series, out, estimator):
    assert main(["track", "--image", os.path.join(series, "planning", "image.nii.gz"), "--labels",
                 os.path.join(series, "planning", "labels.nii.gz"), "--cine", os.path.join(series, "cine"), "--out", str(out),
                 "--device", "cpu", "--estimator", estimator]) == 0
    return np.load(os.path.join(out, "particles.npz"))


def test_the_default_copy_is_where_the_seeds_mpm_ends(series, tmp_path):
    """Why `copy` is the default: the slice-driven MPM, started from the frame's observed motion, ends there (measured on
    the finite-element series; here on a synthetic series, to 0.001 mm on every particle of every frame), at the cost of
    its solve. The copy's estimate is the tracker's `propagate` baseline itself, and moves the organs toward the truth."""
    copy = _track(series, tmp_path / "copy", "copy")
    mpm = _track(series, tmp_path / "mpm", "slice-driven")
    assert np.abs(copy["estimate_mm"] - mpm["estimate_mm"]).max() < 1e-3
    assert np.array_equal(copy["estimate_mm"], copy["propagate_mm"])
    truth = np.load(os.path.join(series, "truth", "positions.npz"))["truth_mm"]
    moved = np.linalg.norm(truth - copy["planning_mm"][None], axis=2).mean()
    assert np.linalg.norm(truth - copy["estimate_mm"], axis=2).mean() < 0.5 * moved


def test_an_estimator_is_one_class_and_one_registry_line(series, tmp_path):
    """A new estimator: a TrackingEstimator subclass registered by name; the tracker and the command line take it."""

    @register
    class Halfway(TrackingEstimator):
        name = "halfway-test"
        uses = "half of what the planes show (a test)"
        measured = "nothing"

        def estimate(self, obs):
            self._positions = obs.positions_mm + 0.5 * (obs.observed_mm - obs.positions_mm)
            return FrameEstimate(self._positions.copy(), dict(solver="halfway", steps=0, linear_iterations=0, converged=True,
                                                              slice_converged=True, settled=True, body_motion_mm=0.0,
                                                              reason="half", wall_s=0.0, rms_residual_mm=0.0))

    try:
        case = load_case(os.path.join(series, "planning", "labels.nii.gz"), os.path.join(series, "planning", "image.nii.gz"))
        frames = read_cine(os.path.join(series, "cine"))[:1]
        tr = Tracker(case, frames, TrackerConfig(estimator="halfway-test"))
        x0 = tr.model.positions_mm.copy()
        tf = tr.step(0, frames[0])
        moved = tf.positions_mm - x0
        full = tr.propagated - x0  # the frame's observed motion (the copy baseline)
        assert np.abs(full).max() > 0.01 and np.allclose(moved, 0.5 * full, atol=1e-9)
        assert tf.row["solver"] == "halfway"
    finally:
        ESTIMATORS.pop("halfway-test", None)


def test_estimators_are_listed_one_line_each_with_the_default_marked(capsys):
    assert main(["estimators"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [ln.split(":")[0].split(" ")[0] for ln in lines] == list(ESTIMATORS) and len(lines) >= 3
    assert [ln for ln in lines if "(default)" in ln] == [ln for ln in lines if ln.startswith(f"{TrackerConfig().estimator} ")]
    assert all("uses " in ln and "measured: " in ln for ln in lines)


def test_an_unknown_estimator_is_refused_naming_the_registered_ones():
    with pytest.raises(InputError, match="copy, slice-driven, completion"):
        get_estimator("physics")
    with pytest.raises(InputError, match="drop them, or add --estimator slice-driven"):
        settled = TrackerConfig(estimator="copy", wait_settled=True)
        from warpmpm.phantom import make_phantom

        Tracker(make_phantom(resolution=3.0), [], settled)
