"""Deformable Spatial Registrations: :func:`write_registration` (planning to frame, mm along LPS) and
:func:`read_registration`."""

from __future__ import annotations


import numpy as np

from ..errors import InputError
from ..images import Geometry
from .common import _base, _ds, _instances, _save, _uid, DEFORMABLE_REGISTRATION, SeriesReference, SHORT_DISCLAIMER

__all__ = ["write_registration", "read_registration"]


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
