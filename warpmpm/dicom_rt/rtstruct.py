"""RT Structure Sets: :func:`write_rtstruct` (one ROI per organ, closed planar contours at the half-voxel boundary),
:func:`read_rtstruct` (contours back to masks, even-odd) and :func:`find_structures` (organ -> ROI name)."""

from __future__ import annotations

import re

import numpy as np

from ..errors import InputError
from ..images import Geometry
from .common import _base, _ds, _instances, _save, _uid, DISCLAIMER, RT_STRUCTURE_SET, SeriesReference, STRUCTURE_NAMES

__all__ = ["write_rtstruct", "read_rtstruct", "find_structures"]


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
    from matplotlib.path import Path

    ds = _read_structure_set(path)
    frames = {str(f.get("FrameOfReferenceUID", "")) for f in ds.get("ReferencedFrameOfReferenceSequence", [])} - {""}
    names = _roi_names(ds, path)
    roi_frames = {int(r.ROINumber): str(r.get("ReferencedFrameOfReferenceUID", "")) for r in ds.get("StructureSetROISequence", [])}
    g = geometry
    shape = tuple(g.size[::-1])
    jj, ii = np.mgrid[0:shape[1], 0:shape[2]]
    centres = np.column_stack([ii.ravel(), jj.ravel()]).astype(np.float64)
    out = {}
    off_series: dict[str, int] = {}
    for rc in ds.get("ROIContourSequence", []):
        try:
            number = int(rc.ReferencedROINumber)
        except (AttributeError, TypeError, ValueError):
            raise InputError(f"the structure set {path} has a contour sequence without a valid ReferencedROINumber (is the "
                             "file cut short?); export it again from the planning system") from None
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
            try:
                data = np.asarray([float(v) for v in c.get("ContourData", [])], dtype=np.float64)
            except (TypeError, ValueError):
                raise InputError(f"structure {name!r} in {path}: a contour holds a value that is not a number; mend it in the "
                                 "planning system") from None
            if kind == "POINT":
                continue
            if not np.all(np.isfinite(data)):
                raise InputError(f"structure {name!r} in {path}: a contour holds a non-finite (NaN or Inf) point; mend it in "
                                 "the planning system")
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
                off_series[name] = off_series.get(name, 0) + 1
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
    if off_series:
        import warnings

        from ..errors import InputWarning

        warnings.warn(f"the structure set {path} has contours beyond the planning series' slices, left out: "
                      + ", ".join(f"{n} contour(s) of {name!r}" for name, n in off_series.items())
                      + "; is the series complete?", InputWarning, stacklevel=2)
    return out


def _read_structure_set(path: str):
    """The structure set's dataset, refused (naming the file) when unreadable, cut, or of another SOP class."""
    import pydicom

    try:
        ds = pydicom.dcmread(path)
        ds.get("StructureSetROISequence", [])  # parse the sequences now: a file cut short fails here, not later
        ds.get("ROIContourSequence", [])
    except Exception as exc:  # noqa: BLE001 - pydicom's many ways to fail on a broken file
        raise InputError(f"cannot read the structure set {path} ({type(exc).__name__}: {exc}); is it cut short? Export it "
                         "again from the planning system") from None
    if str(ds.get("SOPClassUID", "")) != RT_STRUCTURE_SET:
        raise InputError(f"{path} is not an RT Structure Set (SOP class {ds.get('SOPClassUID', 'missing')})")
    return ds


def _roi_names(ds, path: str) -> dict[int, str]:
    """ROI number -> name; refused when a number is missing, not a number, or used twice."""
    names: dict[int, str] = {}
    for r in ds.get("StructureSetROISequence", []):
        try:
            number = int(r.ROINumber)
        except (AttributeError, TypeError, ValueError):
            raise InputError(f"the structure set {path} has an ROI without a valid ROINumber; export it again") from None
        name = str(r.get("ROIName", "") or f"ROI {number}")
        if number in names:
            raise InputError(f"the structure set {path} gives ROINumber {number} to two structures ({names[number]!r} and "
                             f"{name!r}): which contours are whose cannot be told; export it again from the planning system")
        names[number] = name
    return names


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
