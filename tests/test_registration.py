"""Issue 6: slice capture and 2D slice-to-slice registration."""

import numpy as np
import pytest
import SimpleITK as sitk

from conftest import data_case
from warpmpm.images import InputError, load_case
from warpmpm.phantom import make_phantom
from warpmpm.registration import extract_slice, register_slices, resample_slice_affine, slice_mask


def known_affine():
    r, g, s = np.deg2rad(2.0), np.deg2rad(1.5), 0.9
    R = np.array([[np.cos(r), -np.sin(r)], [np.sin(r), np.cos(r)]])
    G = np.array([[1, np.tan(g)], [np.tan(g), 1]])
    return R @ G * s, np.array([5.0, -3.0])


def recover(case, orientation="axial"):
    g = case.geometry
    pan = case.labels == case.label_map["pancreas"]
    k = int(np.median(np.nonzero(pan)[0]))
    centre = g.center_mm()
    stored = extract_slice(case.image, g, orientation, k, centre)
    A, t = known_affine()
    captured = resample_slice_affine(stored, A, t)
    mask = slice_mask(case.labels, g, orientation, k, centre, case.label_map.values())
    reg = register_slices(stored, captured, centre, mask=mask)
    assert reg.ok
    # RMS over the slice's organ pixels, in mm
    m = sitk.GetArrayFromImage(mask) > 0
    jj, ii = np.nonzero(m)
    pts = np.array([stored.TransformIndexToPhysicalPoint((int(i), int(j))) for i, j in zip(ii, jj)])
    true = pts @ A.T + t
    got = pts @ reg.A.T + reg.t_mm
    return float(np.sqrt(np.mean(np.sum((got - true) ** 2, axis=1)))), reg


def test_registration_recovers_known_affine_on_phantom():
    rms, reg = recover(make_phantom(seed=0, resolution=1.5))
    assert rms < 0.5, rms
    assert reg.wall_s < 5.0


def test_registration_recovers_known_affine_on_real_mr():
    labels, image = data_case("totalseg_mr")
    rms, _ = recover(load_case(labels, image, "totalseg_mr"))
    assert rms < 0.5, rms


def test_blank_slice_refused():
    blank = sitk.Image(32, 32, sitk.sitkFloat32)
    with pytest.raises(InputError, match="blank or constant"):
        register_slices(blank, blank, np.zeros(3))


def test_slice_outside_volume_refused(tiny_case):
    with pytest.raises(InputError, match="outside the volume"):
        extract_slice(tiny_case.image, tiny_case.geometry, "coronal", 10_000, np.zeros(3))
