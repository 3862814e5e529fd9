"""The planning series: :func:`write_series` writes one as single-frame images; :func:`read_series_reference` reads
what a structure set or registration must reference from one."""

from __future__ import annotations

import os

import numpy as np
import SimpleITK as sitk

from ..errors import InputError
from ..images import Geometry
from .common import _base, _ds, _now, _save, _uid, CT_IMAGE, DISCLAIMER, MR_IMAGE, SeriesReference

__all__ = ["write_series", "read_series_reference"]


def write_series(image: sitk.Image, folder: str, modality: str = "MR", patient_name: str = "ANONYMOUS^",
                 patient_id: str = "WARPMPM") -> SeriesReference:
    """Write a 3D image as a DICOM series (one file per slice along its third axis) into ``folder``; its reference.

    For a planning image given as NIfTI/MHA/NRRD, so that structure sets and registrations have a series to refer to.
    """
    if modality not in ("MR", "CT"):
        raise InputError(f"planning series modality must be MR or CT, got {modality!r}")
    geometry = Geometry.of(image)
    arr = sitk.GetArrayFromImage(image).astype(np.float64)
    if not np.isfinite(arr).all():
        raise InputError("the planning image holds non-finite voxels; it cannot be written as DICOM")
    integer = np.all(np.equal(np.mod(arr, 1), 0))
    slope, intercept, note = 1.0, 0.0, ""
    if modality == "CT":
        if not (integer and arr.min() >= -32768 and arr.max() <= 32767):
            lo, hi = float(arr.min()), float(arr.max())
            slope = max(hi - lo, 1e-6) / 65535.0
            intercept = lo + 32768.0 * slope
        pixels = np.rint((arr - intercept) / slope).clip(-32768, 32767).astype(np.int16)
    else:
        if integer and arr.min() >= 0 and arr.max() <= 65535:
            pixels = arr.astype(np.uint16)
        elif integer and arr.min() >= -32768 and arr.max() <= 32767:
            pixels = arr.astype(np.int16)
        else:
            lo, hi = float(arr.min()), float(arr.max())
            pixels = np.rint((arr - lo) / max(hi - lo, 1e-12) * 4095.0).astype(np.uint16)
            note = f"intensities mapped linearly from [{lo:.6g}, {hi:.6g}] to [0, 4095]"
    os.makedirs(folder, exist_ok=True)
    ref = SeriesReference(_uid(), _uid(), _uid(), CT_IMAGE if modality == "CT" else MR_IMAGE,
                          [_uid() for _ in range(geometry.size[2])], geometry, patient_name, patient_id)
    date, time = _now()
    ref.study_date, ref.study_time, ref.study_id = date, time, "1"
    d = geometry.direction_matrix
    iop = [_ds(float(x)) for x in np.concatenate([d[:, 0], d[:, 1]])]
    for k in range(geometry.size[2]):
        ds = _base(ref.sop_class_uid, ref.sop_instance_uids[k], ref, modality, ref.series_uid, 1, "warpmpm planning image")
        ds.ImageType = ["DERIVED", "SECONDARY", "OTHER"]
        ds.FrameOfReferenceUID = ref.frame_of_reference_uid
        ds.PositionReferenceIndicator = ""
        ds.InstanceNumber = k + 1
        ds.AcquisitionNumber = 1
        ds.PatientPosition = "HFS"
        ds.ImagePositionPatient = [_ds(float(x)) for x in geometry.index_to_world(np.array([[0.0, 0.0, k]]))[0]]
        ds.ImageOrientationPatient = iop
        ds.SliceThickness = _ds(geometry.spacing_mm[2])
        ds.SliceLocation = _ds(float(geometry.index_to_world(np.array([[0.0, 0.0, k]]))[0] @ np.cross(d[:, 0], d[:, 1])))
        ds.PixelSpacing = [_ds(geometry.spacing_mm[1]), _ds(geometry.spacing_mm[0])]  # between rows, between columns
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.Rows, ds.Columns = geometry.size[1], geometry.size[0]
        ds.BitsAllocated = ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 1 if pixels.dtype == np.int16 else 0
        ds.ImageComments = (DISCLAIMER + ("; " + note if note else ""))[:10240]
        if modality == "CT":
            ds.KVP = ""
            ds.RescaleIntercept = _ds(intercept)
            ds.RescaleSlope = _ds(slope)
            ds.RescaleType = "HU"
        else:
            ds.ScanningSequence = ["RM"]
            ds.SequenceVariant = ["NONE"]
            ds.ScanOptions = ""
            ds.MRAcquisitionType = "3D"
            ds.RepetitionTime = ""
            ds.EchoTime = ""
            ds.EchoTrainLength = ""
            ds.MagneticFieldStrength = ""
            ds.SpacingBetweenSlices = _ds(geometry.spacing_mm[2])
        ds.PixelData = np.ascontiguousarray(pixels[k]).tobytes()
        _save(ds, os.path.join(folder, f"{'CT' if modality == 'CT' else 'MR'}{k + 1:04d}.dcm"))
    return ref


def read_series_reference(folder: str) -> SeriesReference:
    """The reference of a DICOM image series in ``folder`` (one series; slices sorted along their normal)."""
    import pydicom

    if not os.path.isdir(folder):
        raise InputError(f"DICOM series folder not found: {folder}")
    slices = []
    for name in sorted(os.listdir(folder)):
        p = os.path.join(folder, name)
        if not os.path.isfile(p):
            continue
        try:
            ds = pydicom.dcmread(p, stop_before_pixels=True)
        except Exception:  # noqa: BLE001 - not DICOM: skipped, as a series reader does
            continue
        if "ImagePositionPatient" in ds and "ImageOrientationPatient" in ds:
            slices.append(ds)
    if not slices:
        raise InputError(f"no DICOM images with a position in {folder}")
    series = {str(s.SeriesInstanceUID) for s in slices}
    if len(series) > 1:
        raise InputError(f"{folder} holds {len(series)} DICOM series; keep the planning series alone in its folder")
    iop = np.array([float(x) for x in slices[0].ImageOrientationPatient])
    normal = np.cross(iop[:3], iop[3:])
    slices.sort(key=lambda s: float(np.array([float(x) for x in s.ImagePositionPatient]) @ normal))
    image = sitk.ReadImage([s.filename for s in slices]) if len(slices) > 1 else sitk.ReadImage(slices[0].filename)
    s0 = slices[0]
    for tag in ("FrameOfReferenceUID", "StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID"):
        if tag not in s0:
            raise InputError(f"DICOM series in {folder} has no {tag}")
    return SeriesReference(str(s0.StudyInstanceUID), str(s0.SeriesInstanceUID), str(s0.FrameOfReferenceUID),
                           str(s0.SOPClassUID), [str(s.SOPInstanceUID) for s in slices], Geometry.of(image),
                           str(s0.get("PatientName", "")), str(s0.get("PatientID", "")), str(s0.get("StudyDate", "")),
                           str(s0.get("StudyTime", "")), str(s0.get("StudyID", "")), str(s0.get("AccessionNumber", "")))
