"""Displacement fields as truths (:mod:`warpmpm.fields`), ``run --truth-field`` and the per-organ scores and baselines."""

import json

import numpy as np
import pytest
import SimpleITK as sitk

from warpmpm.cli import main
from warpmpm.errors import InputError, InputWarning
from warpmpm.experiment.config import CaseConfig
from warpmpm.experiment.run import run_case
from warpmpm.fields import jacobian_determinant, read_field, sample_field, warp_volume, write_field
from warpmpm.images import Geometry
from warpmpm.phantom import make_phantom

#: A grid whose first two axes are flipped against world (as the CT sample's are).
FLIPPED = Geometry((12, 10, 8), (2.0, 2.5, 3.0), (40.0, -5.0, 10.0), (-1.0, 0, 0, 0, -1.0, 0, 0, 0, 1.0))


def world_points(g: Geometry) -> np.ndarray:
    nz, ny, nx = g.size[::-1]
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    return g.index_to_world(np.stack([i.ravel(), j.ravel(), k.ravel()], 1).astype(float)).reshape(nz, ny, nx, 3)


def test_round_trip_keeps_world_lps_values(tmp_path):
    f = np.zeros(FLIPPED.size[::-1] + (3,), np.float32)
    f[..., :] = (1.0, -2.0, 3.5)
    p = str(tmp_path / "u.nii.gz")
    write_field(f, FLIPPED, p)
    back = read_field(p, FLIPPED)
    assert np.array_equal(back, f.astype(float))
    assert np.allclose(sample_field(back, FLIPPED, [[30.0, -10.0, 16.0]]), [[1.0, -2.0, 3.5]])


def test_bad_fields_are_refused_with_the_reason(tmp_path):
    good = np.zeros(FLIPPED.size[::-1] + (3,), np.float32)
    p = str(tmp_path / "u.nii.gz")
    write_field(good, FLIPPED, p)
    other = Geometry(FLIPPED.size, (2.0, 2.5, 3.0), (41.0, -5.0, 10.0), FLIPPED.direction)
    with pytest.raises(InputError, match="not on the planning image's grid.*origin"):
        read_field(p, other)
    two = FLIPPED.apply_to(sitk.GetImageFromArray(good[..., :2], isVector=True))
    sitk.WriteImage(two, str(tmp_path / "two.nii.gz"))
    with pytest.raises(InputError, match="2 component"):
        read_field(str(tmp_path / "two.nii.gz"), FLIPPED)
    nan = good.copy()
    nan[3, 4, 5, 1] = np.nan
    write_field(nan, FLIPPED, str(tmp_path / "nan.nii.gz"))
    with pytest.raises(InputError, match=r"non-finite.*\(5, 4, 3\)"):
        read_field(str(tmp_path / "nan.nii.gz"), FLIPPED)
    with pytest.raises(InputError, match="not found"):
        read_field(str(tmp_path / "missing.nii.gz"), FLIPPED)


def test_jacobian_of_a_linear_field_and_a_fold_warning(tmp_path):
    """u = A x has det(I + grad u) = det(I + A) everywhere, whatever the grid's orientation; a field that folds an
    organ is read with a warning naming the folded voxels."""
    A = np.array([[0.1, 0.05, 0.0], [0.0, -0.2, 0.03], [0.02, 0.0, 0.15]])
    x = world_points(FLIPPED)
    f = x @ A.T
    det = jacobian_determinant(f, FLIPPED)
    assert np.allclose(det, np.linalg.det(np.eye(3) + A), atol=1e-9)
    fold = (x @ np.diag([-1.5, 0.0, 0.0]).T).astype(np.float32)  # x -> -0.5 x: turned inside out
    p = str(tmp_path / "fold.nii.gz")
    write_field(fold, FLIPPED, p)
    organ = np.zeros(FLIPPED.size[::-1], bool)
    organ[2:5, 2:5, 2:5] = True
    with pytest.warns(InputWarning, match="folds.*27 organ voxels"):
        read_field(p, FLIPPED, organ)


def test_warp_moves_the_image_with_the_tissue():
    """A bright voxel moved by a uniform forward field of +2 voxels along the grid's i axis appears 2 voxels further
    along i (the axis runs toward world -x on this grid)."""
    vol = np.zeros(FLIPPED.size[::-1], np.float32)
    vol[4, 5, 3] = 1.0
    f = np.zeros(FLIPPED.size[::-1] + (3,))
    f[..., 0] = -2 * FLIPPED.spacing_mm[0]  # world -x = +i on this grid
    out = warp_volume(vol, f, FLIPPED, order=0)
    assert out[4, 5, 5] == 1.0 and out.sum() == 1.0


@pytest.fixture(scope="module")
def translated(tmp_path_factory):
    """A uniform translation as the truth of the coarse phantom."""
    case = make_phantom(resolution=3.0)
    f = np.zeros(case.geometry.size[::-1] + (3,), np.float32)
    f[...] = (1.0, -2.0, 3.0)
    p = str(tmp_path_factory.mktemp("field") / "t.nii.gz")
    write_field(f, case.geometry, p)
    k, j, i = np.nonzero(case.labels == case.label_map["pancreas"])
    return case, p, int(np.median(i)), int(np.median(j))


def test_truth_field_run_scores_every_organ_and_the_copies_are_exact(translated, tmp_path):
    """Under a uniform translation seen on a sagittal and a coronal plane (true in-plane motion), every copying
    baseline is exact for the organs they cover, and organs on no plane are scored with nearest and global; the JSON
    holds every organ and says whether the estimate settled."""
    case, p, i, j = translated
    cfg = CaseConfig(phantom_resolution=3.0, protocol="field", truth_field=p, slices=f"sagittal:{i},coronal:{j}", targets="gt-inplane",
                     device="cpu", max_steps=150, baselines=("initial", "propagate", "rigid"))
    out = run_case(cfg)
    res = out.to_json()["results"]
    t = np.linalg.norm([1.0, -2.0, 3.0])
    assert res["initial"]["error_mm"] == pytest.approx(t, abs=1e-4)
    assert set(res["estimate"]["organs"]) == set(out.n_particles)
    assert "settled" in res["estimate"]
    seen = [o for o, s in res["rigid"]["organs"].items() if s["seen"]]
    assert "pancreas" in seen
    for o in seen:
        assert res["rigid"]["organs"][o]["error_mm"] < 1e-4
        assert res["propagate_planes"]["organs"][o]["error_mm"] < 1e-3
    for o, s in res["initial"]["organs"].items():
        assert s["error_mm"] == pytest.approx(t, abs=1e-4)
        assert s["si_mm"] == pytest.approx(3.0, abs=1e-4)
        if "distance_to_pancreas_mm" in s:  # a translation changes no distance
            assert s["distance_error_mm"] == pytest.approx(0.0, abs=1e-6)
    unseen = [o for o in out.n_particles if o not in seen]
    if unseen:
        for name in ("nearest", "global"):
            assert set(res[name]["organs"]) == set(unseen)
            for o in unseen:
                assert res[name]["organs"][o]["error_mm"] < 1e-4


def test_nearest_and_global_copy_what_the_planes_see(translated):
    """One sagittal plane through the pancreas sees (at most) its in-plane part of the translation: the organs it
    does not cross take it through nearest / global, so their error is exactly the unseen (x) component."""
    case, p, i, j = translated
    # a sagittal plane at the pancreas's head, away from the kidney
    k, jj, ii = np.nonzero(case.labels == case.label_map["pancreas"])
    cfg = CaseConfig(phantom_resolution=3.0, protocol="field", truth_field=p, slices=f"sagittal:{int(ii.min()) + 1}", targets="gt-inplane",
                     device="cpu", max_steps=50, baselines=("initial", "rigid"))
    res = run_case(cfg).to_json()["results"]
    unseen = [o for o, s in res["rigid"]["organs"].items() if not s["seen"]]
    assert unseen, "the plane should miss an organ"
    for o in unseen:
        assert res["nearest"]["organs"][o]["error_mm"] == pytest.approx(1.0, abs=1e-4)  # the x component is not seen
        assert res["global"]["organs"][o]["error_mm"] == pytest.approx(1.0, abs=1e-4)
        assert res["rigid"]["organs"][o]["error_mm"] == pytest.approx(np.linalg.norm([1, 2, 3]), abs=1e-4)


def test_truth_field_on_another_grid_is_refused_before_any_work(tmp_path):
    other = str(tmp_path / "other.nii.gz")
    write_field(np.zeros((4, 5, 6, 3), np.float32), Geometry((6, 5, 4), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)), other)
    cfg = CaseConfig(phantom_resolution=3.0, protocol="field", truth_field=other, device="cpu", max_steps=10)
    with pytest.raises(InputError, match="not on the planning image's grid.*size"):
        run_case(cfg)
    with pytest.raises(InputError, match="go together"):
        CaseConfig(protocol="field")


def test_make_truth_then_run_it_from_the_command_line(tmp_path, capsys):
    out = tmp_path / "truth"
    assert main(["make-truth", "--phantom-resolution", "3", "--cell-mm", "12", "--frames", "3", "--fps", "1",
                 "--load", "breathing,filling", "--out", str(out)]) == 0
    rec = json.loads((out / "truth.json").read_text())
    assert rec["frames"][2]["pancreas_mean_mm"] > 1.0 and "linear elasticity" in rec["made_by"]
    j = tmp_path / "r.json"
    assert main(["run", "--phantom-resolution", "3", "--truth-field", str(out / "fields" / "frame_0002.nii.gz"), "--targets",
                 "gt-inplane", "--device", "cpu", "--max-steps", "50", "--no-volume-registration", "--quiet", "--json", str(j)]) == 0
    res = json.loads(j.read_text())
    assert res["protocol"] == "field" and "linear elasticity" in res["gt"]["made_by"]
    assert res["results"]["initial"]["error_mm"] == pytest.approx(res["results"]["initial"]["organs"]["pancreas"]["error_mm"], rel=0.2)
    assert "every organ" in capsys.readouterr().out
    assert main(["make-truth", "--phantom-resolution", "3", "--load", "breathing,sneeze", "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()


def test_a_cine_series_from_finite_element_fields_tracked_and_evaluated(tmp_path):
    """make-truth -> make-cine --truth -> track -> evaluate-track: the cine's truth is the fields' motion of the
    particles, frame 0 (no motion) is the planning image's plane, and evaluate-track reads the fields directly
    to the same scores as the cine's own truth, every organ included."""
    from warpmpm.images import write_case

    lab, img = str(tmp_path / "labels.nii.gz"), str(tmp_path / "image.nii.gz")
    write_case(make_phantom(resolution=3.0), lab, img)
    truth, cine, track = tmp_path / "truth", tmp_path / "cine", tmp_path / "track"
    assert main(["make-truth", "--image", img, "--labels", lab, "--cell-mm", "12", "--frames", "3", "--fps", "2", "--out", str(truth)]) == 0
    assert main(["make-cine", "--image", img, "--labels", lab, "--truth", str(truth), "--plane", "sagittal,coronal",
                 "--format", "nifti", "--out", str(cine)]) == 0
    pos = np.load(cine / "truth" / "positions.npz")
    assert pos["truth_mm"].shape[0] == 3
    assert np.abs(pos["truth_mm"][0] - pos["planning_mm"]).max() == 0.0
    assert np.linalg.norm(pos["truth_mm"][2] - pos["planning_mm"], axis=1).mean() > 1.0
    assert main(["track", "--image", img, "--labels", lab, "--cine", str(cine / "cine"), "--out", str(track), "--device", "cpu",
                 "--estimator", "completion"]) == 0
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    assert main(["evaluate-track", "--track", str(track), "--truth", str(truth), "--json", str(a)]) == 0
    assert main(["evaluate-track", "--track", str(track), "--truth", str(cine / "truth"), "--json", str(b)]) == 0
    ea, eb = json.loads(a.read_text()), json.loads(b.read_text())
    for m in ("estimate", "propagate", "initial"):
        assert ea["results"][m]["error_mm"] == pytest.approx(eb["results"][m]["error_mm"], abs=1e-6)
        assert set(ea["results"][m]["organs"]) == {"pancreas", "stomach", "duodenum", "left_kidney"}
    assert ea["results"]["initial"]["organs"]["pancreas"]["error_mm"] > 0.3
    # --estimator completion: every organ within reach of a plane keeps the copy of the planes' motion
    for o, s in ea["results"]["estimate"]["organs"].items():
        assert s["error_mm"] == pytest.approx(ea["results"]["propagate"]["organs"][o]["error_mm"], abs=0.05), o
    with pytest.raises(SystemExit):
        main(["make-cine", "--truth", str(truth), "--out", str(tmp_path / "x"), "--frames"])
    assert main(["make-cine", "--truth", str(truth), "--out", str(tmp_path / "y")]) == 2  # no planning case given


def test_a_field_made_outside_the_project_is_the_truth(tmp_path):
    """A smooth B-spline deformation made by ITK (SimpleITK's TransformToDisplacementField, d(x) = T(x) - x) read as
    the truth: every particle's truth is T of its planning position, to the field's trilinear interpolation."""
    from warpmpm.experiment.case import prepare_case
    from warpmpm.experiment.truth import field_ground_truth

    case = make_phantom(resolution=3.0)
    ref = case.labels_image()
    tx = sitk.BSplineTransformInitializer(ref, [3, 3, 3])
    rng = np.random.default_rng(1)
    tx.SetParameters(rng.uniform(-4.0, 4.0, len(tx.GetParameters())).tolist())
    f = sitk.TransformToDisplacementField(tx, sitk.sitkVectorFloat64, ref.GetSize(), ref.GetOrigin(), ref.GetSpacing(), ref.GetDirection())
    p = str(tmp_path / "itk.nii.gz")
    sitk.WriteImage(sitk.Cast(f, sitk.sitkVectorFloat32), p)
    prep = prepare_case(CaseConfig(phantom_resolution=3.0, protocol="field", truth_field=p))
    gt = field_ground_truth(prep, p)
    x = prep.full_model.positions_mm
    expected = np.array([tx.TransformPoint(tuple(map(float, q))) for q in x])
    assert np.abs(expected - x).max() > 1.0  # it does move
    assert np.abs(gt.positions_mm - expected).max() < 0.05


def test_evaluate_track_refuses_the_truth_of_another_scan(tmp_path):
    """A track scored against fields on another grid (another scan's truth) is refused, not scored silently."""
    from warpmpm.experiment.cine_series import evaluate_track

    track = tmp_path / "track"
    (track / "labels").mkdir(parents=True)
    g = Geometry((6, 5, 4), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    sitk.WriteImage(g.apply_to(sitk.GetImageFromArray(np.zeros((4, 5, 6), np.uint8))), str(track / "labels" / "frame_0000.nii.gz"))
    x = np.zeros((3, 3))
    np.savez(track / "particles.npz", planning_mm=x, organ_index=np.zeros(3, int), organs=np.array(["pancreas"]),
             estimate_mm=x[None], propagate_mm=x[None])
    (track / "track.csv").write_text("frame,latency_s\n0,0.1\n")
    other = tmp_path / "truth"
    other.mkdir()
    write_field(np.zeros((4, 5, 7, 3), np.float32), Geometry((7, 5, 4), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0)), str(other / "frame_0000.nii.gz"))
    with pytest.raises(InputError, match="not on the track's planning grid"):
        evaluate_track(str(track), str(other))
    write_field(np.zeros((4, 5, 6, 3), np.float32), g, str(other / "frame_0000.nii.gz"))
    write_field(np.zeros((4, 5, 6, 3), np.float32), g, str(other / "frame_0001.nii.gz"))
    with pytest.raises(InputError, match="1 frames and the truth 2"):
        evaluate_track(str(track), str(other))
