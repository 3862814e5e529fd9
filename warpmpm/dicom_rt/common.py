"""What every DICOM object written here shares: SOP classes, UIDs, the patient/study/series module of the planning
series referenced (:class:`SeriesReference`), the disclaimer, the structure names of each organ."""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass, field


from ..images import Geometry

__all__ = ["MR_IMAGE", "CT_IMAGE", "RT_STRUCTURE_SET", "DEFORMABLE_REGISTRATION", "RT_DOSE", "IMPLEMENTATION_NAME",
           "DISCLAIMER", "SHORT_DISCLAIMER", "STRUCTURE_NAMES", "SeriesReference"]


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
