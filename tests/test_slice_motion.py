"""Issue 14 (in part): in-plane driving, orthogonal planes, organ-aware slice registration, fair baselines."""

import numpy as np
import pytest
import SimpleITK as sitk

from warpmpm.driving import ConvergenceConfig, SliceDrivenEstimator
from warpmpm.registration import register_slice_organs
from warpmpm.scenes import block_model
from warpmpm.slices import DrivingSlice, InPlaneAffine, in_plane_axes
from warpmpm.solvers import SolverConfig
from warpmpm.targets import affine_drive_targets, in_plane_truth_targets, plane_projector, slice_targets

CPU = SolverConfig(device="cpu")


def test_in_plane_driving_leaves_the_through_plane_coordinate_free():
    """Targets 3 mm above the slice and 2 mm along x: driven in-plane the slice follows x only; pinned, z too."""
    m = block_model((8, 8, 8), (2.0, 2.0, 2.0), "pancreas")
    sl = [DrivingSlice("axial", 4)]
    t = slice_targets(m, m.positions_mm, sl, lambda s, idx: m.positions_mm[idx] + [2.0, 0.0, 3.0])
    np.testing.assert_allclose(t.axes[0], np.diag([1.0, 1.0, 0.0]), atol=1e-12)
    np.testing.assert_allclose(t.targets_mm - m.positions_mm[t.idx], np.tile([2.0, 0.0, 0.0], (len(t.idx), 1)), atol=1e-9)
    moved = {}
    for mode in ("inplane", "pinned"):
        est = SliceDrivenEstimator(m, sl, solver_config=CPU, extra_points_mm=t.targets_mm + [0, 0, 3.0],
                                   convergence=ConvergenceConfig(max_steps=1500))
        targets = m.positions_mm[t.idx] + [2.0, 0.0, 3.0]  # a target with a through-plane part, as the GT's would be
        res = est.estimate(targets, axes=t.axes if mode == "inplane" else None)
        moved[mode] = (res.positions_mm - m.positions_mm)[t.idx].mean(0)
    assert moved["inplane"][0] > 1.5 and abs(moved["inplane"][2]) < 0.3   # x followed, z left to the physics
    assert moved["pinned"][0] > 1.5 and moved["pinned"][2] > 2.0           # pinned: z dragged to the target too


def test_two_orthogonal_planes_constrain_all_three_components_where_they_cross():
    m = block_model((8, 8, 8), (2.0, 2.0, 2.0), "pancreas")
    sl = [DrivingSlice("axial", 4), DrivingSlice("sagittal", 3)]
    truth = m.positions_mm + [1.0, 2.0, 3.0]
    t = in_plane_truth_targets(m, m.positions_mm, sl, truth)
    on_both = (m.voxel_ijk[t.idx, 2] == 4) & (m.voxel_ijk[t.idx, 0] == 3)
    only_axial = (m.voxel_ijk[t.idx, 2] == 4) & ~on_both
    assert on_both.sum() == 8 and only_axial.any()
    np.testing.assert_allclose(t.axes[on_both], np.tile(np.eye(3), (8, 1, 1)), atol=1e-9)   # x, y from axial; y, z from sagittal
    np.testing.assert_allclose(t.targets_mm[on_both], truth[t.idx][on_both], atol=1e-9)      # the whole 3D motion
    d = t.targets_mm[only_axial] - m.positions_mm[t.idx][only_axial]
    np.testing.assert_allclose(d, np.tile([1.0, 2.0, 0.0], (only_axial.sum(), 1)), atol=1e-9)  # the axial plane's part only
    np.testing.assert_allclose(plane_projector(m, "sagittal"), np.diag([0.0, 1.0, 1.0]), atol=1e-12)


def test_two_planes_disagreeing_on_a_shared_direction_are_averaged():
    m = block_model((4, 4, 4), (2.0, 2.0, 2.0), "pancreas")
    sl = [DrivingSlice("axial", 1), DrivingSlice("coronal", 2)]  # both measure x
    affines = [InPlaneAffine(np.eye(2), [1.0, 0.0]), InPlaneAffine(np.eye(2), [3.0, 0.0])]
    t = affine_drive_targets(m, m.positions_mm, sl, affines)
    both = (m.voxel_ijk[t.idx, 2] == 1) & (m.voxel_ijk[t.idx, 1] == 2)
    np.testing.assert_allclose((t.targets_mm - m.positions_mm[t.idx])[both, 0], 2.0, atol=1e-9)


def _textured(size=(96, 64), spacing=1.5, seed=0):
    rng = np.random.default_rng(seed)
    img = sitk.GetImageFromArray(rng.normal(0, 1, size[::-1]).astype(np.float32))
    img.SetSpacing((spacing, spacing))
    img.SetOrigin((-size[0] * spacing / 2, -size[1] * spacing / 2))
    return sitk.SmoothingRecursiveGaussian(img, 3.0)


@pytest.mark.parametrize("backend", ["itk", "gauss-newton"])
def test_organ_aware_registration_recovers_two_organs_sliding_where_one_affine_cannot(backend):
    """Left organ moves 3 mm up, right organ 2 mm down, along their shared boundary (sliding)."""
    stored = _textured()
    arr = sitk.GetArrayFromImage(stored)
    moves = {"pancreas": np.array([0.0, 3.0]), "duodenum": np.array([0.0, -2.0])}
    shifted = {}
    for organ, t in moves.items():
        tx = sitk.TranslationTransform(2, (-t).tolist())  # resampling maps output points back: x - t
        shifted[organ] = sitk.GetArrayFromImage(sitk.Resample(stored, stored, tx, sitk.sitkLinear, 0.0))
    cols = np.arange(arr.shape[1])
    left = cols < arr.shape[1] // 2
    captured = sitk.GetImageFromArray(np.where(left[None, :], shifted["pancreas"], shifted["duodenum"]).astype(np.float32))
    captured.CopyInformation(stored)
    masks = {}
    for organ, side in (("pancreas", left), ("duodenum", ~left)):
        m = np.zeros(arr.shape, np.uint8)
        m[8:-8, :][:, side] = 1
        m[:, np.abs(cols - arr.shape[1] // 2) < 4] = 0  # keep the footprints off the boundary itself
        mi = sitk.GetImageFromArray(m)
        mi.CopyInformation(stored)
        masks[organ] = mi
    whole_mask = sitk.Or(masks["pancreas"], masks["duodenum"])
    tiny = np.zeros(arr.shape, np.uint8)
    tiny[20:23, 20:23] = 1  # 9 pixels: too few to register on its own, reported as such
    masks["stomach"] = sitk.GetImageFromArray(tiny)
    masks["stomach"].CopyInformation(stored)
    candidates = {}
    whole, per_organ = register_slice_organs(stored, captured, np.zeros(3), whole_mask, masks, backend=backend,
                                             candidates=candidates)
    assert set(per_organ) == set(moves)
    assert {o: c["kept"] for o, c in candidates.items()} == {"pancreas": True, "duodenum": True, "stomach": False}
    assert candidates["stomach"]["registration"] is None and "9 pixels" in candidates["stomach"]["why"]
    assert candidates["pancreas"]["registration"] is per_organ["pancreas"]
    del masks["stomach"]
    for organ, t in moves.items():
        got = per_organ[organ].affine
        np.testing.assert_allclose(got.t_mm, t, atol=0.3)
        assert np.abs(got.A - np.eye(2)).max() < 0.02
    # one affine for the slice is off by more than 1 mm on at least one organ
    errs = [np.linalg.norm(whole.affine.t_mm - t) for t in moves.values()]
    assert max(errs) > 1.0


def test_propagate_uses_the_same_per_organ_slice_motion():
    from warpmpm.experiment.baselines import propagate
    from warpmpm.images import PRESETS, Case, Geometry
    from warpmpm.model import build_model

    lab = np.zeros((6, 10, 20), np.int32)
    lab[:, :, :10] = PRESETS["amos"]["pancreas"]
    lab[:, :, 10:] = PRESETS["amos"]["duodenum"]
    m = build_model(Case(lab, Geometry((20, 10, 6), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0)), dict(PRESETS["amos"])), "pd")
    whole = InPlaneAffine(np.eye(2), [1.0, 0.0])
    organs = {"pancreas": InPlaneAffine(np.eye(2), [0.0, 3.0])}
    out = propagate(m, DrivingSlice("axial", 2), whole, np.zeros(3), organs)
    d = out - m.positions_mm
    np.testing.assert_allclose(d[m.organ_slice("pancreas")], np.tile([0.0, 3.0, 0.0], (m.counts()["pancreas"], 1)), atol=1e-9)
    np.testing.assert_allclose(d[m.organ_slice("duodenum")], np.tile([1.0, 0.0, 0.0], (m.counts()["duodenum"], 1)), atol=1e-9)


def test_the_ceiling_baselines_copy_each_organs_true_motion_and_combine_the_planes():
    """Beside the gt / gt-inplane ceilings ``propagate`` copies each organ's in-plane affine fitted to its true motion
    on the slice, and ``propagate_planes`` combines the planes: a truth that moves each organ by its own 3D
    translation is reproduced exactly by the combined sagittal + coronal copy, and by neither plane alone."""
    from warpmpm.experiment.baselines import propagate
    from warpmpm.experiment.target_kinds import truth_organ_affines
    from warpmpm.images import PRESETS, Case, Geometry
    from warpmpm.model import build_model
    from warpmpm.targets import combine_planes

    lab = np.zeros((10, 10, 12), np.int32)  # (z, y, x): the pancreas below, the duodenum above
    lab[:5] = PRESETS["amos"]["pancreas"]
    lab[5:] = PRESETS["amos"]["duodenum"]
    m = build_model(Case(lab, Geometry((12, 10, 10), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0)), dict(PRESETS["amos"])), "pd")
    shift = {"pancreas": np.array([1.0, -2.0, 0.5]), "duodenum": np.array([-1.5, 0.7, 2.0])}
    truth = m.positions_mm.copy()
    for o, t in shift.items():
        truth[m.organ_slice(o)] += t
    centre = m.positions_mm.mean(0)
    slices = [DrivingSlice("sagittal", 6), DrivingSlice("coronal", 5)]  # each plane crosses both organs
    fits = truth_organ_affines(m, truth, slices, centre)
    assert all(set(fits[s]) == {"pancreas", "duodenum"} for s in slices)
    whole = {s: InPlaneAffine.fit(m.positions_mm, truth, *in_plane_axes(m, s.orientation), centre) for s in slices}
    copied = {s: propagate(m, s, whole[s], centre, fits[s]) for s in slices}
    combined = combine_planes(m, m.positions_mm, slices, lambda s, i: copied[s][i])
    np.testing.assert_allclose(combined, truth, atol=1e-6)
    for s in slices:  # one plane misses its normal component of every organ's motion
        assert np.abs(copied[s] - truth).max() > 0.4


@pytest.mark.parametrize("kind", ["gt-inplane", "registration", "registration-affine", "registration-bspline", "registration-demons"])
def test_every_target_kind_runs_end_to_end(kind):
    import warnings

    from warpmpm.experiment import CaseConfig, run_case

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = run_case(CaseConfig(phantom_resolution=3.0, protocol="contact", targets=kind, drive="inplane", device="cpu",
                                  baselines=("initial", "propagate"), max_steps=800))
    assert np.isfinite(out.estimate.error_mm) and out.drive == "inplane"
    assert np.isfinite(out.target_in_plane_error_mm)
    if kind == "gt-inplane":
        assert out.target_in_plane_error_mm < 1e-6
    else:
        assert out.registration is not None and "median_error_mm" in out.registration
    if kind == "registration-bspline":  # a field that folds falls back, and says so (tested on its own below)
        assert all("folds" in f for f in out.registration["fallbacks"])


@pytest.mark.parametrize("kind,function,message", [("registration-bspline", "register_slice_bspline", "B-spline field folds"),
                                                    ("registration-demons", "register_organ_demons", "demons field folds")])
def test_a_folding_deformable_field_falls_back_to_the_organ_aware_registration(monkeypatch, kind, function, message):
    """Whatever the field, a slice (B-spline) or an organ (demons) whose deformable motion folds gets the organ-aware
    targets, with a warning and the reason in the run's JSON (the coarse phantom's fields fold or not depending on
    the GT)."""
    import dataclasses
    import warnings

    import warpmpm.targets as T
    from warpmpm.experiment import CaseConfig, run_case

    real = getattr(T, function)

    def folding(*args, **kwargs):
        return dataclasses.replace(real(*args, **kwargs), ok=False, min_jacobian=-0.5)

    monkeypatch.setattr(T, function, folding)
    cfg = dict(phantom_resolution=3.0, protocol="contact", drive="inplane", device="cpu", baselines=("propagate",), max_steps=800)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = run_case(CaseConfig(targets=kind, **cfg))
    assert out.registration["fallbacks"] and "folds" in out.registration["fallbacks"][0]
    assert any(message in str(w.message) for w in caught)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        organs = run_case(CaseConfig(targets="registration", **cfg))
    assert out.estimate.error_mm == pytest.approx(organs.estimate.error_mm, abs=1e-9)  # the same targets as organ-aware


def _smoothly_warped_slice():
    """The phantom's mid-pancreas axial slice and the same slice under a known sinusoidal in-plane warp (up to 2 mm):
    ``(case, stored, captured, organs_mask, fwd, centre)``, ``fwd`` the warp of stored in-plane points (N, 2, mm)."""
    from warpmpm.phantom import make_phantom
    from warpmpm.imaging import slice_mask
    from warpmpm.slices import extract_slice

    case = make_phantom(resolution=1.0)
    k = int(np.median(np.nonzero(case.organ_mask("pancreas"))[0]))
    c = case.geometry.center_mm()
    stored = extract_slice(case.image, case.geometry, "axial", k, c)
    mask = slice_mask(case.labels, case.geometry, "axial", k, c, list(case.label_map.values()))

    def fwd(p):
        return p + np.stack([2.0 * np.sin(2 * np.pi * p[:, 1] / 120.0), 1.5 * np.cos(2 * np.pi * p[:, 0] / 150.0)], 1)

    q = _pixel_points(stored, np.ones(sitk.GetArrayViewFromImage(stored).shape, bool))
    p = q.copy()
    for _ in range(10):  # the captured image at q shows the stored point p with fwd(p) = q
        p = p - (fwd(p) - q)
    df = sitk.GetImageFromArray((p - q).reshape(sitk.GetArrayViewFromImage(stored).shape + (2,)), isVector=True)
    df.CopyInformation(stored)
    captured = sitk.Resample(stored, stored, sitk.DisplacementFieldTransform(sitk.Cast(df, sitk.sitkVectorFloat64)),
                             sitk.sitkLinear, 0.0)
    return case, stored, captured, mask, fwd, c, k


def _pixel_points(img, where):
    """In-plane positions (N, 2, mm) of the pixels of ``img`` where ``where`` (ny, nx) holds, row by row."""
    o, sp = np.asarray(img.GetOrigin()), np.asarray(img.GetSpacing())
    ys, xs = np.nonzero(where)
    return np.stack([o[0] + xs * sp[0], o[1] + ys * sp[1]], 1)


def test_a_known_smooth_deformation_of_a_slice_is_recovered_by_the_bspline_field():
    """A sinusoidal in-plane warp (up to 2 mm) of the phantom's mid-pancreas slice: the B-spline field recovers it
    within 0.5 mm RMS over the organs, where one affine is 1.7 mm off."""
    from warpmpm.registration import register_slice_bspline

    case, stored, captured, mask, fwd, c, _ = _smoothly_warped_slice()
    f = register_slice_bspline(stored, captured, c, mask)
    pts = _pixel_points(stored, sitk.GetArrayFromImage(sitk.BinaryErode(mask, [2, 2])))[::5]
    rms = np.sqrt(np.mean(np.sum((f.forward(pts) - fwd(pts)) ** 2, axis=1)))
    rms_affine = np.sqrt(np.mean(np.sum((pts @ f.affine.A.T + f.affine.t_mm - fwd(pts)) ** 2, axis=1)))
    assert f.ok and f.min_jacobian > 0.5
    assert rms < 0.5 and rms_affine > 1.0


def test_the_demons_refinement_recovers_a_known_deformation_over_an_organ_where_its_affine_cannot():
    """The same warp, one organ at a time: the demons field started from an organ's own registered affine follows
    the warp over that organ (measured 0.04 mm RMS over the pancreas, 0.004 over the stomach) where the affine
    cannot (0.70 and 0.75 mm RMS off: over one organ the warp is close to, not exactly, affine)."""
    from warpmpm.registration import register_organ_demons
    from warpmpm.imaging import slice_mask

    case, stored, captured, mask, fwd, c, k = _smoothly_warped_slice()
    own = {o: slice_mask(case.labels, case.geometry, "axial", k, c, [case.label_map[o]], dilate_mm=0.0) for o in case.label_map}
    whole, per_organ = register_slice_organs(stored, captured, c, mask, own)
    for organ in ("pancreas", "stomach"):
        start = per_organ.get(organ, whole).affine
        f = register_organ_demons(stored, captured, start, own[organ])
        pts = _pixel_points(stored, sitk.GetArrayFromImage(sitk.BinaryErode(own[organ], [1, 1])))
        rms = np.sqrt(np.mean(np.sum((f.forward(pts) - fwd(pts)) ** 2, axis=1)))
        rms_affine = np.sqrt(np.mean(np.sum((pts @ start.A.T + start.t_mm - fwd(pts)) ** 2, axis=1)))
        assert f.ok and f.min_jacobian > 0.5
        assert rms < 0.2 and rms_affine > 0.5, (organ, rms, rms_affine)


def test_a_particle_driven_along_no_direction_feels_no_force_even_with_a_carried_bias():
    """Interleaved planes drive one plane per frame: the other plane's particles get zero axes. Their held force
    from the previous frame (the carried bias) must not keep pushing them."""
    m = block_model((6, 6, 6), (2.0, 2.0, 2.0), "pancreas")
    idx = np.nonzero(m.voxel_ijk[:, 2] == 3)[0]
    est = SliceDrivenEstimator(m, driven=idx, solver_config=CPU, extra_points_mm=m.positions_mm + [0, 0, 4.0],
                               convergence=ConvergenceConfig(max_steps=400))
    est.estimate(m.positions_mm[idx] + [0.0, 0.0, 2.0])  # frame 1: lift the layer 2 mm (a bias is carried)
    after1 = est.positions_mm()[idx].copy()
    zero = np.zeros((len(idx), 3, 3))
    est.estimate(m.positions_mm[idx] + [0.0, 0.0, 4.0], axes=zero, convergence=ConvergenceConfig(max_steps=300, th_s=10**6))
    moved = est.positions_mm()[idx] - after1
    assert moved[:, 2].mean() < 0.2  # not dragged on to the new target, nor pushed by the old bias


@pytest.fixture(scope="module")
def phantom_case():
    from warpmpm.phantom import make_phantom

    return make_phantom(seed=0, resolution=2.0)  # the tiny one's 4 x 9 mm voxels register too coarsely


@pytest.mark.parametrize("backend", ["itk", "gauss-newton"])
def test_rendered_passes_recover_motion_through_two_orthogonal_planes(phantom_case, backend):
    """The whole image translated by t = (4, 3, 2) mm, imaged on a sagittal and a coronal plane through the pancreas:
    each plane's content changes with the motion through it (4 mm for the sagittal, 3 for the coronal), which a
    single registration reads as in-plane motion (2.2 mm off, measured). Registered again against the planning image
    moved by both planes' combined motion, each plane's reference holds what the other measured: 0.4-0.5 mm
    (measured), and every particle's combined motion follows t."""
    from warpmpm.model import build_model
    from warpmpm.targets import registration_targets

    case = phantom_case
    m = build_model(case, "psdl")
    k, j, i = (int(np.median(a)) for a in np.nonzero(case.organ_mask("pancreas")))
    t = np.array([4.0, 3.0, 2.0])
    img = case.intensity_image()
    moved = sitk.GetArrayFromImage(sitk.Resample(img, img, sitk.TranslationTransform(3, tuple(-t)), sitk.sitkLinear, 0.0))
    slices = [DrivingSlice("sagittal", i), DrivingSlice("coronal", j)]
    err, combined = {}, {}
    for passes in (1, 3):
        _, info = registration_targets(m, slices, case.image, moved, case.labels, case.geometry, case.label_map,
                                       case.geometry.center_mm(), truth_mm=m.positions_mm + t, passes=passes, backend=backend)
        pan = m.organ_slice("pancreas")
        err[passes] = info["error_mm"]
        combined[passes] = float(np.linalg.norm(info["combined_mm"][pan] - m.positions_mm[pan] - t, axis=1).mean())
    assert err[1] > 1.5  # measured 2.2 (both backends): the through-plane motion misread
    assert err[3] < 0.7 and err[3] < 0.35 * err[1]  # measured 0.43 (itk), 0.48 (gauss-newton)
    assert combined[3] < 1.2 and combined[3] < 0.4 * combined[1]  # measured 0.57 / 1.0 against 3.6 / 4.7


def test_bad_registration_passes_are_refused():
    from warpmpm.errors import InputError
    from warpmpm.experiment import CaseConfig

    for bad in (0, 6, 2.5, True):
        with pytest.raises(InputError, match="registration-passes"):
            CaseConfig(registration_passes=bad)
