"""Reading 3D images and label maps, label presets, and the paper's preprocessing.

Every volume keeps its physical geometry (origin, spacing, direction) so that all positions the
package reports are world (scanner) coordinates in millimetres, as SimpleITK defines them:
``world = origin + direction @ (spacing * index)`` with ``index = (i, j, k)`` along the image's
x, y, z axes.

Arrays follow SimpleITK's numpy convention: ``array[k, j, i]`` (z, y, x).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

import numpy as np
import SimpleITK as sitk

import warnings

from .errors import InputError, InputWarning

__all__ = ["ORGANS", "ORGAN_LETTERS", "COMBINATIONS", "PRESETS", "resolve_labels", "parse_organs",
           "organs_to_letters", "Geometry", "grid_differences", "check_file_integrity", "read_volume", "Case",
           "load_case", "MAX_ORGAN_VOLUME_ML", "MAX_DISTANCE_TO_PANCREAS_MM", "plausibility_warnings",
           "crop_to_organs", "pad_square", "mask_image", "write_case", "ORIENTATION_WORLD_AXIS",
           "orientation_image_axis"]

#: Organ names in the method's order and their one-letter codes (the paper's ``psdl``).
ORGANS = ("pancreas", "stomach", "duodenum", "left_kidney")
ORGAN_LETTERS = {"p": "pancreas", "s": "stomach", "d": "duodenum", "l": "left_kidney"}
#: The paper's organ combinations: the pancreas always, with any subset of the other three.
COMBINATIONS = ("p", "ps", "pd", "pl", "psd", "psl", "pdl", "psdl")

#: Label presets: organ name -> label value in the label map.
PRESETS: dict[str, dict[str, int]] = {
    # AMOS 2022 (the paper's data)
    "amos": {"left_kidney": 3, "stomach": 7, "pancreas": 10, "duodenum": 13},
    # TotalSegmentator v2 `total` task (CT)
    "totalseg_ct": {"left_kidney": 3, "stomach": 6, "pancreas": 7, "duodenum": 19},
    # TotalSegmentator `total_mr` task
    "totalseg_mr": {"left_kidney": 3, "stomach": 6, "pancreas": 7, "duodenum": 14},
}


def resolve_labels(preset: str | dict[str, int]) -> dict[str, int]:
    """Return the organ -> label mapping for a preset name or a user mapping.

    A user mapping may name any subset of :data:`ORGANS` (pancreas is required by the method
    but checked where a model is built). Raises :class:`InputError` for unknown presets/organs.
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise InputError(f"unknown label preset {preset!r}; choose one of {sorted(PRESETS)} or pass a mapping")
        return dict(PRESETS[preset])
    mapping = dict(preset)
    for organ, value in mapping.items():
        if organ not in ORGANS:
            raise InputError(f"unknown organ {organ!r} in label mapping; organs are {ORGANS}")
        if int(value) != value or value <= 0:
            raise InputError(f"label of {organ!r} must be a positive integer, got {value!r}")
    return {k: int(v) for k, v in mapping.items()}


def parse_organs(combination: str) -> tuple[str, ...]:
    """Organ names from the paper's letters (``p, ps, pd, pl, psd, psl, pdl, psdl``).

    The pancreas is always part of the model; letters may come in any order.
    """
    if not combination:
        raise InputError("empty organ combination; use letters from 'psdl' with 'p' included, e.g. 'psdl'")
    bad = [c for c in combination if c not in ORGAN_LETTERS]
    if bad:
        raise InputError(f"unknown organ letter(s) {''.join(bad)!r} in {combination!r}; use p, s, d, l")
    if "p" not in combination:
        raise InputError(f"organ combination {combination!r} lacks the pancreas 'p', which is always modelled")
    return tuple(o for o in ORGANS if any(ORGAN_LETTERS[c] == o for c in combination))


def organs_to_letters(organs) -> str:
    inv = {v: k for k, v in ORGAN_LETTERS.items()}
    return "".join(inv[o] for o in ORGANS if o in organs)


@dataclass(frozen=True)
class Geometry:
    """Physical geometry of a 3D image grid.

    Attributes:
        size: number of voxels along x, y, z (SimpleITK order).
        spacing_mm: voxel size along x, y, z in mm.
        origin_mm: world position of voxel (0, 0, 0) in mm.
        direction: 3x3 direction cosines, columns are the image axes in world coordinates.
    """

    size: tuple[int, int, int]
    spacing_mm: tuple[float, float, float]
    origin_mm: tuple[float, float, float]
    direction: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)

    @staticmethod
    def of(image: sitk.Image) -> "Geometry":
        return Geometry(
            tuple(int(s) for s in image.GetSize()),
            tuple(float(s) for s in image.GetSpacing()),
            tuple(float(s) for s in image.GetOrigin()),
            tuple(float(s) for s in image.GetDirection()),
        )

    @property
    def direction_matrix(self) -> np.ndarray:
        return np.asarray(self.direction, dtype=np.float64).reshape(3, 3)

    @property
    def voxel_volume_mm3(self) -> float:
        return float(np.prod(self.spacing_mm))

    def index_to_world(self, ijk: np.ndarray) -> np.ndarray:
        """World positions (mm) of continuous indices ``ijk`` (N, 3) in (i, j, k) order."""
        ijk = np.asarray(ijk, dtype=np.float64)
        scaled = ijk * np.asarray(self.spacing_mm)
        return scaled @ self.direction_matrix.T + np.asarray(self.origin_mm)

    def world_to_index(self, xyz: np.ndarray) -> np.ndarray:
        """Continuous (i, j, k) indices of world positions ``xyz`` (N, 3) in mm."""
        xyz = np.asarray(xyz, dtype=np.float64) - np.asarray(self.origin_mm)
        local = xyz @ np.linalg.inv(self.direction_matrix).T
        return local / np.asarray(self.spacing_mm)

    def axis_world_direction(self, axis: int) -> np.ndarray:
        return self.direction_matrix[:, axis]

    def center_mm(self) -> np.ndarray:
        """World position of the volume's centre (the paper's 'image centre')."""
        return self.index_to_world((np.asarray(self.size, dtype=np.float64) - 1.0)[None, :] / 2.0)[0]

    def apply_to(self, image: sitk.Image) -> sitk.Image:
        image.SetSpacing(self.spacing_mm)
        image.SetOrigin(self.origin_mm)
        image.SetDirection(self.direction)
        return image

    def crop(self, lo: tuple[int, int, int], hi: tuple[int, int, int]) -> "Geometry":
        """Geometry of the sub-grid of voxel indices ``lo <= ijk < hi``."""
        origin = self.index_to_world(np.asarray(lo, dtype=np.float64)[None, :])[0]
        return replace(self, size=tuple(int(h - l) for l, h in zip(lo, hi)), origin_mm=tuple(float(v) for v in origin))


def grid_differences(a: Geometry, b: Geometry, tol_mm: float = 1e-3) -> list[str]:
    """Human-readable list of how two grids differ (empty when they match)."""
    out = []
    if a.size != b.size:
        out.append(f"size {a.size} vs {b.size}")
    if not np.allclose(a.spacing_mm, b.spacing_mm, atol=tol_mm):
        out.append(f"spacing {a.spacing_mm} vs {b.spacing_mm} mm")
    if not np.allclose(a.origin_mm, b.origin_mm, atol=tol_mm):
        out.append(f"origin {a.origin_mm} vs {b.origin_mm} mm")
    if not np.allclose(a.direction, b.direction, atol=1e-4):
        out.append(f"direction {a.direction} vs {b.direction}")
    return out


def check_file_integrity(path: str) -> None:
    """Refuse a truncated or corrupt file that ITK would read as data (it fills what is missing with zeros).

    A gzip stream (``.gz``) must decompress to its end-of-stream marker with a matching CRC; a NIfTI-1
    file must hold as many voxel bytes as its header announces, and no NaN or Inf in floating-point
    voxels (ITK reads those as 0).
    """
    import gzip
    import struct
    import zlib

    name = path.lower()
    if not (name.endswith(".gz") or name.endswith(".nii")):
        return
    if name.endswith(".gz"):
        try:
            with gzip.open(path, "rb") as f:
                data = f.read()
        except (EOFError, OSError, zlib.error) as exc:
            raise InputError(f"{path} is truncated or corrupt (its gzip stream is broken: {exc}); "
                             "copy it again from the source") from None
    else:
        with open(path, "rb") as f:
            data = f.read()
    if not (name.endswith(".nii") or name.endswith(".nii.gz")) or len(data) < 348:
        return
    for endian in ("<", ">"):
        if struct.unpack(endian + "i", data[:4])[0] == 348:
            break
    else:
        return  # not NIfTI-1 (NIfTI-2 or another format): ITK's own checks apply
    dims = struct.unpack(endian + "8h", data[40:56])
    bitpix = struct.unpack(endian + "h", data[72:74])[0]
    vox_offset = int(struct.unpack(endian + "f", data[108:112])[0])
    n = 1
    for d in dims[1:1 + max(0, min(dims[0], 7))]:
        n *= max(int(d), 1)
    expected = vox_offset + n * bitpix // 8
    if len(data) < expected:
        raise InputError(f"{path} is truncated: its header announces {expected:,} bytes (voxels {dims[1:1 + dims[0]]}, "
                         f"{bitpix} bits each) but it holds {len(data):,}; copy it again from the source")
    datatype = struct.unpack(endian + "h", data[70:72])[0]
    if datatype in (16, 64):  # float32, float64: ITK's NIfTI reader turns NaN into 0 without a word
        values = np.frombuffer(data, dtype=endian + ("f4" if datatype == 16 else "f8"), count=n, offset=vox_offset)
        bad = np.nonzero(~np.isfinite(values))[0]
        if len(bad):
            nx, ny, nz = (max(int(dims[a]), 1) if dims[0] >= a else 1 for a in (1, 2, 3))
            f = int(bad[0])
            # a vector image (a displacement field) stores each component as a whole volume after the first
            comp = f // (nx * ny * nz)
            what = f", component {comp}" if comp else ""
            raise InputError(f"{path} holds {len(bad)} non-finite (NaN or Inf) voxels, the first at index (i, j, k) = "
                             f"({f % nx}, {(f // nx) % ny}, {(f // (nx * ny)) % nz}){what}; fill or mask them before use")


def read_volume(path: str | os.PathLike) -> sitk.Image:
    """Read a 3D image: NIfTI, MHA/MHD, NRRD (any format SimpleITK reads) or a DICOM series folder.

    A truncated or corrupt NIfTI / gzip file is refused (:func:`check_file_integrity`).
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"file not found: {path}")
    if not (os.path.isfile(path) or os.path.isdir(path)):
        raise InputError(f"{path} is not a regular file (a device or a pipe?); give an image file or a DICOM series folder")
    if os.path.isfile(path) and os.path.getsize(path) == 0:
        raise InputError(f"{path} is empty (0 bytes); copy it again from the source")
    if os.path.isfile(path):
        check_file_integrity(path)
    try:
        if os.path.isdir(path):
            from .dicom_rt.series import series_headers

            reader = sitk.ImageSeriesReader()
            reader.SetFileNames([s.filename for s in series_headers(path)])  # checked: one series, whole, on one grid
            image = reader.Execute()
        else:
            image = sitk.ReadImage(path)
    except RuntimeError as exc:  # SimpleITK raises RuntimeError for unreadable files
        raise InputError(f"cannot read image {path}: {str(exc).strip().splitlines()[-1]}") from None
    if image.GetDimension() != 3:
        raise InputError(f"{path} is {image.GetDimension()}D; a 3D volume is required")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"{path} has {image.GetNumberOfComponentsPerPixel()} components per voxel; a scalar image is required")
    return image


@dataclass
class Case:
    """A planning case: a label map, an optional intensity image, and the organ label mapping.

    Attributes:
        labels: integer label array, shape (z, y, x).
        geometry: physical grid of ``labels`` (and ``image``).
        label_map: organ name -> label value.
        image: optional intensity array on the same grid (float32), shape (z, y, x).
        name: a short name for tables.
        source: where it came from (paths or 'phantom seed=N').
    """

    labels: np.ndarray
    geometry: Geometry
    label_map: dict[str, int]
    image: np.ndarray | None = None
    name: str = "case"
    source: str = ""
    meta: dict = field(default_factory=dict)

    def organ_mask(self, organ: str) -> np.ndarray:
        if organ not in self.label_map:
            raise InputError(f"organ {organ!r} has no label in this case's mapping {self.label_map}")
        return self.labels == self.label_map[organ]

    def check_organs(self, organs) -> None:
        """Raise :class:`InputError` when an organ is unmapped or absent from the label map."""
        for organ in organs:
            if organ not in self.label_map:
                raise InputError(f"organ {organ!r} has no label in the mapping {self.label_map} ({self.source})")
            if not np.any(self.labels == self.label_map[organ]):
                raise InputError(
                    f"organ {organ!r} (label {self.label_map[organ]}) is absent from the label map {self.source}"
                )

    def labels_image(self) -> sitk.Image:
        return self.geometry.apply_to(sitk.GetImageFromArray(self.labels.astype(np.uint8)))

    def intensity_image(self) -> sitk.Image:
        if self.image is None:
            raise InputError(f"case {self.name} has no intensity image")
        return self.geometry.apply_to(sitk.GetImageFromArray(self.image.astype(np.float32)))


def load_case(labels_path, image_path=None, preset: str | dict[str, int] = "amos", name: str | None = None) -> Case:
    """Read a label map (and optionally its image) into a :class:`Case`.

    A label map on another grid than the image (another axis order, a flipped axis, another spacing) is
    resampled onto the image's grid with a warning; one that does not overlap the image is refused.
    All checks run before any work is done.
    """
    label_map = resolve_labels(preset)
    lab_img = read_volume(labels_path)
    geometry = Geometry.of(lab_img)
    labels = sitk.GetArrayFromImage(lab_img)
    if not np.issubdtype(labels.dtype, np.integer):
        if not np.all(np.equal(np.mod(labels, 1), 0)):
            raise InputError(f"label map {labels_path} holds non-integer values")
        labels = labels.astype(np.int32)
    image = None
    if image_path is not None:
        img = read_volume(image_path)
        diff = grid_differences(Geometry.of(img), geometry)
        if diff:
            labels, geometry = _labels_onto_image(lab_img, labels, img, labels_path, image_path, diff)
        image = sitk.GetArrayFromImage(img).astype(np.float32)
        bad = ~np.isfinite(image)
        if bad.any():
            k, j, i = (int(v[0]) for v in np.nonzero(bad))
            raise InputError(f"image {image_path} holds {int(bad.sum())} non-finite (NaN or Inf) voxels, the first at index "
                             f"(i, j, k) = ({i}, {j}, {k}); fill or mask them before use")
    if "pancreas" not in label_map:
        raise InputError("the label mapping has no 'pancreas'; the method always models the pancreas")
    source = f"{labels_path}"
    case = Case(labels.astype(np.int32), geometry, label_map, image, name or os.path.basename(os.path.dirname(os.fspath(labels_path))) or "case", source)
    if not np.any(case.labels == label_map["pancreas"]):
        raise InputError(f"the label map {labels_path} holds no pancreas (label {label_map['pancreas']})")
    for message in plausibility_warnings(case):
        warnings.warn(f"{labels_path}: {message}", InputWarning, stacklevel=2)
    return case


#: Largest plausible adult organ volume (mL) for the plausibility check of a label mapping.
MAX_ORGAN_VOLUME_ML = {"pancreas": 250.0, "stomach": 4000.0, "duodenum": 300.0, "left_kidney": 500.0}
#: Farthest an organ of the method may lie from the pancreas (mm): the duodenum wraps its head, the
#: stomach lies in front of it, the left kidney behind its tail. Measured on the two samples: 3-13 mm;
#: a wrong preset that names a lung lobe the duodenum puts it 47-68 mm away.
MAX_DISTANCE_TO_PANCREAS_MM = 30.0


def plausibility_warnings(case: "Case") -> list[str]:
    """Why the organs of a case look mislabelled (empty list when they look right).

    Checks each mapped organ's volume against :data:`MAX_ORGAN_VOLUME_ML` (and above 0.5 mL) and its
    nearest distance to the pancreas against :data:`MAX_DISTANCE_TO_PANCREAS_MM`. A wrong ``--preset``
    (e.g. ``totalseg_mr`` on a TotalSegmentator CT, whose label 14 is a lung lobe) shows up here.
    """
    g = case.geometry
    out = []
    if "pancreas" not in case.label_map or not np.any(case.labels == case.label_map["pancreas"]):
        return out
    pan = (case.labels == case.label_map["pancreas"]).astype(np.uint8)
    dist = None
    for organ, value in case.label_map.items():
        mask = case.labels == value
        if not mask.any():
            continue
        ml = float(mask.sum()) * g.voxel_volume_mm3 / 1000.0
        if ml > MAX_ORGAN_VOLUME_ML.get(organ, np.inf):
            out.append(f"the {organ} (label {value}) is {ml:.0f} mL, more than a {organ} holds "
                       f"(<= {MAX_ORGAN_VOLUME_ML[organ]:.0f} mL): is the label preset right?")
        elif ml < 0.5:
            out.append(f"the {organ} (label {value}) is only {ml:.2f} mL: is the label preset right?")
        if organ == "pancreas":
            continue
        if dist is None:
            img = g.apply_to(sitk.GetImageFromArray(pan))
            dist = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(img, insideIsPositive=False, squaredDistance=False,
                                                                      useImageSpacing=True))
        d = float(dist[mask].min())
        if d > MAX_DISTANCE_TO_PANCREAS_MM:
            out.append(f"the {organ} (label {value}) lies {d:.0f} mm from the pancreas at its nearest; it should touch or "
                       f"nearly touch it (<= {MAX_DISTANCE_TO_PANCREAS_MM:.0f} mm): is the label preset right?")
    return out


def _labels_onto_image(lab_img: sitk.Image, labels: np.ndarray, img: sitk.Image, labels_path, image_path, diff: list[str]):
    """A label map on another grid than its image (TotalSegmentator's NIfTI beside a DICOM series: other axis
    order, a flipped axis, another spacing) resampled onto the image's grid, nearest neighbour, with a
    one-line warning; :class:`InputError` when fewer than half of the labelled voxels fall inside the image."""
    geo_l, geo_i = Geometry.of(lab_img), Geometry.of(img)
    kk, jj, ii = np.nonzero(labels)
    if len(ii):
        pts = geo_l.index_to_world(np.stack([ii, jj, kk], axis=1)[:: max(1, len(ii) // 20000)])
        idx = geo_i.world_to_index(pts)
        inside = float(np.mean(np.all((idx >= -0.5) & (idx <= np.asarray(geo_i.size) - 0.5), axis=1)))
    else:
        inside = 0.0
    if inside < 0.5:
        raise InputError(f"image {image_path} and label map {labels_path} do not overlap ({inside:.0%} of the labelled "
                         "voxels fall inside the image): " + "; ".join(diff))
    lab = sitk.GetImageFromArray(labels.astype(np.int32))
    lab.CopyInformation(lab_img)
    resampled = sitk.Resample(lab, img, sitk.Transform(), sitk.sitkNearestNeighbor, 0, sitk.sitkInt32)
    warnings.warn(f"label map {labels_path} is on another grid than the image ({'; '.join(diff)}): resampled onto the "
                  "image's grid (nearest neighbour)", InputWarning, stacklevel=3)
    return sitk.GetArrayFromImage(resampled), geo_i


def crop_to_organs(case: Case, organs, margin_mm: float = 15.0) -> tuple[Case, tuple[int, int, int]]:
    """Crop the case to the bounding box of ``organs`` plus ``margin_mm`` on every side.

    Returns the cropped case and the (i, j, k) voxel offset of the crop in the input volume,
    so that input voxel indices map to ``index - offset`` in the crop.
    """
    case.check_organs(organs)
    mask = np.zeros_like(case.labels, dtype=bool)
    for organ in organs:
        mask |= case.organ_mask(organ)
    kk, jj, ii = np.nonzero(mask)
    lo_idx = np.array([ii.min(), jj.min(), kk.min()])
    hi_idx = np.array([ii.max(), jj.max(), kk.max()]) + 1
    margin = np.ceil(margin_mm / np.asarray(case.geometry.spacing_mm)).astype(int)
    lo = np.maximum(lo_idx - margin, 0)
    hi = np.minimum(hi_idx + margin, np.asarray(case.geometry.size))
    sl = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
    geom = case.geometry.crop(tuple(int(v) for v in lo), tuple(int(v) for v in hi))
    image = None if case.image is None else case.image[sl].copy()
    cropped = Case(case.labels[sl].copy(), geom, dict(case.label_map), image, case.name, case.source, dict(case.meta))
    return cropped, (int(lo[0]), int(lo[1]), int(lo[2]))


def pad_square(case: Case) -> tuple[Case, tuple[int, int, int]]:
    """Zero-pad the in-plane (x, y) size to a square, centred (the paper's preprocessing).

    Returns the padded case and the (i, j, k) offset of the input volume inside it
    (input index ``ijk`` maps to ``ijk + offset``).
    """
    nz, ny, nx = case.labels.shape
    n = max(nx, ny)
    px, py = (n - nx) // 2, (n - ny) // 2
    pad = ((0, 0), (py, n - ny - py), (px, n - nx - px))
    geom = case.geometry.crop((-px, -py, 0), (nx + (n - nx - px), ny + (n - ny - py), nz))
    image = None if case.image is None else np.pad(case.image, pad)
    return Case(np.pad(case.labels, pad), geom, dict(case.label_map), image, case.name, case.source, dict(case.meta)), (px, py, 0)


def mask_image(case: Case, organs) -> Case:
    """Zero the intensity image outside ``organs`` (the paper's masking by the contours)."""
    if case.image is None:
        raise InputError(f"case {case.name} has no intensity image to mask")
    mask = np.zeros_like(case.labels, dtype=bool)
    for organ in organs:
        mask |= case.organ_mask(organ)
    return replace(case, image=np.where(mask, case.image, 0.0).astype(np.float32))


def write_case(case: Case, labels_path, image_path=None) -> None:
    """Write a case's label map (and image) with its geometry, in any SimpleITK format."""
    sitk.WriteImage(case.labels_image(), os.fspath(labels_path))
    if image_path is not None:
        sitk.WriteImage(case.intensity_image(), os.fspath(image_path))


#: Orientation name -> world axis it is normal to (0: x L-R, 1: y A-P, 2: z S-I).
ORIENTATION_WORLD_AXIS = {"sagittal": 0, "coronal": 1, "axial": 2}


def orientation_image_axis(geometry: Geometry, orientation: str) -> int:
    """The image axis (0: i, 1: j, 2: k) whose direction is closest to the orientation's normal."""
    if orientation not in ORIENTATION_WORLD_AXIS:
        raise InputError(f"unknown slice orientation {orientation!r}; use axial, sagittal or coronal")
    world_axis = ORIENTATION_WORLD_AXIS[orientation]
    return int(np.argmax(np.abs(geometry.direction_matrix[world_axis, :])))
