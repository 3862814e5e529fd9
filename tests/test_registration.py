"""Issue 6: slice capture and 2D slice-to-slice registration."""

import numpy as np
import pytest
import SimpleITK as sitk

from conftest import data_case
from warpmpm.images import InputError, load_case
from warpmpm.phantom import make_phantom
from warpmpm.registration import register_slices, resample_slice_affine
from warpmpm.imaging import slice_mask
from warpmpm.slices import extract_slice


def known_affine():
    r, g, s = np.deg2rad(2.0), np.deg2rad(1.5), 0.9
    R = np.array([[np.cos(r), -np.sin(r)], [np.sin(r), np.cos(r)]])
    G = np.array([[1, np.tan(g)], [np.tan(g), 1]])
    return R @ G * s, np.array([5.0, -3.0])


def recover(case, orientation="axial", backend="itk"):
    g = case.geometry
    pan = case.labels == case.label_map["pancreas"]
    k = int(np.median(np.nonzero(pan)[0]))
    centre = g.center_mm()
    stored = extract_slice(case.image, g, orientation, k, centre)
    A, t = known_affine()
    captured = resample_slice_affine(stored, A, t)
    mask = slice_mask(case.labels, g, orientation, k, centre, case.label_map.values())
    reg = register_slices(stored, captured, centre, mask=mask, backend=backend)
    assert reg.ok
    # RMS over the slice's organ pixels, in mm
    m = sitk.GetArrayFromImage(mask) > 0
    jj, ii = np.nonzero(m)
    pts = np.array([stored.TransformIndexToPhysicalPoint((int(i), int(j))) for i, j in zip(ii, jj)])
    true = pts @ A.T + t
    got = pts @ reg.A.T + reg.t_mm
    return float(np.sqrt(np.mean(np.sum((got - true) ** 2, axis=1)))), reg


#: RMS error (mm) each backend is held to: ITK the first wave's 0.5 (measured 0.19 on the phantom, 0.15 on the MR
#: sample's 3 mm pixels: its gradient descent stops at a minimum step); Gauss-Newton measured 0.0005 and 0.0003, held
#: to 0.01. (Both sample the captured slice's pixels and interpolate the stored one, the interpolation that made the
#: captured slice here, so the correlation peaks exactly at the true affine; sampling the stored slice's pixels
#: instead, the peak sat 0.09 / 0.17 mm RMS from it.)
TOLERANCE_MM = {("phantom", "itk"): 0.5, ("mr", "itk"): 0.5, ("phantom", "gauss-newton"): 0.01, ("mr", "gauss-newton"): 0.01}


@pytest.mark.parametrize("backend", ["itk", "gauss-newton"])
def test_registration_recovers_known_affine_on_phantom(backend):
    rms, reg = recover(make_phantom(seed=0, resolution=1.5), backend=backend)
    assert rms < TOLERANCE_MM["phantom", backend], rms


@pytest.mark.parametrize("backend", ["itk", "gauss-newton"])
def test_registration_recovers_known_affine_on_real_mr(backend):
    labels, image = data_case("totalseg_mr")
    rms, _ = recover(load_case(labels, image, "totalseg_mr"), backend=backend)
    assert rms < TOLERANCE_MM["mr", backend], rms


def test_gauss_newton_refuses_a_flat_template_and_a_slice_that_misses_it():
    """No structure under the mask, or a captured slice that does not overlap the stored one's organs: not ok, with
    the reason, never a transform."""
    from warpmpm.gauss_newton import register_affine_gn

    rng = np.random.default_rng(0)
    img = sitk.GetImageFromArray(rng.normal(size=(40, 40)).astype(np.float32))
    flat = sitk.GetImageFromArray(np.ones((40, 40), np.float32))
    mask = sitk.GetImageFromArray(np.pad(np.ones((10, 10), np.uint8), 15))
    r = register_affine_gn(flat, img, mask)
    assert not r.ok and "constant" in r.stop
    far = sitk.GetImageFromArray(rng.normal(size=(40, 40)).astype(np.float32))
    far.SetOrigin((500.0, 500.0))
    r = register_affine_gn(img, far, mask)
    assert not r.ok and "overlap" in r.stop


@pytest.mark.parametrize("backend", ["itk", "gauss-newton"])
def test_blank_slice_refused(backend):
    blank = sitk.Image(32, 32, sitk.sitkFloat32)
    with pytest.raises(InputError, match="blank or constant"):
        register_slices(blank, blank, np.zeros(3), backend=backend)


def test_unknown_backend_refused():
    img = sitk.GetImageFromArray(np.random.default_rng(0).normal(size=(16, 16)).astype(np.float32))
    with pytest.raises(InputError, match="backend"):
        register_slices(img, img, np.zeros(3), backend="lbfgs")


def test_slice_outside_volume_refused(tiny_case):
    with pytest.raises(InputError, match="outside the volume"):
        extract_slice(tiny_case.image, tiny_case.geometry, "coronal", 10_000, np.zeros(3))


def test_gauss_newton_recovers_a_known_affine_through_noise_better_than_itk():
    """The known affine with Gaussian noise of 10 % of the slice's spread on the captured slice, five noise draws: the
    Gauss-Newton backend measured 0.019-0.046 mm RMS over the organ pixels (mean 0.035), ITK's 0.15-0.32 (mean
    0.23). Held to 0.1 mm for Gauss-Newton, and to at most half of ITK's on every draw."""
    case = make_phantom(seed=0, resolution=1.5)
    g = case.geometry
    k = int(np.median(np.nonzero(case.labels == case.label_map["pancreas"])[0]))
    centre = g.center_mm()
    stored = extract_slice(case.image, g, "axial", k, centre)
    A, t = known_affine()
    captured = resample_slice_affine(stored, A, t)
    mask = slice_mask(case.labels, g, "axial", k, centre, case.label_map.values())
    jj, ii = np.nonzero(sitk.GetArrayFromImage(mask))
    pts = np.array([stored.TransformIndexToPhysicalPoint((int(i), int(j))) for i, j in zip(ii, jj)])
    arr = sitk.GetArrayFromImage(captured)
    for seed in range(5):
        noisy = sitk.GetImageFromArray(arr + np.random.default_rng(seed).normal(0, 0.1 * arr.std(), arr.shape).astype(np.float32))
        noisy.CopyInformation(captured)
        err = {}
        for backend in ("itk", "gauss-newton"):
            r = register_slices(stored, noisy, centre, mask=mask, backend=backend)
            err[backend] = float(np.sqrt(np.mean(np.sum((pts @ r.A.T + r.t_mm - (pts @ A.T + t)) ** 2, axis=1))))
        assert err["gauss-newton"] < 0.1 and err["gauss-newton"] < 0.5 * err["itk"], (seed, err)


def test_gauss_newton_leaves_a_coarse_level_with_too_few_points_to_the_finer_ones():
    """A footprint at the slice's edge moving out of it: at the coarsest level (every 4th pixel) fewer than 30 of its
    points stay on the slice, which once failed the whole registration (and stopped the tracker on an interleaved
    series); the finer levels have enough and recover the 8 mm shift."""
    from warpmpm.gauss_newton import register_affine_gn

    img = sitk.GetImageFromArray(np.random.default_rng(0).normal(size=(40, 40)).astype(np.float32))
    img.SetSpacing((2.0, 2.0))
    stored = sitk.SmoothingRecursiveGaussian(img, 3.0)
    tx = sitk.TranslationTransform(2, (8.0, 0.0))  # captured(x) = stored(x + 8 mm): the content moves 8 mm to -u
    captured = sitk.Resample(stored, stored, tx, sitk.sitkLinear, 0.0)
    m = np.zeros((40, 40), np.uint8)
    m[4:36, 24:40] = 1  # at the +u edge: on the captured slice a quarter of it maps off the stored one
    mask = sitk.GetImageFromArray(m)
    mask.CopyInformation(stored)
    r = register_affine_gn(stored, captured, mask)
    assert r.ok, r.stop
    assert "skipped" not in r.stop
    np.testing.assert_allclose(r.t_mm + (r.A - np.eye(2)) @ np.array([62.0, 40.0]), [-8.0, 0.0], atol=0.05)
