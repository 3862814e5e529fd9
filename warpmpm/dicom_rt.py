"""DICOM for the planning system: a planning series, RT Structure Sets in and out, Deformable Spatial Registrations out.

Written with pydicom (the DICOM file layer: tags, value representations, file meta), with the information
objects built here attribute by attribute from DICOM PS3.3 and checked by dicom3tools' ``dciodvfy`` in the
tests. Contours come from contourpy (matplotlib's contouring library) and are rasterised with matplotlib's
point-in-polygon; both already come with this package's dependencies.

Conventions (all positions in mm in the DICOM patient coordinate system, which is world LPS, the same axes as
every other output of this package):

- **Planning series** (:func:`write_series`): one single-frame image per slice of the planning grid along its third
  axis, in the grid's own orientation (ImageOrientationPatient = its first two axes), intensities kept when they
  are integers that fit 16 bits, else rescaled (RescaleSlope / RescaleIntercept for CT; a linear map to 0-4095
  for MR, said in the ImageComments). It exists for the structure sets and registrations to reference.
- **RT Structure Set** (:func:`write_rtstruct`): one ROI per organ, one CLOSED_PLANAR contour per connected
  outline on each slice it crosses (holes as separate contours: read them even-odd), traced at the half-voxel
  boundary so that the voxels whose centres lie inside are the mask.
- **Deformable Spatial Registration** (:func:`write_registration`): the displacement of the estimate on the
  planning grid, *planning to frame*: the vector at planning grid point x is where the tissue at x is in this
  frame, minus x (mm, LPS). In DICOM's words the Registered RCS is the planning scan's and the Source RCS the
  frame's (the same scanner frame of reference, pre- and post-deformation matrices identity): a point P of the
  planning grid corresponds to P + V(P) in the frame, as resampling the frame onto the planning grid needs.

This software is a research tool, not a medical device: its contours and registrations are estimates to be
reviewed, never to plan or deliver a treatment without review.
"""

from __future__ import annotations

import datetime
import os
import re
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

from .errors import InputError
from .images import Geometry

__all__ = ["SeriesReference", "STRUCTURE_NAMES", "write_series", "read_series_reference", "write_rtstruct", "read_rtstruct",
           "find_structures", "write_registration", "read_registration", "case_from_rtstruct", "FrameDicomWriter",
           "write_rtdose"]

MR_IMAGE = "1.2.840.10008.5.1.4.1.1.4"
CT_IMAGE = "1.2.840.10008.5.1.4.1.1.2"
RT_STRUCTURE_SET = "1.2.840.10008.5.1.4.1.1.481.3"
DEFORMABLE_REGISTRATION = "1.2.840.10008.5.1.4.1.1.66.3"
RT_DOSE = "1.2.840.10008.5.1.4.1.1.481.2"
IMPLEMENTATION_NAME = "WARPMPM"
DISCLAIMER = "warpmpm research estimate; not a medical device; review before clinical use"
SHORT_DISCLAIMER = "warpmpm estimate; not a medical device"

#: common names of each organ's structure in planning structure sets (matched after lower-casing and turning every
#: run of non-letters/digits into one space); a user's own mapping (``--structure organ=NAME``) goes first. Names of
#: other bowel ("Bowel_Small", "Bowel_Large", "Bowel") are deliberately not the duodenum.
STRUCTURE_NAMES = {
    "pancreas": ("pancreas", "pancreas gtv", "panc", "pancreas whole"),
    "stomach": ("stomach", "stomach prv", "gastric", "stomach whole"),
    "duodenum": ("duodenum", "bowel duodenum", "duodenum whole", "duod"),
    "left_kidney": ("kidney l", "l kidney", "left kidney", "kidney left", "lt kidney", "kidney lt", "kidneyl", "kidney_l"),
}


@dataclass
class SeriesReference:
    """What a structure set or registration needs of the image series it refers to.

    Attributes: study_uid, series_uid, frame_of_reference_uid; sop_class_uid and sop_instance_uids (one per slice
    along the grid's third axis, in index order); geometry (the grid); patient_name, patient_id, study_date,
    study_time, study_id, accession (copied into what refers to it)."""

    study_uid: str
    series_uid: str
    frame_of_reference_uid: str
    sop_class_uid: str
    sop_instance_uids: list[str]
    geometry: Geometry
    patient_name: str = "ANONYMOUS^"
    patient_id: str = "WARPMPM"
    study_date: str = ""
    study_time: str = ""
    study_id: str = ""
    accession: str = ""
    extra: dict = field(default_factory=dict)


def _uid() -> str:
    from pydicom.uid import generate_uid

    return generate_uid()


def _now():
    t = datetime.datetime.now()
    return t.strftime("%Y%m%d"), t.strftime("%H%M%S")


def _ds(value: float) -> str:
    """A decimal string of at most 16 characters (DICOM DS)."""
    for digits in range(10, 0, -1):
        s = f"{value:.{digits}g}"
        if len(s) <= 16:
            return s
    return f"{value:.1e}"


def _base(sop_class: str, sop_uid: str, ref: SeriesReference, modality: str, series_uid: str, series_number: int,
          description: str):
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, PYDICOM_IMPLEMENTATION_UID

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    meta.ImplementationVersionName = IMPLEMENTATION_NAME
    ds = FileDataset(None, {}, file_meta=meta, preamble=b"\0" * 128)
    date, time = _now()
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = sop_uid
    ds.InstanceCreationDate, ds.InstanceCreationTime = date, time
    ds.StudyDate, ds.StudyTime = ref.study_date or date, ref.study_time or time
    ds.AccessionNumber = ref.accession
    ds.Modality = modality
    ds.Manufacturer = "warpmpm"
    ds.ManufacturerModelName = "warpmpm"
    ds.DeviceSerialNumber = "0"
    ds.SoftwareVersions = _version()
    if sop_class not in (RT_STRUCTURE_SET, RT_DOSE):
        ds.Laterality = ""
    if sop_class in (RT_STRUCTURE_SET, RT_DOSE):
        ds.OperatorsName = ""
    ds.ReferringPhysicianName = ""
    ds.StudyDescription = "warpmpm"
    ds.SeriesDescription = description[:64]
    ds.PatientName = ref.patient_name
    ds.PatientID = ref.patient_id
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    ds.StudyInstanceUID = ref.study_uid
    ds.SeriesInstanceUID = series_uid
    ds.StudyID = ref.study_id
    ds.SeriesNumber = series_number
    ds.InstanceNumber = 1
    ds.SeriesDate, ds.SeriesTime = date, time
    if sop_class != RT_STRUCTURE_SET:
        ds.ContentDate, ds.ContentTime = date, time
    return ds


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("warpmpm")
    except Exception:  # noqa: BLE001 - run from a source tree
        return "0"


def _instances(ref: SeriesReference):
    """A Sequence referring to every image of the series ``ref`` (class and instance UIDs)."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    out = Sequence()
    for uid in ref.sop_instance_uids:
        item = Dataset()
        item.ReferencedSOPClassUID = ref.sop_class_uid
        item.ReferencedSOPInstanceUID = uid
        out.append(item)
    return out


def _save(ds, path: str) -> None:
    tmp = path + ".part"
    ds.save_as(tmp, enforce_file_format=True)
    os.replace(tmp, path)


# ------------------------------------------------------------------------------------------------
# the planning series
# ------------------------------------------------------------------------------------------------

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


# ------------------------------------------------------------------------------------------------
# structure sets
# ------------------------------------------------------------------------------------------------

def _outlines(mask2d: np.ndarray) -> list[np.ndarray]:
    """Closed outlines (each (n, 2) as (column, row) index coordinates) of a 2D mask at the half-voxel boundary."""
    import contourpy

    padded = np.pad(mask2d.astype(np.float64), 1)
    gen = contourpy.contour_generator(z=padded, line_type=contourpy.LineType.Separate)
    out = []
    for line in gen.lines(0.5):
        pts = np.asarray(line, dtype=np.float64) - 1.0
        if len(pts) > 1 and np.allclose(pts[0], pts[-1]):
            pts = pts[:-1]
        if len(pts) >= 3:
            out.append(pts)
    return out


_COLOURS = {"pancreas": (255, 128, 0), "stomach": (0, 160, 255), "duodenum": (0, 200, 80), "left_kidney": (220, 0, 220)}


def write_rtstruct(path: str, ref: SeriesReference, masks: dict[str, np.ndarray], names: dict[str, str] | None = None,
                   label: str = "warpmpm", description: str = "warpmpm estimate") -> None:
    """An RT Structure Set of ``masks`` (organ -> boolean (z, y, x) on ``ref.geometry``) referring to ``ref``.

    ``names``: the ROI name of each organ (default: the organ's name). Contours: see the module docstring.
    """
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    g = ref.geometry
    names = names or {}
    ds = _base(RT_STRUCTURE_SET, _uid(), ref, "RTSTRUCT", _uid(), 901, description)
    ds.FrameOfReferenceUID = ref.frame_of_reference_uid
    ds.PositionReferenceIndicator = ""
    ds.StructureSetLabel = label[:16]
    ds.StructureSetName = label[:64]
    ds.StructureSetDescription = DISCLAIMER
    ds.StructureSetDate, ds.StructureSetTime = ds.InstanceCreationDate, ds.InstanceCreationTime
    series = Dataset()
    series.SeriesInstanceUID = ref.series_uid
    series.ContourImageSequence = _instances(ref)
    study = Dataset()
    study.ReferencedSOPClassUID = "1.2.840.10008.3.1.2.3.1"  # Detached Study Management (retired), as TPSs write it
    study.ReferencedSOPInstanceUID = ref.study_uid
    study.RTReferencedSeriesSequence = Sequence([series])
    frame = Dataset()
    frame.FrameOfReferenceUID = ref.frame_of_reference_uid
    frame.RTReferencedStudySequence = Sequence([study])
    ds.ReferencedFrameOfReferenceSequence = Sequence([frame])
    rois, contours, observations = Sequence(), Sequence(), Sequence()
    for number, (organ, mask) in enumerate(masks.items(), start=1):
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != tuple(g.size[::-1]):
            raise InputError(f"structure {organ}: a mask of shape {mask.shape}, the series is {tuple(g.size[::-1])} (z, y, x)")
        roi = Dataset()
        roi.ROINumber = number
        roi.ReferencedFrameOfReferenceUID = ref.frame_of_reference_uid
        roi.ROIName = names.get(organ, organ)[:64]
        roi.ROIGenerationAlgorithm = "AUTOMATIC"
        rois.append(roi)
        items = Sequence()
        for k in np.nonzero(mask.any(axis=(1, 2)))[0]:
            for pts in _outlines(mask[k]):
                ijk = np.column_stack([pts[:, 0], pts[:, 1], np.full(len(pts), float(k))])
                world = g.index_to_world(ijk)
                c = Dataset()
                img = Dataset()
                img.ReferencedSOPClassUID = ref.sop_class_uid
                img.ReferencedSOPInstanceUID = ref.sop_instance_uids[int(k)]
                c.ContourImageSequence = Sequence([img])
                c.ContourGeometricType = "CLOSED_PLANAR"
                c.NumberOfContourPoints = len(world)
                c.ContourData = [_ds(float(v)) for v in np.round(world, 4).ravel()]
                items.append(c)
        rc = Dataset()
        rc.ROIDisplayColor = list(_COLOURS.get(organ, (255, 255, 0)))
        rc.ReferencedROINumber = number
        if len(items):
            rc.ContourSequence = items
        contours.append(rc)
        obs = Dataset()
        obs.ObservationNumber = number
        obs.ReferencedROINumber = number
        obs.RTROIInterpretedType = "ORGAN"
        obs.ROIInterpreter = ""
        observations.append(obs)
    ds.StructureSetROISequence = rois
    ds.ROIContourSequence = contours
    ds.RTROIObservationsSequence = observations
    ds.ApprovalStatus = "UNAPPROVED"
    _save(ds, path)


def _normalised(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", " ", name.lower()).strip()


def _self_intersects(pts: np.ndarray) -> bool:
    """Whether a closed polygon (n, 2) crosses itself (edges that are not neighbours properly intersect)."""
    n = len(pts)
    a, b = pts, np.roll(pts, -1, axis=0)
    for i in range(n):
        j = np.arange(i + 2, n)
        if i == 0:
            j = j[j != n - 1]
        if not len(j):
            continue
        p, r = a[i], b[i] - a[i]
        q, s = a[j], b[j] - a[j]
        denom = r[0] * s[:, 1] - r[1] * s[:, 0]
        qp = q - p
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (qp[:, 0] * s[:, 1] - qp[:, 1] * s[:, 0]) / denom
            u = (qp[:, 0] * r[1] - qp[:, 1] * r[0]) / denom
        if np.any((np.abs(denom) > 1e-12) & (t > 1e-9) & (t < 1 - 1e-9) & (u > 1e-9) & (u < 1 - 1e-9)):
            return True
    return False


def read_rtstruct(path: str, geometry: Geometry, frame_of_reference_uid: str | None = None,
                  rois: list[str] | None = None) -> dict[str, np.ndarray]:
    """The structures of an RT Structure Set rasterised on ``geometry``: ROI name -> boolean (z, y, x).

    A voxel is inside when its centre is inside an odd number of the ROI's contours on its slice (holes). Only the
    ROIs named in ``rois`` are read when given. Raises :class:`InputError` naming the ROI for a structure set of
    another frame of reference than ``frame_of_reference_uid``, a contour off the grid's slices, an empty contour
    or one that crosses itself.
    """
    import pydicom
    from matplotlib.path import Path

    try:
        ds = pydicom.dcmread(path)
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"cannot read the structure set {path}: {exc}") from None
    if str(ds.get("SOPClassUID", "")) != RT_STRUCTURE_SET:
        raise InputError(f"{path} is not an RT Structure Set (SOP class {ds.get('SOPClassUID', 'missing')})")
    frames = {str(f.FrameOfReferenceUID) for f in ds.get("ReferencedFrameOfReferenceSequence", [])}
    names = {int(r.ROINumber): str(r.ROIName) for r in ds.get("StructureSetROISequence", [])}
    roi_frames = {int(r.ROINumber): str(r.get("ReferencedFrameOfReferenceUID", "")) for r in ds.get("StructureSetROISequence", [])}
    g = geometry
    shape = tuple(g.size[::-1])
    jj, ii = np.mgrid[0:shape[1], 0:shape[2]]
    centres = np.column_stack([ii.ravel(), jj.ravel()]).astype(np.float64)
    out = {}
    for rc in ds.get("ROIContourSequence", []):
        number = int(rc.ReferencedROINumber)
        name = names.get(number, f"ROI {number}")
        if rois is not None and name not in rois:
            continue
        if frame_of_reference_uid is not None:
            fr = roi_frames.get(number) or (next(iter(frames)) if len(frames) == 1 else "")
            if fr and fr != frame_of_reference_uid:
                raise InputError(f"structure {name!r} in {path} is on frame of reference {fr}, the planning image on "
                                 f"{frame_of_reference_uid}: the structure set belongs to another scan (register it first)")
        mask = np.zeros(shape, dtype=bool)
        for c in rc.get("ContourSequence", []):
            kind = str(c.get("ContourGeometricType", "CLOSED_PLANAR"))
            data = np.asarray([float(v) for v in c.get("ContourData", [])], dtype=np.float64)
            if kind == "POINT":
                continue
            if data.size < 9 or data.size % 3:
                raise InputError(f"structure {name!r} in {path}: a contour with {data.size // 3} points; a closed contour "
                                 "needs at least 3")
            ijk = g.world_to_index(data.reshape(-1, 3))
            k = float(np.mean(ijk[:, 2]))
            kr = int(round(k))
            if np.ptp(ijk[:, 2]) > 0.1 or abs(k - kr) > 0.25:
                raise InputError(f"structure {name!r} in {path}: a contour at slice position {k:.2f} does not lie on a slice "
                                 "of the planning image (contours must be drawn on the image's slices)")
            if not 0 <= kr < shape[0]:
                continue
            poly = ijk[:, :2]
            if _self_intersects(poly):
                raise InputError(f"structure {name!r} in {path}: its contour on slice {kr} crosses itself; mend it in "
                                 "the planning system")
            lo = np.floor(poly.min(0)).astype(int)
            hi = np.ceil(poly.max(0)).astype(int)
            inside = Path(poly).contains_points(centres, radius=0.0).reshape(shape[1], shape[2])
            window = np.zeros_like(inside)
            window[max(lo[1], 0):hi[1] + 1, max(lo[0], 0):hi[0] + 1] = True
            mask[kr] ^= inside & window
        out[name] = mask
    return out


def find_structures(roi_names, mapping: dict[str, str] | None = None, organs=("pancreas", "stomach", "duodenum", "left_kidney")):
    """Which ROI is each organ: ``mapping`` (organ -> ROI name) first, then :data:`STRUCTURE_NAMES`. Returns organ -> ROI
    name for the organs found; raises :class:`InputError` when a mapped ROI is missing or one name fits two ROIs."""
    mapping = dict(mapping or {})
    roi_names = list(roi_names)
    found = {}
    for organ in organs:
        if organ in mapping:
            if mapping[organ] not in roi_names:
                raise InputError(f"structure {mapping[organ]!r} (given for {organ}) is not in the structure set; it holds: "
                                 f"{', '.join(roi_names)}")
            found[organ] = mapping[organ]
            continue
        hits = [r for r in roi_names if _normalised(r) in {_normalised(n) for n in STRUCTURE_NAMES[organ]}]
        if len(hits) > 1:
            raise InputError(f"structures {', '.join(hits)} could each be the {organ}; name one with --structure {organ}=NAME")
        if hits:
            found[organ] = hits[0]
    return found


# ------------------------------------------------------------------------------------------------
# deformable spatial registration
# ------------------------------------------------------------------------------------------------

def write_registration(path: str, ref: SeriesReference, field_mm: np.ndarray, description: str = "warpmpm estimate",
                       source_frame_of_reference_uid: str | None = None) -> None:
    """A Deformable Spatial Registration of the displacement ``field_mm`` ((z, y, x, 3) mm, LPS, planning to frame, on
    ``ref.geometry``) referring to the planning series ``ref`` (conventions: module docstring)."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    g = ref.geometry
    field_mm = np.asarray(field_mm, dtype=np.float32)
    if field_mm.shape != tuple(g.size[::-1]) + (3,):
        raise InputError(f"registration: a field of shape {field_mm.shape}, the series needs {tuple(g.size[::-1]) + (3,)}")
    if not np.isfinite(field_mm).all():
        raise InputError("registration: the displacement field holds non-finite values; nothing was written")
    ds = _base(DEFORMABLE_REGISTRATION, _uid(), ref, "REG", _uid(), 902, description)
    ds.FrameOfReferenceUID = ref.frame_of_reference_uid
    ds.PositionReferenceIndicator = ""
    ds.ContentLabel = "WARPMPM"
    ds.ContentDescription = SHORT_DISCLAIMER
    ds.ContentCreatorName = ""
    series = Dataset()
    series.SeriesInstanceUID = ref.series_uid
    series.ReferencedInstanceSequence = _instances(ref)
    ds.ReferencedSeriesSequence = Sequence([series])
    identity = ["1.0", "0.0", "0.0", "0.0", "0.0", "1.0", "0.0", "0.0", "0.0", "0.0", "1.0", "0.0", "0.0", "0.0", "0.0", "1.0"]

    def matrix():
        m = Dataset()
        m.FrameOfReferenceTransformationMatrix = identity
        m.FrameOfReferenceTransformationMatrixType = "RIGID"
        return Sequence([m])

    d = g.direction_matrix
    grid = Dataset()
    grid.ImageOrientationPatient = [_ds(float(x)) for x in np.concatenate([d[:, 0], d[:, 1]])]
    grid.ImagePositionPatient = [_ds(float(x)) for x in g.origin_mm]
    grid.GridDimensions = [int(v) for v in g.size]
    grid.GridResolution = [float(v) for v in g.spacing_mm]
    grid.VectorGridData = np.ascontiguousarray(field_mm, dtype="<f4").tobytes()
    reg = Dataset()
    reg.ReferencedImageSequence = _instances(ref)
    reg.SourceFrameOfReferenceUID = source_frame_of_reference_uid or ref.frame_of_reference_uid
    reg.DeformableRegistrationGridSequence = Sequence([grid])
    reg.PreDeformationMatrixRegistrationSequence = matrix()
    reg.PostDeformationMatrixRegistrationSequence = matrix()
    code = Dataset()
    code.CodeValue = "125024"
    code.CodingSchemeDesignator = "DCM"
    code.CodeMeaning = "Image Content-based Alignment"
    reg.RegistrationTypeCodeSequence = Sequence([code])
    ds.DeformableRegistrationSequence = Sequence([reg])
    _save(ds, path)


def read_registration(path: str) -> tuple[np.ndarray, Geometry]:
    """The displacement field ((z, y, x, 3) mm) and its grid from a Deformable Spatial Registration written here."""
    import pydicom

    ds = pydicom.dcmread(path)
    if str(ds.SOPClassUID) != DEFORMABLE_REGISTRATION:
        raise InputError(f"{path} is not a Deformable Spatial Registration")
    grid = ds.DeformableRegistrationSequence[0].DeformableRegistrationGridSequence[0]
    size = tuple(int(v) for v in grid.GridDimensions)
    iop = np.array([float(x) for x in grid.ImageOrientationPatient])
    n = np.cross(iop[:3], iop[3:])
    geometry = Geometry(size, tuple(float(v) for v in grid.GridResolution), tuple(float(x) for x in grid.ImagePositionPatient),
                        tuple(np.stack([iop[:3], iop[3:], n], axis=1).ravel().tolist()))
    field_mm = np.frombuffer(grid.VectorGridData, dtype="<f4").reshape(size[::-1] + (3,))
    return field_mm, geometry


# ------------------------------------------------------------------------------------------------
# a planning case from a DICOM series and its structure set
# ------------------------------------------------------------------------------------------------

def case_from_rtstruct(image_folder: str, rtstruct: str, mapping: dict[str, str] | None = None, organs: str = "psdl"):
    """A :class:`~warpmpm.images.Case` from a DICOM planning series and its RT Structure Set.

    The organs are found by name (:func:`find_structures`; ``mapping`` organ -> ROI name first) and rasterised on the
    series' grid, labelled with the AMOS values (3 left kidney, 7 stomach, 10 pancreas, 13 duodenum). A voxel in two
    organs' contours goes to the first of pancreas, duodenum, stomach, left kidney (a warning gives the counts).
    ``case.meta["dicom"]`` keeps the series reference and ``case.meta["roi_names"]`` each organ's ROI name.
    Raises :class:`InputError` naming the organ, the structure or the frame of reference that is wrong.
    """
    import warnings

    import pydicom

    from .errors import InputWarning
    from .images import PRESETS, Case, read_volume

    if not os.path.isfile(rtstruct):
        raise InputError(f"structure set not found: {rtstruct}")
    if not os.path.isdir(image_folder):
        raise InputError(f"--rtstruct needs the planning image as a DICOM series folder (--image FOLDER); {image_folder} is not a folder")
    ref = read_series_reference(image_folder)
    image = read_volume(image_folder)
    geometry = Geometry.of(image)
    ref.geometry = geometry
    try:
        names = [str(r.ROIName) for r in pydicom.dcmread(rtstruct, stop_before_pixels=True).get("StructureSetROISequence", [])]
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"cannot read the structure set {rtstruct}: {exc}") from None
    letters = {"p": "pancreas", "s": "stomach", "d": "duodenum", "l": "left_kidney"}
    wanted = [letters[c] for c in organs if c in letters]
    found = find_structures(names, mapping, organs=tuple(letters.values()))
    missing = [o for o in wanted if o not in found]
    if missing:
        leave = ("the pancreas is always modelled" if missing[0] == "pancreas" else "or leave the organ out with --organs")
        raise InputError(f"the structure set {rtstruct} has no structure for {', '.join(missing)} (it holds: {', '.join(names)}); "
                         f"name it with --structure {missing[0]}=NAME; {leave}")
    masks = read_rtstruct(rtstruct, geometry, ref.frame_of_reference_uid, rois=[found[o] for o in wanted])
    label_map = dict(PRESETS["amos"])
    labels = np.zeros(tuple(geometry.size[::-1]), dtype=np.int32)
    overlaps = []
    for organ in ("pancreas", "duodenum", "stomach", "left_kidney"):
        if organ not in wanted:
            continue
        m = masks[found[organ]]
        if not m.any():
            raise InputError(f"structure {found[organ]!r} ({organ}) in {rtstruct} covers no voxel of the planning image")
        taken = m & (labels > 0)
        if taken.any():
            overlaps.append(f"{int(taken.sum())} voxels of {found[organ]!r}")
        labels[m & (labels == 0)] = label_map[organ]
    if overlaps:
        warnings.warn(f"structures overlap; the overlapping voxels go to the organ first in pancreas, duodenum, stomach, left "
                      f"kidney: {', '.join(overlaps)}", InputWarning, stacklevel=2)
    arr = sitk.GetArrayFromImage(image).astype(np.float32)
    case = Case(labels, geometry, {o: label_map[o] for o in wanted}, arr, os.path.basename(os.path.normpath(image_folder)),
                f"{image_folder} + {rtstruct}")
    case.meta["dicom"] = ref
    case.meta["roi_names"] = {o: found[o] for o in wanted}
    return case


class FrameDicomWriter:
    """Writes a tracked frame for the planning system: ``OUT/dicom/frame_NNNN/RS.dcm`` (the estimated organs) and
    ``REG.dcm`` (the estimate's displacement, planning to frame), both referring to the planning series ``ref``.

    ``roi_names``: organ -> ROI name (the planning structure set's names; default the organ's name).
    ``cine_frame_of_reference``: the cine frames' Frame of Reference UID, the REG's source (default: the planning one's:
    the cine is taken to be in the planning scan's coordinates, which is what tracking assumes)."""

    def __init__(self, ref: SeriesReference, roi_names: dict[str, str] | None = None, cine_frame_of_reference: str | None = None):
        self.ref = ref
        self.roi_names = dict(roi_names or {})
        self.source = cine_frame_of_reference or None  # the REG's source: the cine's frame of reference when its files name one

    def write(self, out_dir: str, n: int, labels: np.ndarray, label_map: dict[str, int], field_mm: np.ndarray,
              time_s: float) -> None:
        folder = os.path.join(out_dir, "dicom", f"frame_{n:04d}")
        os.makedirs(folder, exist_ok=True)
        masks = {o: labels == v for o, v in label_map.items()}
        what = f"warpmpm frame {n} (t = {time_s:.3f} s)"
        write_rtstruct(os.path.join(folder, "RS.dcm"), self.ref, masks, self.roi_names, label=f"frame {n}", description=what)
        write_registration(os.path.join(folder, "REG.dcm"), self.ref, field_mm, description=what,
                           source_frame_of_reference_uid=self.source)


def write_rtdose(path: str, ref: SeriesReference, dose_gy: np.ndarray, plan_uid: str | None = None,
                 description: str = "warpmpm dose") -> None:
    """An RT Dose (Gy, summation PLAN) on the planning grid of ``ref`` (multi-frame, one frame per slice along its
    third axis), referring to the RT Plan ``plan_uid`` (the planned dose's plan; a new UID when unknown)."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    g = ref.geometry
    dose_gy = np.asarray(dose_gy, dtype=np.float64)
    if dose_gy.shape != tuple(g.size[::-1]):
        raise InputError(f"RT Dose: a dose of shape {dose_gy.shape}, the grid is {tuple(g.size[::-1])} (z, y, x)")
    if not np.isfinite(dose_gy).all() or dose_gy.min() < 0:
        raise InputError("RT Dose: the dose holds negative or non-finite values; nothing was written")
    scale = max(float(dose_gy.max()), 1e-9) / 65535.0
    ds = _base(RT_DOSE, _uid(), ref, "RTDOSE", _uid(), 903, description)
    ds.FrameOfReferenceUID = ref.frame_of_reference_uid
    ds.PositionReferenceIndicator = ""
    d = g.direction_matrix
    ds.ImageType = ["DERIVED", "SECONDARY", "OTHER"]
    ds.ImagePositionPatient = [_ds(float(x)) for x in g.origin_mm]
    ds.ImageOrientationPatient = [_ds(float(x)) for x in np.concatenate([d[:, 0], d[:, 1]])]
    ds.PixelSpacing = [_ds(g.spacing_mm[1]), _ds(g.spacing_mm[0])]
    ds.SliceThickness = _ds(g.spacing_mm[2])
    ds.NumberOfFrames = g.size[2]
    ds.FrameIncrementPointer = 0x3004000C
    ds.GridFrameOffsetVector = [_ds(k * g.spacing_mm[2]) for k in range(g.size[2])]
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = g.size[1], g.size[0]
    ds.BitsAllocated = ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.DoseUnits = "GY"
    ds.DoseType = "PHYSICAL"
    ds.DoseSummationType = "PLAN"
    ds.DoseGridScaling = _ds(scale)
    ds.DoseComment = SHORT_DISCLAIMER
    plan = Dataset()
    plan.ReferencedSOPClassUID = "1.2.840.10008.5.1.4.1.1.481.5"
    plan.ReferencedSOPInstanceUID = plan_uid or _uid()
    ds.ReferencedRTPlanSequence = Sequence([plan])
    ds.PixelData = np.rint(dose_gy / scale).astype("<u2").tobytes()
    _save(ds, path)
