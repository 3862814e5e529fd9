"""Per-frame DICOM output of the tracker (:class:`FrameDicomWriter`): each frame's structure set and registration."""

from __future__ import annotations

import os

import numpy as np

from .common import SeriesReference
from .registration import write_registration
from .rtstruct import write_rtstruct

__all__ = ["FrameDicomWriter"]


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
        empty = [self.roi_names.get(o, o) for o, m in masks.items() if not m.any()]
        if empty:
            import warnings

            from ..errors import InputWarning

            warnings.warn(f"frame {n}: the estimated {', '.join(repr(e) for e in empty)} cover{'s' if len(empty) == 1 else ''} "
                          f"no voxel of the planning grid (moved outside the planning scan?); {'its ROI is' if len(empty) == 1 else 'their ROIs are'} "
                          f"empty in {os.path.join(folder, 'RS.dcm')}", InputWarning, stacklevel=2)
        what = f"warpmpm frame {n} (t = {time_s:.3f} s)"
        write_rtstruct(os.path.join(folder, "RS.dcm"), self.ref, masks, self.roi_names, label=f"frame {n}", description=what)
        write_registration(os.path.join(folder, "REG.dcm"), self.ref, field_mm, description=what,
                           source_frame_of_reference_uid=self.source)
