"""RT Dose: :func:`write_rtdose` writes a dose grid (Gy) referencing the planning series."""

from __future__ import annotations


import numpy as np

from ..errors import InputError
from .common import _base, _ds, _save, _uid, RT_DOSE, SeriesReference, SHORT_DISCLAIMER

__all__ = ["write_rtdose"]


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
