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


def series_headers(folder: str) -> list:
    """The headers (pydicom datasets, no pixels) of the DICOM image series in ``folder``, sorted along the slice normal,
    checked as a planning system checks a series before it uses it. Refused, naming the files:

    - no image with a position, or more than one series in the folder;
    - a slice without ImagePositionPatient, ImageOrientationPatient or PixelSpacing, or with unusable values;
    - slices of another orientation (a tilted slice), pixel spacing or size than the others, or shifted in plane;
    - two slices at one position; uneven gaps between slices (a missing slice: everything beyond it would be misplaced).
    """
    import pydicom

    if not os.path.isdir(folder):
        raise InputError(f"DICOM series folder {folder} " + ("is a file; give the folder of the series' slices"
                                                             if os.path.exists(folder) else "not found"))
    slices, seen = [], 0
    for name in sorted(os.listdir(folder)):
        p = os.path.join(folder, name)
        if not os.path.isfile(p):
            continue
        try:
            ds = pydicom.dcmread(p, stop_before_pixels=True)
        except Exception:  # noqa: BLE001 - not DICOM: skipped, as a series reader does
            continue
        seen += 1
        if "PixelData" in ds or "ImagePositionPatient" in ds or "Rows" in ds:
            slices.append(ds)
    if not slices:
        raise InputError(f"no DICOM series in {folder}: no DICOM image" + (f" ({seen} other DICOM files)" if seen else "")
                         + "; give the folder of the planning series' slices")
    series = {str(s.get("SeriesInstanceUID", "")) for s in slices}
    if len(series) > 1:
        raise InputError(f"{folder} holds {len(series)} DICOM series; keep the planning series alone in its folder")

    def numbers(ds, tag, n):
        try:
            v = np.array([float(x) for x in ds.get(tag)], dtype=np.float64)
        except (TypeError, ValueError):
            v = np.array([])
        if v.size != n or not np.all(np.isfinite(v)):
            raise InputError(f"planning slice {ds.filename} has {'no' if tag not in ds else 'an unusable'} {tag} "
                             f"({ds.get(tag, '')!s}); every slice must be placed: export the series again")
        return v

    for ds in slices:
        ds._iop, ds._ipp, ds._ps = (numbers(ds, "ImageOrientationPatient", 6), numbers(ds, "ImagePositionPatient", 3),
                                    numbers(ds, "PixelSpacing", 2))
        if not np.all(ds._ps > 0):
            raise InputError(f"planning slice {ds.filename} has PixelSpacing {ds._ps.tolist()}; two positive numbers (mm) "
                             "are required")
    first = slices[0]
    normal = np.cross(first._iop[:3], first._iop[3:])
    for ds in slices[1:]:
        name = os.path.basename(ds.filename)
        if np.abs(ds._iop - first._iop).max() > 1e-4:
            angle = np.degrees(np.arccos(np.clip(abs(np.cross(ds._iop[:3], ds._iop[3:]) @ normal), -1, 1)))
            raise InputError(f"planning slice {name} in {folder} is tilted {angle:.1f} degrees against "
                             f"{os.path.basename(first.filename)} (ImageOrientationPatient); a series of parallel slices is "
                             "required: export it again, or resample it onto one grid")
        if np.abs(ds._ps - first._ps).max() > 1e-4 or (int(ds.get("Rows", 0)), int(ds.get("Columns", 0))) != \
                (int(first.get("Rows", 0)), int(first.get("Columns", 0))):
            raise InputError(f"planning slice {name} in {folder} has another pixel spacing or size "
                             f"({ds._ps.tolist()} mm, {ds.get('Rows')} x {ds.get('Columns')}) than "
                             f"{os.path.basename(first.filename)} ({first._ps.tolist()} mm, {first.get('Rows')} x "
                             f"{first.get('Columns')}); one grid is required: export the series again")
    slices.sort(key=lambda s: float(s._ipp @ normal))
    pos = np.array([float(s._ipp @ normal) for s in slices])
    inplane = np.array([s._ipp - (s._ipp @ normal) * normal for s in slices])
    if len(slices) > 1:
        if np.abs(inplane - inplane[0]).max() > 0.01 * float(first._ps.min()) + 1e-3:
            k = int(np.argmax(np.abs(inplane - inplane[0]).max(1)))
            raise InputError(f"planning slice {os.path.basename(slices[k].filename)} in {folder} is shifted in its plane "
                             "against the others (a gantry-tilted or sheared stack); resample the series onto one grid")
        gaps = np.diff(pos)
        if np.any(gaps < 1e-3):
            k = int(np.argmin(gaps))
            raise InputError(f"planning slices {os.path.basename(slices[k].filename)} and "
                             f"{os.path.basename(slices[k + 1].filename)} in {folder} lie at the same position "
                             f"({pos[k]:.2f} mm); remove the duplicate")
        step = float(np.median(gaps))
        uneven = np.nonzero(np.abs(gaps - step) > max(0.01 * step, 1e-3))[0]
        if len(uneven):
            k = int(uneven[0])
            missing = int(round(gaps[k] / step)) - 1
            what = (f"{missing} slice{'s' if missing > 1 else ''} missing" if missing >= 1
                    else "slices unevenly spaced")
            raise InputError(f"planning series {folder}: {gaps[k]:.2f} mm between {os.path.basename(slices[k].filename)} "
                             f"({pos[k]:.2f} mm) and {os.path.basename(slices[k + 1].filename)} ({pos[k + 1]:.2f} mm), "
                             f"{step:.2f} mm elsewhere ({what}); everything beyond would be misplaced. Export the whole "
                             "series again")
    return slices


def read_series_reference(folder: str) -> SeriesReference:
    """The reference of a DICOM image series in ``folder`` (one series, checked by :func:`series_headers`; slices sorted
    along their normal). A UID the series leaves empty (Study, Series, Frame of Reference, an image's SOP Instance) is
    generated for the outputs that refer to it, and a warning says so."""
    import warnings

    from ..errors import InputWarning

    slices = series_headers(folder)
    image = sitk.ReadImage([s.filename for s in slices]) if len(slices) > 1 else sitk.ReadImage(slices[0].filename)
    s0 = slices[0]
    made = []

    def uid(ds, tag):
        value = str(ds.get(tag, "") or "").strip()
        if not value:
            made.append(tag)
            value = _uid()
        return value

    study, series, frame = (uid(s0, t) for t in ("StudyInstanceUID", "SeriesInstanceUID", "FrameOfReferenceUID"))
    instances = [uid(s, "SOPInstanceUID") for s in slices]
    sop_class = str(s0.get("SOPClassUID", "") or "").strip() or (CT_IMAGE if str(s0.get("Modality", "")) == "CT" else MR_IMAGE)
    if made:
        warnings.warn(f"the planning series {folder} has no value for {', '.join(sorted(set(made)))}: new UIDs were made for "
                      "the DICOM files written from it, which a planning system will not link to this series; export "
                      "the series with its UIDs to keep them linked", InputWarning, stacklevel=2)
    ref = SeriesReference(study, series, frame, sop_class, instances, Geometry.of(image),
                          str(s0.get("PatientName", "")), str(s0.get("PatientID", "")), str(s0.get("StudyDate", "")),
                          str(s0.get("StudyTime", "")), str(s0.get("StudyID", "")), str(s0.get("AccessionNumber", "")))
    ref.extra["generated_uids"] = sorted(set(made))
    return ref
