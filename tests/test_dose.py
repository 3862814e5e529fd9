"""Dose from motion: each organ's dose through the estimated motion, against analytic answers."""

import numpy as np
import pytest
import SimpleITK as sitk

from warpmpm.dose import DoseAccumulator, dose_metrics, read_dose
from warpmpm.errors import InputError
from warpmpm.images import Geometry

G = Geometry((20, 16, 12), (2.0, 2.0, 3.0), (-20.0, -16.0, -18.0))


def linear_dose(slope_gy_per_mm=0.5, base=40.0, geometry=G):
    """A dose that rises along z (superior) by ``slope`` Gy/mm, on a grid larger than the planning grid."""
    big = Geometry((30, 26, 50), (2.0, 2.0, 2.0), (-30.0, -26.0, -50.0))
    k = np.arange(big.size[2]) * big.spacing_mm[2] + big.origin_mm[2]
    arr = np.broadcast_to((base + slope_gy_per_mm * k)[:, None, None], big.size[::-1]).astype(np.float32)
    return big.apply_to(sitk.GetImageFromArray(np.ascontiguousarray(arr)))


def organ():
    m = np.zeros(G.size[::-1], bool)
    m[3:9, 4:12, 5:15] = True
    return m


def test_rigid_shift_through_a_dose_gradient_adds_slope_times_shift():
    """Every frame moves the organ 4 mm superior through a 0.5 Gy/mm gradient: every voxel gets 2 Gy more (exact,
    trilinear sampling is exact on a linear dose), so D95, D98, Dmax and Dmean all rise by 2 Gy."""
    acc = DoseAccumulator(linear_dose(), G, {"pancreas": organ()})
    shift = np.zeros(G.size[::-1] + (3,))
    shift[..., 2] = 4.0
    for _ in range(3):
        acc.add(shift)
    a = acc.accumulated()["pancreas"]
    assert np.allclose(a - acc.planned["pancreas"], 2.0, atol=1e-4)
    rows = {r["metric"]: r for r in acc.metrics()}
    for m in ("D98_Gy", "D95_Gy", "Dmax_Gy", "Dmean_Gy", "D1cc_Gy"):
        assert rows[m]["difference"] == pytest.approx(2.0, abs=1e-4), m


def test_frames_are_weighted_by_beam_on_time():
    """Two frames, +4 mm (beam on 3 s) and -4 mm (beam on 1 s): the mean shift is +2 mm, so +1 Gy; a frame with the
    beam off adds nothing."""
    acc = DoseAccumulator(linear_dose(), G, {"pancreas": organ()})
    up, down = np.zeros(G.size[::-1] + (3,)), np.zeros(G.size[::-1] + (3,))
    up[..., 2], down[..., 2] = 4.0, -4.0
    acc.add(up, 3.0)
    acc.add(down, 1.0)
    acc.add(up * 10, 0.0)
    assert np.allclose(acc.accumulated()["pancreas"] - acc.planned["pancreas"], 1.0, atol=1e-4)
    with pytest.raises(InputError, match="weight must be finite"):
        acc.add(up, float("nan"))


def test_uniform_dose_is_unchanged_by_any_motion():
    arr = np.full((20, 20, 20), 50.0, np.float32)
    dose = Geometry((20, 20, 20), (4.0, 4.0, 4.0), (-40.0, -40.0, -40.0)).apply_to(sitk.GetImageFromArray(arr))
    acc = DoseAccumulator(dose, G, {"duodenum": organ()})
    acc.add(np.random.default_rng(1).normal(scale=3.0, size=G.size[::-1] + (3,)))
    assert np.allclose(acc.accumulated()["duodenum"], 50.0, atol=1e-4)


def test_dose_volume_figures_of_a_known_distribution():
    """Doses 1..100 Gy in 100 voxels of 0.5 cm^3: D95 = 6 (95 voxels get at least 6), D98 = 3, D0.5cc = 100 (the
    hottest voxel), D1cc = 99 (the two hottest), Dmax = 100, Dmean = 50.5."""
    m = dose_metrics(np.arange(1, 101, dtype=float)[::-1].copy(), 0.5)
    assert (m["D95_Gy"], m["D98_Gy"], m["D0.5cc_Gy"], m["D1cc_Gy"], m["Dmax_Gy"], m["Dmean_Gy"]) == (6, 3, 100, 99, 100, 50.5)


def test_rtdose_round_trip_and_reversed_frames(tmp_path, tiny_case):
    import pydicom

    from warpmpm.dicom_rt import write_rtdose, write_series

    ref = write_series(tiny_case.intensity_image(), str(tmp_path / "series"), "MR")
    g = ref.geometry
    k = np.arange(g.size[2])[:, None, None] * np.ones(g.size[::-1])
    d = 10.0 + 2.0 * k
    write_rtdose(str(tmp_path / "RD.dcm"), ref, d)
    img = read_dose(str(tmp_path / "RD.dcm"))
    assert np.abs(sitk.GetArrayFromImage(img) - d).max() < 1e-3 * d.max()
    assert np.allclose(img.GetOrigin(), g.origin_mm) and np.allclose(img.GetSpacing(), g.spacing_mm)
    # the same dose stored top-down (frames in decreasing z, negative offsets), as some planning systems write it
    ds = pydicom.dcmread(str(tmp_path / "RD.dcm"))
    n = int(ds.NumberOfFrames)
    arr = ds.pixel_array.reshape(n, int(ds.Rows), int(ds.Columns))[::-1]
    top = np.array([float(x) for x in ds.ImagePositionPatient])
    top[2] += (n - 1) * g.spacing_mm[2]
    ds.ImagePositionPatient = [f"{v:.4f}" for v in top]
    ds.GridFrameOffsetVector = [f"{-i * g.spacing_mm[2]:.4f}" for i in range(n)]
    ds.PixelData = np.ascontiguousarray(arr).tobytes()
    ds.save_as(str(tmp_path / "RD_down.dcm"))
    down = read_dose(str(tmp_path / "RD_down.dcm"))
    pts = g.index_to_world(np.array([[3.0, 4.0, k] for k in range(g.size[2])]))
    from warpmpm.dose import _sample

    assert np.allclose(_sample(down, pts)[0], _sample(img, pts)[0], atol=1e-3 * d.max())


def test_a_dose_that_misses_every_organ_is_refused():
    far = Geometry((5, 5, 5), (2.0, 2.0, 2.0), (500.0, 500.0, 500.0)).apply_to(sitk.GetImageFromArray(np.ones((5, 5, 5), np.float32)))
    with pytest.raises(InputError, match="zero on every organ"):
        DoseAccumulator(far, G, {"pancreas": organ()})
