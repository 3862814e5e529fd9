"""The plane check: a plane's motion that makes the captured planes match worse is dropped before it drives anything.

The phantom's planning image is moved by a known motion (each organ translated) to make the captured volume; each
plane's "registered" motion is then the truth, or the truth with an error put in on purpose.
"""

import numpy as np
import pytest

from warpmpm.plane_check import MAX_MOTION_MM, check_planes, combined_motion
from warpmpm.imaging import warp_array
from warpmpm.slices import DrivingSlice
from warpmpm.targets import slice_targets

SHIFT = {"pancreas": (1.0, 3.0, -6.0), "stomach": (0.0, 2.0, -7.0), "duodenum": (2.0, 3.0, -5.0), "left_kidney": (0.0, 0.0, -6.0)}


@pytest.fixture(scope="module")
def scene(tiny_case, tiny_model):
    m, case = tiny_model, tiny_case
    organ_of = np.asarray(m.organs)[m.organ_index]
    truth = m.positions_mm + np.array([SHIFT[o] for o in organ_of])
    captured = warp_array(case.image, case.geometry, m.positions_mm, truth)
    ijk = np.argwhere(case.labels == case.label_map["pancreas"]).mean(0).round().astype(int)  # (k, j, i)
    slices = [DrivingSlice("sagittal", int(ijk[2])), DrivingSlice("coronal", int(ijk[1]))]
    values = {o: case.label_map[o] for o in m.organs}
    centre = case.geometry.center_mm()
    return m, case, truth, captured, slices, values, centre


def moved_with(truth, error):
    """Each plane's motion: the truth, plus ``error[(plane orientation, organ)]`` (mm) where given."""
    def moved(s, idx, model):
        organ_of = np.asarray(model.organs)[model.organ_index]
        out = truth[idx].copy()
        for (orientation, organ), e in error.items():
            if s.orientation == orientation:
                out[organ_of[idx] == organ] += np.asarray(e)
        return out
    return moved


def run(scene, error):
    m, case, truth, captured, slices, values, centre = scene
    f = moved_with(truth, error)
    moved = lambda s, idx: f(s, idx, m)  # noqa: E731
    pc, keep = check_planes(m, slices, moved, case.image, captured, case.labels, case.geometry, values, centre, warn=False)
    return pc, keep, moved


def test_true_motion_on_both_planes_is_kept(scene):
    pc, _, _ = run(scene, {})
    assert pc.dropped == [] and pc.match_kept == pc.match_all > pc.match_none + 0.1


def test_a_wrong_organ_motion_on_one_plane_is_dropped_and_never_driven(scene):
    """The coronal plane's pancreas registered 12 mm too far superior: that pair alone is dropped, and no particle takes
    a target from it; the sagittal plane's pancreas still drives."""
    m, case, truth, captured, slices, values, centre = scene
    pc, keep, moved = run(scene, {("coronal", "pancreas"): (0.0, 0.0, 12.0)})
    assert pc.dropped == [(str(slices[1]), "pancreas")], pc.reasons
    assert pc.match_kept > pc.match_all
    drive = slice_targets(m, m.positions_mm, slices, moved, keep)
    organ_of = np.asarray(m.organs)[m.organ_index]
    on_cor_only = m.slice_mask("coronal", slices[1].index) & ~m.slice_mask("sagittal", slices[0].index) & (organ_of == "pancreas")
    assert not np.isin(np.nonzero(on_cor_only)[0], drive.idx).any()
    on_sag = m.slice_mask("sagittal", slices[0].index) & (organ_of == "pancreas")
    assert np.isin(np.nonzero(on_sag)[0], drive.idx).all()
    # the copy of the checked motion is closer to the truth than the copy of everything
    every = combined_motion(m, m.positions_mm, slices, moved, lambda s, idx: np.ones(len(idx), bool))
    checked = combined_motion(m, m.positions_mm, slices, moved, keep)
    sel = organ_of == "pancreas"
    assert np.linalg.norm(checked[sel] - truth[sel], axis=1).mean() < np.linalg.norm(every[sel] - truth[sel], axis=1).mean()


def test_motion_larger_than_a_frame_shows_is_dropped(scene):
    pc, _, _ = run(scene, {("sagittal", "stomach"): (0.0, 0.0, MAX_MOTION_MM + 10.0)})
    assert ("sagittal" in pc.dropped[0][0] and pc.dropped[0][1] == "stomach"
            and "more than a frame shows" in pc.reasons[pc.dropped[0]])


def test_motion_worse_than_none_everywhere_leaves_nothing_driven(scene):
    """Every plane's every organ registered 10 mm the wrong way: no motion matches the planes better; nothing is driven
    and the planes disagree is reported where they share a direction."""
    m, case, truth, captured, slices, values, centre = scene
    wrong = {(s.orientation, o): (-2 * np.array(SHIFT[o]) + np.array([0.0, 0.0, 0.0])) for s in slices for o in m.organs}
    pc, keep, moved = run(scene, wrong)
    assert pc.kept == [] and pc.match_kept == pc.match_none
    assert len(slice_targets(m, m.positions_mm, slices, moved, keep).idx) == 0


def test_run_with_a_corrupted_plane_warns_and_ends_no_worse_than_no_motion(tiny_case):
    """A whole run (the phantom, contact truth, sagittal + coronal, registration targets) whose coronal frame is
    replaced by a blank one (a failed acquisition): the check drops what the frame would have driven, with warnings,
    and the estimate ends no worse than no motion."""
    import warnings

    from warpmpm.experiment import capture as cap
    from warpmpm.experiment.config import CaseConfig
    from warpmpm.experiment.run import run_case

    original = cap.planning_and_gt_volumes

    def corrupted(case, gt):
        planning, warped = original(case, gt)
        warped = warped.copy()
        j = int(np.argwhere(case.labels == case.label_map["pancreas"]).mean(0).round()[1])
        warped[:, j, :] = np.random.default_rng(0).normal(warped.mean(), warped.std(), warped[:, j, :].shape)
        return planning, warped

    from warpmpm.experiment import target_kinds

    target_kinds.planning_and_gt_volumes = corrupted
    try:
        k, j, i = np.argwhere(tiny_case.labels == tiny_case.label_map["pancreas"]).mean(0).round().astype(int)
        cfg = CaseConfig(phantom_resolution=3.0, protocol="contact", deformation=1, slices=f"sagittal:{i},coronal:{j}",
                         targets="registration-demons", device="cpu", max_steps=1500,
                         baselines=("initial", "propagate"))
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            out = run_case(cfg)
    finally:
        target_kinds.planning_and_gt_volumes = original
    said = " ".join(str(x.message) for x in w)
    assert "plane check: coronal" in said
    est, initial = out.results["estimate"], out.results["initial"]
    assert est.error_mm <= initial.error_mm + 0.05
    assert out.registration["plane_check"]["dropped"]
