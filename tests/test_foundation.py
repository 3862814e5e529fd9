"""Issue 2: reading images and labels, presets, the phantom, the particle model."""

import numpy as np
import pytest
import SimpleITK as sitk

from conftest import data_case
from warpmpm.images import InputError, crop_to_organs, load_case, mask_image, pad_square, parse_organs, resolve_labels, write_case
from warpmpm.metrics import correlation, dice
from warpmpm.model import build_model, voxelize
from warpmpm.phantom import make_phantom


@pytest.mark.parametrize("name,preset", [("totalseg_mr", "totalseg_mr"), ("totalseg_ct", "totalseg_ct")])
def test_sample_case_particles_match_voxels(name, preset):
    labels_path, image_path = data_case(name)
    case = load_case(labels_path, image_path, preset)
    model = build_model(case, "psdl")
    img = sitk.ReadImage(labels_path)
    arr = sitk.GetArrayFromImage(img)
    for organ, count in model.counts().items():
        assert count == int(np.sum(arr == case.label_map[organ])), organ
    # world coordinates equal SimpleITK's index-to-physical mapping (direction included: the CT is flipped)
    for p in np.random.default_rng(1).choice(model.n, 50, replace=False):
        expected = img.TransformIndexToPhysicalPoint([int(v) for v in model.voxel_ijk[p]])
        np.testing.assert_allclose(model.positions_mm[p], expected, atol=1e-6)
    # voxelising the model at rest gives back every organ's mask exactly
    for organ in model.organs:
        mask = voxelize(model.positions_mm, case.geometry, model.organ_slice(organ))
        assert dice(mask, arr == case.label_map[organ]) == 1.0
        assert np.array_equal(mask, arr == case.label_map[organ])


def test_phantom_deterministic_and_seeded():
    a = make_phantom(seed=3, resolution=2.0)
    b = make_phantom(seed=3, resolution=2.0)
    c = make_phantom(seed=4, resolution=2.0)
    assert np.array_equal(a.labels, b.labels) and np.array_equal(a.image, b.image)
    assert not np.array_equal(a.labels, c.labels)


def test_phantom_default_matches_paper_geometry_and_counts():
    case = make_phantom(seed=0)
    assert case.geometry.spacing_mm[2] == pytest.approx(3.0) and 1.2 <= case.geometry.spacing_mm[0] <= 1.5
    model = build_model(case, "psdl")
    # adult organ volumes (mL): pancreas ~70, stomach (empty to moderately filled) 150-600, duodenum ~40-120,
    # kidney ~120-200; the phantom's particle counts are these volumes over a 5.3 mm^3 voxel
    volumes = {"pancreas": (40, 110), "stomach": (150, 600), "duodenum": (35, 120), "left_kidney": (100, 250)}
    for seed in (0, 1, 2, 3):
        m = model if seed == 0 else build_model(make_phantom(seed=seed), "psdl")
        for organ, (lo, hi) in volumes.items():
            ml = m.counts()[organ] * m.volume_mm3[0] / 1000
            assert lo <= ml <= hi, (seed, organ, ml)
    # the counts sit inside the paper's AMOS ranges (particles per organ)
    ranges = {"pancreas": (7160, 71679), "stomach": (6914, 130371), "duodenum": (5177, 30234), "left_kidney": (21197, 125083)}
    for organ, (lo, hi) in ranges.items():
        assert lo <= model.counts()[organ] <= hi, organ
    assert np.array_equal(make_phantom(seed=0).labels, case.labels)  # the seed fixes the anatomy
    ks = np.unique(model.voxel_ijk[model.organ_slice("pancreas"), 2])
    assert len(ks) <= 40
    # the neighbours touch the pancreas (a face-adjacent voxel pair exists)
    pan = case.labels == case.label_map["pancreas"]
    grown = pan.copy()
    for ax in range(3):
        grown |= np.roll(pan, 1, ax) | np.roll(pan, -1, ax)
    for organ in ("stomach", "duodenum", "left_kidney"):
        assert np.any(grown & (case.labels == case.label_map[organ])), organ


def test_sampling_step_coarsens_and_keeps_slices(tiny_case):
    full = build_model(tiny_case, "psdl")
    coarse = build_model(tiny_case, "psdl", sampling_step=2)
    assert coarse.n < full.n / 3
    assert np.isclose(coarse.volume_mm3[0], 4 * full.volume_mm3[0])
    # exactly the voxels on even (i, j), every slice kept
    keep = (full.voxel_ijk[:, 0] % 2 == 0) & (full.voxel_ijk[:, 1] % 2 == 0)
    np.testing.assert_array_equal(coarse.voxel_ijk, full.voxel_ijk[keep])
    np.testing.assert_array_equal(coarse.positions_mm, full.positions_mm[keep])
    # every axial slice still carries particles (a thin tip of one organ may lose its few, not a slice of the model)
    assert set(np.unique(coarse.voxel_ijk[:, 2])) == set(np.unique(full.voxel_ijk[:, 2]))


def test_slice_counts_and_subset(tiny_model):
    counts = tiny_model.slice_counts("axial")
    assert counts.sum() == tiny_model.n
    k = int(np.argmax(counts[:, 0]))
    assert tiny_model.slice_mask("axial", k).sum() == counts[k].sum()
    p = tiny_model.subset(("pancreas",))
    assert p.counts() == {"pancreas": tiny_model.counts()["pancreas"]}
    assert np.array_equal(p.positions_mm, tiny_model.positions_mm[tiny_model.organ_slice("pancreas")])


def test_formats_roundtrip_and_preprocessing(tmp_path, tiny_case):
    for ext in ("mha", "nrrd", "nii.gz"):
        write_case(tiny_case, tmp_path / f"l.{ext}", tmp_path / f"i.{ext}")
        back = load_case(tmp_path / f"l.{ext}", tmp_path / f"i.{ext}", "amos")
        assert np.array_equal(back.labels, tiny_case.labels)
        np.testing.assert_allclose(back.geometry.origin_mm, tiny_case.geometry.origin_mm, atol=1e-4)
    cropped, off = crop_to_organs(tiny_case, ("pancreas",), margin_mm=10)
    assert cropped.labels.shape[2] < tiny_case.labels.shape[2]
    full = build_model(tiny_case, "p")
    crop = build_model(cropped, "p")
    np.testing.assert_allclose(full.positions_mm, crop.positions_mm, atol=1e-6)
    np.testing.assert_array_equal(full.voxel_ijk - np.array(off), crop.voxel_ijk)
    sq, _ = pad_square(tiny_case)
    assert sq.labels.shape[1] == sq.labels.shape[2]
    np.testing.assert_allclose(build_model(sq, "p").positions_mm, full.positions_mm, atol=1e-6)
    masked = mask_image(tiny_case, ("pancreas",))
    assert np.all(masked.image[tiny_case.labels != tiny_case.label_map["pancreas"]] == 0)


def test_bad_inputs(tmp_path, tiny_case):
    with pytest.raises(InputError, match="file not found"):
        load_case(tmp_path / "missing.nii.gz")
    (tmp_path / "junk.nii.gz").write_bytes(b"not an image")
    with pytest.raises(InputError, match="cannot read|corrupt"):
        load_case(tmp_path / "junk.nii.gz")
    write_case(tiny_case, tmp_path / "l.mha")
    img = tiny_case.intensity_image()
    img.SetOrigin((5000.0, 0.0, 0.0))
    sitk.WriteImage(img, str(tmp_path / "i.mha"))
    with pytest.raises(InputError, match="do not overlap.*origin"):
        load_case(tmp_path / "l.mha", tmp_path / "i.mha")
    with pytest.raises(InputError, match="unknown label preset"):
        resolve_labels("nope")
    with pytest.raises(InputError, match="holds no pancreas"):
        load_case(tmp_path / "l.mha", preset={"pancreas": 99, "stomach": 7})
    case = load_case(tmp_path / "l.mha", preset={"pancreas": 10, "stomach": 7, "duodenum": 55})
    with pytest.raises(InputError, match="duodenum.*absent"):
        build_model(case, "pd")
    with pytest.raises(InputError, match="empty organ combination"):
        parse_organs("")
    with pytest.raises(InputError, match="lacks the pancreas"):
        parse_organs("sd")
    with pytest.raises(InputError, match="unknown organ letter"):
        parse_organs("px")
    with pytest.raises(InputError, match="sampling step"):
        build_model(tiny_case, "p", sampling_step=0)


def test_dicom_series_folder(tmp_path):
    """A DICOM series folder reads with its geometry (written here slice by slice with SimpleITK)."""
    from warpmpm.images import read_volume

    arr = (np.arange(4 * 5 * 6).reshape(4, 5, 6) % 7).astype(np.int16)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((1.5, 1.5, 3.0))
    img.SetOrigin((10.0, 20.0, 30.0))
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    uid = "1.2.826.0.1.3680043.2.1125.4242"
    for k in range(arr.shape[0]):
        s = img[:, :, k]
        s.SetMetaData("0020|000e", uid)
        s.SetMetaData("0020|0032", "\\".join(str(v) for v in img.TransformIndexToPhysicalPoint((0, 0, k))))
        s.SetMetaData("0020|0013", str(k))
        s.SetMetaData("0008|0060", "MR")
        writer.SetFileName(str(tmp_path / f"{k}.dcm"))
        writer.Execute(s)
    vol = read_volume(tmp_path)
    assert vol.GetSize() == (6, 5, 4)
    np.testing.assert_allclose(vol.GetSpacing(), (1.5, 1.5, 3.0))
    np.testing.assert_allclose(vol.GetOrigin(), (10.0, 20.0, 30.0))
    assert np.array_equal(sitk.GetArrayFromImage(vol), arr)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no DICOM series"):
        read_volume(empty)


def test_a_label_map_on_a_reoriented_grid_is_resampled_onto_the_image(tmp_path, tiny_case):
    """TotalSegmentator's NIfTI beside a DICOM series may flip an axis: same region, another grid."""
    import warnings

    from warpmpm.errors import InputWarning

    write_case(tiny_case, tmp_path / "l.nii.gz", tmp_path / "i.nii.gz")
    lab = sitk.ReadImage(str(tmp_path / "l.nii.gz"))
    flipped = sitk.Flip(lab, [False, True, False])  # y reversed, the same physical region
    assert flipped.GetDirection() != lab.GetDirection()
    sitk.WriteImage(flipped, str(tmp_path / "flipped.nii.gz"))
    with pytest.warns(InputWarning, match="resampled onto the image's grid"):
        case = load_case(tmp_path / "flipped.nii.gz", tmp_path / "i.nii.gz")
    np.testing.assert_array_equal(case.labels, tiny_case.labels)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_case(tmp_path / "l.nii.gz", tmp_path / "i.nii.gz")  # the same grid: no warning


def test_merged_models_share_one_grid():
    """merge_models puts both blocks on one grid covering them: a slice index names the same plane for both blocks'
    particles (each particle's index is where it lies), the grid's centre is the scene's, and a block placed before
    the first shifts the first's indices; blocks on different lattices are refused."""
    from warpmpm.scenes import block_model, merge_models

    a = block_model((4, 3, 3), (2.0, 2.0, 2.0), "pancreas")
    b = block_model((3, 3, 3), (2.0, 2.0, 2.0), "duodenum", origin_mm=(8.0, 0.0, 0.0))
    for m in (merge_models(a, b), merge_models(b, a)):
        g = m.geometry
        assert g.size == (7, 3, 3)
        np.testing.assert_allclose(g.index_to_world(m.voxel_ijk), m.positions_mm, atol=1e-9)  # every index is where it lies
        np.testing.assert_allclose(g.center_mm(), [6.0, 2.0, 2.0])  # the box of both, not the first block's
        on = m.slice_mask("sagittal", 5)
        assert on.sum() == 9 and np.all(np.asarray(m.organs)[m.organ_index[on]] == "duodenum")
        assert m.slice_mask("sagittal", 1).sum() == 9 and np.all(np.asarray(m.organs)[m.organ_index[m.slice_mask("sagittal", 1)]] == "pancreas")
    before = block_model((2, 3, 3), (2.0, 2.0, 2.0), "stomach", origin_mm=(-4.0, 0.0, 0.0))
    m = merge_models(a, before)
    assert m.geometry.size == (6, 3, 3) and m.geometry.origin_mm == (-4.0, 0.0, 0.0)
    np.testing.assert_allclose(m.geometry.index_to_world(m.voxel_ijk), m.positions_mm, atol=1e-9)
    with pytest.raises(InputError, match="one voxel lattice"):
        merge_models(a, block_model((3, 3, 3), (2.0, 2.0, 2.0), "duodenum", origin_mm=(9.0, 0.0, 0.0)))
    with pytest.raises(InputError, match="one voxel lattice"):
        merge_models(a, block_model((3, 3, 3), (2.5, 2.0, 2.0), "duodenum", origin_mm=(10.0, 0.0, 0.0)))


def test_correlation_is_the_normalised_cross_correlation():
    """The one correlation the plane check and the registration passes score slices by: invariant to an intensity
    scale and offset, -1 for an inverted image, near 0 for independent noise, and the caller's value where an image
    is flat."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=2000)
    assert correlation(a, 2.5 * a + 7.0) == pytest.approx(1.0, abs=1e-12)
    assert correlation(a, -a) == pytest.approx(-1.0, abs=1e-12)
    assert abs(correlation(a, rng.normal(size=2000))) < 0.1
    b = 0.6 * a + 0.8 * rng.normal(size=2000)
    assert correlation(a, b) == pytest.approx(np.corrcoef(a, b)[0, 1], abs=1e-12)
    assert correlation(a, np.full(2000, 3.0)) == 0.0 and correlation(a, np.full(2000, 3.0), flat=-1.0) == -1.0
    assert correlation(np.zeros(0), np.zeros(0), flat=-1.0) == -1.0
