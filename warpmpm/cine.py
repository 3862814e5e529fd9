"""Cine MR frames: reading a series of 2D frames, their planes in the scanner's space, grouping by plane.

A frame is a 2D image placed in 3D: a NIfTI / MHA / NRRD image one voxel thick (its geometry places the
plane; frames are ordered by file name) or a 2D DICOM file (ImagePositionPatient / ImageOrientationPatient
place it; frames are ordered by acquisition time, then instance number). Any plane orientation, oblique
included. Frames of the same plane (same normal and position, to 0.5 mm) form one plane's stream:
one plane on MRIdian (sagittal), interleaved sagittal / coronal on Unity.

In-plane coordinates of a frame are the offsets ``(u, v) = ((x - c) . e_u, (x - c) . e_v)`` in mm from its
centre ``c``, along its two in-plane image axes: the convention of :mod:`warpmpm.slices`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from .errors import InputError
from .images import check_file_integrity

__all__ = ["IMAGE_SUFFIXES", "CineFrame", "read_cine"]

IMAGE_SUFFIXES = (".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".dcm")


@dataclass
class CineFrame:
    """One cine frame.

    Attributes:
        path: the file. image: the frame as a 3D SimpleITK image one voxel thick. time_s: acquisition time
        (s, from the first frame). plane: the index of its plane in the series. thin_axis: the image axis of
        size 1. normal, e_u, e_v: unit world vectors (the slice normal and the in-plane image axes).
        centre_mm: the world centre of the frame. thickness_mm: the slice thickness.
    """

    path: str
    image: sitk.Image
    time_s: float
    thin_axis: int
    normal: np.ndarray
    e_u: np.ndarray
    e_v: np.ndarray
    centre_mm: np.ndarray
    thickness_mm: float
    plane: int = 0

    def slice_2d(self, volume_image: sitk.Image | None = None, interpolator=sitk.sitkLinear) -> sitk.Image:
        """The frame (or ``volume_image`` resampled on the frame's plane) as a 2D image in centred in-plane mm."""
        img = self.image if volume_image is None else sitk.Resample(volume_image, self.image, sitk.Transform(), interpolator, 0.0)
        arr = np.squeeze(sitk.GetArrayFromImage(img), axis=2 - self.thin_axis).astype(np.float32)
        out = sitk.GetImageFromArray(arr)
        axes = [a for a in range(3) if a != self.thin_axis]
        x0 = np.asarray(self.image.GetOrigin()) - self.centre_mm
        out.SetOrigin((float(x0 @ self.e_u), float(x0 @ self.e_v)))
        out.SetSpacing(tuple(float(self.image.GetSpacing()[a]) for a in axes))
        return out

    def in_plane(self, positions_mm: np.ndarray) -> np.ndarray:
        """(N, 2) in-plane coordinates (mm) of world positions."""
        d = np.asarray(positions_mm, dtype=np.float64) - self.centre_mm
        return np.stack([d @ self.e_u, d @ self.e_v], axis=1)

    def distance_mm(self, positions_mm: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of world positions from the frame's plane."""
        return (np.asarray(positions_mm, dtype=np.float64) - self.centre_mm) @ self.normal

    @property
    def projector(self) -> np.ndarray:
        return np.outer(self.e_u, self.e_u) + np.outer(self.e_v, self.e_v)


def _frame(path: str, image: sitk.Image, time_s: float) -> CineFrame:
    if image.GetDimension() == 2:
        image = sitk.JoinSeries(image)
    if image.GetDimension() != 3:
        raise InputError(f"cine frame {path} is {image.GetDimension()}D; a 2D frame (or a 3D image one voxel thick) is required")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"cine frame {path} is not a scalar image")
    size = image.GetSize()
    thin = [a for a in range(3) if size[a] == 1]
    if len(thin) != 1:
        raise InputError(f"cine frame {path} is {size[0]} x {size[1]} x {size[2]} voxels; a frame must be one voxel thick")
    a = thin[0]
    d = np.asarray(image.GetDirection()).reshape(3, 3)
    u, v = [b for b in range(3) if b != a]
    arr = sitk.GetArrayViewFromImage(image)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"cine frame {path} holds non-finite (NaN or Inf) pixels")
    centre_idx = (np.asarray(size, dtype=np.float64) - 1.0) / 2.0
    centre = np.asarray(image.TransformContinuousIndexToPhysicalPoint(centre_idx.tolist()))
    return CineFrame(path, image, time_s, a, d[:, a] / np.linalg.norm(d[:, a]), d[:, u], d[:, v], centre,
                     float(image.GetSpacing()[a]))


def read_cine(folder: str) -> list[CineFrame]:
    """Every frame of a cine folder, in acquisition order, with its plane index (see module docstring).

    Raises :class:`InputError` naming the file for an unreadable frame, a frame that is not one voxel
    thick, mixed sizes within one plane, or DICOM frames whose acquisition times go backwards.
    """
    if not os.path.isdir(folder):
        raise InputError(f"cine folder not found: {folder}")
    paths = sorted(os.path.join(folder, f) for f in os.listdir(folder) if f.lower().endswith(IMAGE_SUFFIXES))
    if not paths:
        raise InputError(f"no cine frames (NIfTI, MHA, NRRD or DICOM files) in {folder}")
    frames = []
    dicom = [p for p in paths if p.lower().endswith(".dcm")]
    if dicom and len(dicom) != len(paths):
        raise InputError(f"{folder} mixes DICOM and other frames; keep one kind per series")
    for n, p in enumerate(paths):
        if not p.lower().endswith(".dcm"):
            check_file_integrity(p)
        try:
            reader = sitk.ImageFileReader()
            reader.SetFileName(p)
            reader.LoadPrivateTagsOff()
            image = reader.Execute()
        except RuntimeError as exc:
            raise InputError(f"cannot read cine frame {p}: {str(exc).strip().splitlines()[-1]}") from None
        t = float(n)
        if dicom:
            t = _dicom_time_s(reader, p) + 1e-6 * _dicom_int(reader, "0020|0013")
        frames.append(_frame(p, image, t))
    frames.sort(key=lambda f: f.time_s)
    t0 = frames[0].time_s
    for f in frames:
        f.time_s -= t0
    # group by plane: same normal (up to sign) and the same offset along it
    planes: list[tuple[np.ndarray, float, tuple]] = []
    for f in frames:
        n = f.normal * np.sign(f.normal[np.argmax(np.abs(f.normal))])
        off = float(f.centre_mm @ n)
        for i, (pn, po, size) in enumerate(planes):
            if abs(abs(pn @ n) - 1) < 1e-4 and abs(po - off) < 0.5:
                if f.image.GetSize() != size:
                    raise InputError(f"cine frame {f.path} is {f.image.GetSize()} voxels, other frames of its plane "
                                     f"{size}: one plane's frames must share a size")
                f.plane = i
                break
        else:
            planes.append((n, off, f.image.GetSize()))
            f.plane = len(planes) - 1
    return frames


def _dicom_int(reader, tag: str) -> int:
    try:
        return int(str(reader.GetMetaData(tag)).strip())
    except (RuntimeError, ValueError):
        return 0


def _dicom_time_s(reader, path: str) -> float:
    for tag in ("0008|0032", "0008|0033"):  # acquisition time, content time (HHMMSS.frac)
        if reader.HasMetaDataKey(tag):
            v = str(reader.GetMetaData(tag)).strip()
            try:
                return int(v[0:2]) * 3600 + int(v[2:4]) * 60 + float(v[4:] or 0)
            except ValueError:
                raise InputError(f"cine frame {path} has an unreadable acquisition time {v!r}") from None
    return 0.0
