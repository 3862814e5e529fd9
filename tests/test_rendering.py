"""The planning image as a particle state shows it (the cine tracker's reference, the ground truths' images)."""

import numpy as np
import pytest
import SimpleITK as sitk

from warpmpm.errors import InputError
from warpmpm.experiment.cine_series import slab_average
from warpmpm.rendering import render_plane, warp_volume


def _sagittal(case, i, thickness_mm):
    """A one-voxel sagittal plane image through planning voxel column ``i``, labelled ``thickness_mm`` thick."""
    plane = case.intensity_image()[i:i + 1, :, :]
    sp = list(plane.GetSpacing())
    sp[0] = thickness_mm
    plane.SetSpacing(sp)
    return plane


def test_the_planning_state_renders_the_planning_slab(tiny_case):
    """At the planning positions the render is the planning image averaged over the slice thickness with a box
    profile: a slice two voxels thick is half its centre voxel and a quarter of each neighbour (the sub-plane
    midpoint rule against the voxel weights of ``slab_average``, two independent ways to the same average)."""
    from warpmpm.model import build_model

    m = build_model(tiny_case, "psdl")
    i = int(np.median(np.nonzero(tiny_case.organ_mask("pancreas"))[2]))
    s = tiny_case.geometry.spacing_mm[0]
    for thickness in (s, 2 * s):
        out = sitk.GetArrayFromImage(render_plane(tiny_case, m.positions_mm, m.positions_mm, _sagittal(tiny_case, i, thickness),
                                                  np.array([1.0, 0, 0]), thickness))
        want = slab_average(tiny_case.image, 2, i, thickness / tiny_case.geometry.spacing_mm[0])
        np.testing.assert_allclose(out, want, rtol=0, atol=1e-3 * np.ptp(tiny_case.image))
    centre = tiny_case.image[:, :, i:i + 1]
    assert np.abs(out - centre).max() > 0.05 * np.ptp(tiny_case.image)  # the two-voxel slab is not the centre plane


def test_a_translated_state_renders_the_translated_image(tiny_case):
    """Every particle moved by t: the backward field is -t wherever the particles reach, so the render is the
    planning image sampled at x - t on the plane; and the render of the slab agrees with the whole-volume warp."""
    from warpmpm.model import build_model

    m = build_model(tiny_case, "psdl")
    i = int(np.median(np.nonzero(tiny_case.organ_mask("pancreas"))[2]))
    t = np.array([0.0, 2.5, -4.0])
    plane = _sagittal(tiny_case, i, 3.0)
    out = sitk.GetArrayFromImage(render_plane(tiny_case, m.positions_mm, m.positions_mm + t, plane, np.array([1.0, 0, 0]), 3.0))
    tx = sitk.TranslationTransform(3, tuple(-t))
    want = sitk.GetArrayFromImage(sitk.Resample(tiny_case.intensity_image(), plane, tx, sitk.sitkLinear, 0.0))
    labels = tiny_case.geometry.apply_to(sitk.GetImageFromArray((tiny_case.labels > 0).astype(np.uint8)))
    organs = sitk.GetArrayFromImage(sitk.Resample(sitk.BinaryDilate(labels, [2, 2, 1]), plane, tx, sitk.sitkNearestNeighbor, 0)) > 0
    assert organs.sum() > 100  # the moved organs and 8 mm around them: where the tracker registers
    np.testing.assert_allclose(out[organs], want[organs], rtol=0, atol=1e-3 * np.ptp(tiny_case.image))
    full = warp_volume(tiny_case, m.positions_mm, m.positions_mm + t)[:, :, i:i + 1]
    np.testing.assert_allclose(out[organs], full[organs], rtol=0, atol=1e-3 * np.ptp(tiny_case.image))
    identity = sitk.GetArrayFromImage(plane)
    assert np.abs(out[organs] - identity[organs]).max() > 0.2 * np.ptp(tiny_case.image)  # the motion shows


def test_bad_rendering_input_is_refused(tiny_case):
    from warpmpm.model import build_model

    m = build_model(tiny_case, "psdl")
    plane = _sagittal(tiny_case, 5, 3.0)
    with pytest.raises(InputError, match="thickness"):
        render_plane(tiny_case, m.positions_mm, m.positions_mm, plane, np.array([1.0, 0, 0]), 0.0)
    far = sitk.Image(plane)
    far.SetOrigin(tuple(np.asarray(plane.GetOrigin()) + [500.0, 0, 0]))
    with pytest.raises(InputError, match="does not cross"):
        render_plane(tiny_case, m.positions_mm, m.positions_mm, far, np.array([1.0, 0, 0]), 3.0)
    with pytest.raises(InputError, match="sigma_mm"):
        render_plane(tiny_case, m.positions_mm, m.positions_mm, plane, np.array([1.0, 0, 0]), 3.0, sigma_mm=float("nan"))


def test_a_uniform_translation_moves_every_voxel_by_it(tiny_case):
    """Every particle moved by t: the backward field is -t at every voxel, near the organs and far from them, on the
    whole grid and on a thin slab of it (far from every particle the normalised fill's weights fall into the
    recursive filter's error: before the fallback 5 % of this grid's voxels read up to 1e6 mm)."""
    from warpmpm.model import build_model
    from warpmpm.rendering import backward_displacement

    m = build_model(tiny_case, "psdl")
    t = np.array([1.0, 2.0, 3.0])
    g = tiny_case.geometry
    for geom in (g, g.crop((g.size[0] // 2 - 3, 0, 0), (g.size[0] // 2 + 4, g.size[1], g.size[2]))):
        f = sitk.GetArrayFromImage(backward_displacement(geom, m.positions_mm, m.positions_mm + t))
        np.testing.assert_allclose(f.reshape(-1, 3), np.tile(-t, (f.size // 3, 1)), rtol=0, atol=1e-3)
