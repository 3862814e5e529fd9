"""The planning image as a particle state shows it (the cine tracker's reference, the ground truths' images)."""

import dataclasses

import numpy as np
import pytest
import SimpleITK as sitk

from warpmpm.errors import InputError
from warpmpm.experiment.cine_series import slab_average
from warpmpm.imaging import render_plane, warp_volume


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
    from warpmpm.imaging import backward_displacement

    m = build_model(tiny_case, "psdl")
    t = np.array([1.0, 2.0, 3.0])
    g = tiny_case.geometry
    for geom in (g, g.crop((g.size[0] // 2 - 3, 0, 0), (g.size[0] // 2 + 4, g.size[1], g.size[2]))):
        f = sitk.GetArrayFromImage(backward_displacement(geom, m.positions_mm, m.positions_mm + t))
        np.testing.assert_allclose(f.reshape(-1, 3), np.tile(-t, (f.size // 3, 1)), rtol=0, atol=1e-3)


def _rotated_sphere():
    """A 2.5 mm lattice of particles in a 20 mm sphere, rotated 6 degrees about z and shifted (a field up to 3.7 mm that
    varies across the sphere), on a grid of 1.25 x 1.25 x 2.5 mm voxels (the far fill's coarse cells: 5 x 5 x 2 voxels);
    and each voxel's distance from the moved sphere's surface (mm)."""
    from warpmpm.images import Geometry

    g = Geometry((72, 64, 40), (1.25, 1.25, 2.5), (-45.0, -40.0, -50.0), (1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0))
    lattice = np.mgrid[-20:20.1:2.5, -20:20.1:2.5, -20:20.1:2.5].reshape(3, -1).T
    centre, shift = np.array([-5.0, 0.0, 0.0]), np.array([1.0, -2.0, 3.0])
    planning = lattice[np.linalg.norm(lattice, axis=1) <= 20.0] + centre
    a = np.radians(6.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    moved = (planning - centre) @ rot.T + centre + shift
    zz, yy, xx = np.meshgrid(*(np.arange(n) for n in g.size[::-1]), indexing="ij")
    voxels = g.index_to_world(np.stack([xx, yy, zz], -1).reshape(-1, 3)).reshape(*g.size[::-1], 3)
    return g, planning, moved, np.linalg.norm(voxels - (centre + shift), axis=-1) - 20.0


def test_the_coarse_far_fill_is_the_fine_one(monkeypatch):
    """The far fill (25 mm) smoothed on cells of 5 x 5 x 2 voxels and interpolated back is the fill smoothed on the
    voxels themselves: within 0.01 mm where the near fill weighs (within 8 mm of the particles; measured 0.0017) and
    0.05 mm elsewhere (measured 0.030) on a 3.7 mm field."""
    from warpmpm import imaging

    g, planning, moved, dist = _rotated_sphere()
    coarse = sitk.GetArrayFromImage(imaging.backward_displacement(g, planning, moved))
    monkeypatch.setattr(imaging, "FAR_CELLS_PER_SIGMA", 1e9)  # one voxel a cell: the fine far fill
    fine = sitk.GetArrayFromImage(imaging.backward_displacement(g, planning, moved))
    assert np.abs(fine).max() > 3.5
    diff = np.abs(coarse - fine).max(axis=-1)
    assert diff[dist < 8].max() < 0.01
    assert diff.max() < 0.05


def test_a_slab_field_sees_the_particles_beyond_the_slab():
    """The field on a 15 mm slab with the whole grid as ``far_geometry`` (as render_plane builds it) is the whole
    grid's field there, away from the particles where the far fill decides (measured: within 0.032 mm; the slab's
    own far fill, which sees only the particles inside it, is up to 0.29 mm off). A grid the slab is no crop of is
    refused."""
    from warpmpm.imaging import backward_displacement

    g, planning, moved, dist = _rotated_sphere()
    whole = sitk.GetArrayFromImage(backward_displacement(g, planning, moved))
    lo, hi = (30, 0, 0), (42, g.size[1], g.size[2])
    far = dist[:, :, lo[0]:hi[0]] >= 8
    slab = sitk.GetArrayFromImage(backward_displacement(g.crop(lo, hi), planning, moved, far_geometry=g))
    own = sitk.GetArrayFromImage(backward_displacement(g.crop(lo, hi), planning, moved))
    assert np.abs(slab - whole[:, :, lo[0]:hi[0]]).max(axis=-1)[far].max() < 0.05
    assert np.abs(own - whole[:, :, lo[0]:hi[0]]).max(axis=-1)[far].max() > 0.2
    with pytest.raises(InputError, match="crop"):
        backward_displacement(g.crop(lo, hi), planning, moved, far_geometry=dataclasses.replace(g, spacing_mm=(1.3, 1.25, 2.5)))
    with pytest.raises(InputError, match="crop"):  # a far grid that does not hold the slab
        backward_displacement(g.crop(lo, hi), planning, moved, far_geometry=g.crop((36, 0, 0), g.size))


def test_a_field_returned_on_a_thin_crop_is_the_crop_of_the_whole_field():
    """render_plane asks for the field on the frame's thickness only: smoothed along the cut axis over the whole slab
    and along the other two over the crop (the Gaussian is separable), it is the whole slab's field cut to the crop, to
    float32 rounding; a crop cutting two axes takes the general path, with the same result."""
    from warpmpm.imaging import backward_displacement

    g, planning, moved, _ = _rotated_sphere()
    slab = g.crop((24, 0, 0), (48, g.size[1], g.size[2]))
    whole = sitk.GetArrayFromImage(backward_displacement(slab, planning, moved, far_geometry=g))
    for lo, hi in (((10, 0, 0), (15, g.size[1], g.size[2])), ((10, 5, 0), (15, 60, g.size[2]))):
        thin = slab.crop(lo, hi)
        part = sitk.GetArrayFromImage(backward_displacement(slab, planning, moved, far_geometry=g, out_geometry=thin))
        want = whole[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
        assert part.shape == want.shape and np.abs(want).max() > 2.0
        np.testing.assert_allclose(part, want, rtol=0, atol=1e-5)


def test_far_from_the_organs_the_field_is_continuous_and_within_the_particles_motion():
    """The default phantom under a smooth non-rigid motion (breathing growing to 10 mm along the body, 3 degrees about
    z): every voxel's backward displacement lies within the particles' range (a weighted mean of their displacements),
    and 40 mm and more from every particle the field changes between neighbouring voxels at most 1.5x as fast as it
    does within 8 mm of the organs (measured: 0.26 against 0.30 mm/mm; before, the fill switched to the particles' mean
    where its weights fell below 1e-3 of their peak: 1.43 mm/mm, a jump of 3.8 mm between two voxels 3 mm apart, and
    values up to 2.2 mm outside the particles' range)."""
    from warpmpm.model import build_model
    from warpmpm.phantom import make_phantom
    from warpmpm.imaging import backward_displacement

    case = make_phantom(seed=0)
    m = build_model(case, "psdl", sampling_step=2)
    g = case.geometry
    p = m.positions_mm
    c = p.mean(axis=0)
    a = np.radians(3.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    moved = (p - c) @ rot.T + c
    moved[:, 2] += 10.0 * (p[:, 2] - p[:, 2].min()) / np.ptp(p[:, 2])
    f = sitk.GetArrayFromImage(backward_displacement(g, p, moved)).astype(np.float64)
    back = p - moved
    assert np.all(f >= back.min(axis=0) - 1e-4) and np.all(f <= back.max(axis=0) + 1e-4)
    ijk = np.rint(g.world_to_index(moved)).astype(int)
    occupied = np.zeros(g.size[::-1], dtype=np.uint8)
    occupied[ijk[:, 2], ijk[:, 1], ijk[:, 0]] = 1
    dist = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(g.apply_to(sitk.GetImageFromArray(occupied)), insideIsPositive=False,
                                                              squaredDistance=False, useImageSpacing=True))
    near, far = [], []
    for axis, spacing in enumerate(g.spacing_mm[::-1]):  # z, y, x
        rate = np.abs(np.diff(f, axis=axis)).max(axis=-1) / spacing
        d = np.minimum(np.delete(dist, -1, axis=axis), np.delete(dist, 0, axis=axis))  # the nearer voxel of each pair
        near.append(rate[d < 8.0].max())
        far.append(rate[d >= 40.0].max())
    assert np.abs(f).max() > 9.0 and (dist >= 40.0).mean() > 0.05
    assert max(far) < 1.5 * max(near)
