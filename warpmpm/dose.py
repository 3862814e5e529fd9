"""Dose from motion: what each organ received through the estimated motion, accumulated over a cine series.

The planned dose ``D(y)`` (Gy) is fixed in the room (the scanner's frame of reference, world LPS mm); the tissue moves.
The tissue at planning position ``x`` sits at ``x + u_f(x)`` in frame ``f`` (the estimate's displacement, planning to
frame), so it receives there ``D(x + u_f(x))``. Accumulated over the series with weights ``w_f`` (equal, or each frame's
beam-on time), the dose of that tissue is

    D_acc(x) = sum_f w_f D(x + u_f(x)) / sum_f w_f,

evaluated at the centre of every planning voxel inside an organ (trilinear in the dose grid; outside the dose grid the
dose is 0, and the share of each organ outside it, per frame, is written to ``dose_coverage.csv``, its worst frame to
``dose_metrics.csv`` and a warning names the organ and frame above a threshold). The planned DVH is ``D(x)`` over the same voxels: the two differ only by the motion. Dose-volume figures
per organ: ``D95``/``D98`` (the least dose to the best-covered 95 % / 98 % of the organ), ``D0.5cc``/``D1cc`` (the
least dose to the hottest 0.5 / 1 cm^3), ``Dmax`` and ``Dmean`` (Gy); the DVH is cumulative (volume % receiving at
least each dose).

Reads RT Dose (DICOM; DoseGridScaling, GridFrameOffsetVector) or a dose image on any grid (NIfTI/MHA/NRRD, in Gy).
"""

from __future__ import annotations

import csv
import math
import os

import numpy as np
import SimpleITK as sitk

from .errors import InputError
from .images import Geometry, read_volume

__all__ = ["read_dose", "DoseAccumulator", "dose_metrics", "METRICS"]

METRICS = ("D98_Gy", "D95_Gy", "D1cc_Gy", "D0.5cc_Gy", "Dmax_Gy", "Dmean_Gy")


def _dicom_number(ds, name: str, path: str, count: int | None = None, positive: bool = False):
    """A numeric tag of ``ds`` as a float (or a list of ``count`` floats), refused when absent, empty, non-finite or (with
    ``positive``) not above zero."""
    if name not in ds or ds.get(name) in (None, ""):
        raise InputError(f"RT Dose {path} has no {name}; it is required to read the dose (export it again from the planning "
                         "system)")
    raw = ds.get(name)
    try:
        values = [float(x) for x in raw] if count is not None else [float(raw)]
    except (TypeError, ValueError):
        raise InputError(f"RT Dose {path}: {name} {raw!r} is not a number; export the dose again from the planning "
                         "system") from None
    if count is not None and len(values) != count:
        raise InputError(f"RT Dose {path}: {name} holds {len(values)} values, {count} are required; export the dose again "
                         "from the planning system")
    if not all(np.isfinite(values)) or (positive and not all(v > 0 for v in values)):
        raise InputError(f"RT Dose {path}: {name} {raw!r} must be finite{' and above zero' if positive else ''}; export "
                         "the dose again from the planning system")
    return values if count is not None else values[0]


def read_dose(path: str, max_gy: float = 120.0) -> sitk.Image:
    """A dose (Gy) as a 3D image in world LPS mm: an RT Dose file, or an image any SimpleITK reads (values in Gy).

    Refused, naming the file and the tag: a missing, empty or non-finite DoseGridScaling, spacing or position; units
    other than GY; negative voxels; a voxel above ``max_gy`` (a dose in cGy labelled Gy is 100x too high: a plan of
    50 Gy reads as 5000). An RT Dose keeps its Frame of Reference UID and patient ID as metadata
    (``frame_of_reference``, ``patient``) for the caller to check against the planning series.
    """
    if not os.path.exists(path):
        raise InputError(f"dose not found: {path}")
    if not (math.isfinite(max_gy) and max_gy > 0):
        raise InputError(f"the largest plausible dose must be a positive number of Gy, got {max_gy}")
    if os.path.isfile(path) and path.lower().endswith(".dcm"):
        import pydicom

        try:
            ds = pydicom.dcmread(path)
            if str(ds.get("Modality", "")) != "RTDOSE":
                raise InputError(f"{path} is not an RT Dose (modality {ds.get('Modality', 'missing')})")
            if str(ds.get("DoseUnits", "")).upper() != "GY":
                raise InputError(f"{path}: dose units {str(ds.get('DoseUnits', '')) or 'missing'}; an RT Dose in Gy (GY) is "
                                 "required (RELATIVE doses cannot be accumulated)")
            frames = int(ds.get("NumberOfFrames", 1) or 1)
            rows, cols = int(ds.Rows), int(ds.Columns)
            pixels = ds.pixel_array
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - pydicom's many ways to fail on a broken file
            raise InputError(f"cannot read the dose {path} ({type(exc).__name__}: {exc}); export it again from the planning "
                             "system") from None
        scaling = _dicom_number(ds, "DoseGridScaling", path, positive=True)
        if pixels.size != frames * rows * cols:
            raise InputError(f"RT Dose {path}: {pixels.size} dose values for {frames} x {rows} x {cols}; the file is cut or "
                             "its NumberOfFrames is wrong")
        arr = pixels.reshape(frames, rows, cols).astype(np.float64) * scaling
        iop = np.array(_dicom_number(ds, "ImageOrientationPatient", path, count=6))
        if not (abs(np.linalg.norm(iop[:3]) - 1) < 1e-3 and abs(np.linalg.norm(iop[3:]) - 1) < 1e-3
                and abs(iop[:3] @ iop[3:]) < 1e-3):
            raise InputError(f"RT Dose {path}: ImageOrientationPatient {iop.tolist()} is not two perpendicular unit vectors")
        position = np.array(_dicom_number(ds, "ImagePositionPatient", path, count=3))
        sp = _dicom_number(ds, "PixelSpacing", path, count=2, positive=True)  # between rows, between columns
        offsets = np.array(_dicom_number(ds, "GridFrameOffsetVector", path, count=frames)
                           if frames > 1 or "GridFrameOffsetVector" in ds else [0.0])
        if len(offsets) != frames:
            raise InputError(f"{path}: {len(offsets)} grid frame offsets for {frames} frames")
        dz = float(np.diff(offsets).mean()) if frames > 1 else float(ds.get("SliceThickness", 1.0) or 1.0)
        if frames > 1 and (abs(dz) < 1e-6 or not np.allclose(np.diff(offsets), dz, atol=1e-3)):
            raise InputError(f"{path}: its dose planes are not evenly spaced (GridFrameOffsetVector)")
        normal = np.cross(iop[:3], iop[3:])
        ipp = position + offsets[0] * normal
        if dz < 0:  # frames in decreasing order along the normal: flip so that the third axis runs along it
            arr, dz, ipp = arr[::-1], -dz, ipp + offsets[-1] * normal - offsets[0] * normal
        img = sitk.GetImageFromArray(arr.astype(np.float32))
        img.SetSpacing((sp[1], sp[0], dz))
        img.SetOrigin(tuple(ipp))
        img.SetDirection(tuple(np.stack([iop[:3], iop[3:], normal], 1).ravel()))
        plans = ds.get("ReferencedRTPlanSequence", [])
        if plans and plans[0].get("ReferencedSOPInstanceUID"):
            img.SetMetaData("plan_uid", str(plans[0].ReferencedSOPInstanceUID))
        for tag, key in (("FrameOfReferenceUID", "frame_of_reference"), ("PatientID", "patient")):
            if str(ds.get(tag, "") or "").strip():
                img.SetMetaData(key, str(ds.get(tag)).strip())
    else:
        img = sitk.Cast(read_volume(path), sitk.sitkFloat32)
    arr = sitk.GetArrayViewFromImage(img)
    if not np.isfinite(arr).all():
        raise InputError(f"dose {path} holds non-finite values; export the plan's physical dose in Gy again")
    if arr.min() < 0:
        raise InputError(f"dose {path} holds negative values (down to {float(arr.min()):.3g} Gy); a physical dose is >= 0: "
                         "export the plan's physical dose in Gy")
    if arr.max() > max_gy:
        raise InputError(f"dose {path} reaches {float(arr.max()):.4g} Gy, above the plausible {max_gy:g} Gy: is it in cGy "
                         "labelled Gy, or is its DoseGridScaling wrong? Export it in Gy, or raise --max-dose-gy if the plan "
                         "really gives this much")
    return img


def _sample(dose: sitk.Image, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The dose at ``points_mm`` (trilinear; 0 outside the grid) and which points lie outside the grid (beyond the
    centres of its outermost voxels)."""
    from scipy import ndimage

    g = Geometry.of(dose)
    q = g.world_to_index(points_mm)
    outside = np.any((q < -1e-6) | (q > np.asarray(g.size, dtype=np.float64) - 1 + 1e-6), axis=1)
    values = ndimage.map_coordinates(sitk.GetArrayViewFromImage(dose), q[:, ::-1].T, order=1, mode="constant", cval=0.0)
    return values, outside


def dose_metrics(doses_gy: np.ndarray, voxel_cc: float) -> dict:
    """D98, D95, D1cc, D0.5cc, Dmax, Dmean (Gy) of one organ's voxel doses (each voxel ``voxel_cc`` cm^3)."""
    d = np.sort(np.asarray(doses_gy, dtype=np.float64))[::-1]  # hottest first
    if not d.size:
        return {m: float("nan") for m in METRICS}

    def hottest(cc):  # the least dose within the hottest ``cc``
        n = int(np.ceil(cc / voxel_cc - 1e-9))
        return float(d[min(max(n, 1), d.size) - 1])

    def covering(fraction):  # the least dose to the best-covered ``fraction`` of the volume
        n = int(np.ceil(fraction * d.size - 1e-9))
        return float(d[min(max(n, 1), d.size) - 1])

    return {"D98_Gy": covering(0.98), "D95_Gy": covering(0.95), "D1cc_Gy": hottest(1.0), "D0.5cc_Gy": hottest(0.5),
            "Dmax_Gy": float(d[0]), "Dmean_Gy": float(d.mean())}


class DoseAccumulator:
    """Accumulates each organ's dose over the frames of a series (module docstring).

    Args:
        dose: the planned dose (Gy) on any grid (:func:`read_dose`).
        geometry: the planning grid. masks: organ -> boolean (z, y, x) of its planning voxels.
    """

    def __init__(self, dose: sitk.Image, geometry: Geometry, masks: dict[str, np.ndarray], warn_outside_pct: float = 1.0):
        import warnings

        from .errors import InputWarning

        if not (math.isfinite(warn_outside_pct) and 0 <= warn_outside_pct <= 100):
            raise InputError(f"the dose-grid coverage warning threshold must be a percentage in 0..100, got {warn_outside_pct}")
        self.dose = dose
        self.geometry = geometry
        self.warn_outside_pct = warn_outside_pct
        self.index = {o: np.argwhere(m) for o, m in masks.items() if np.any(m)}
        self.points = {o: geometry.index_to_world(ix[:, ::-1].astype(np.float64)) for o, ix in self.index.items()}
        sampled = {o: _sample(dose, p) for o, p in self.points.items()}
        self.planned = {o: v for o, (v, _) in sampled.items()}
        if all(float(np.max(v)) <= 0 for v in self.planned.values()):
            raise InputError("the dose is zero on every organ: is it of this plan, and on this scan's frame of reference?")
        #: per frame (the first row: planning), organ -> % of its voxels outside the dose grid (their dose counted as 0 Gy)
        self.outside_pct: list[dict[str, float]] = [{o: 100.0 * float(out.mean()) for o, (_, out) in sampled.items()}]
        late = {o: v for o, v in self.outside_pct[0].items() if v > warn_outside_pct}
        if late:
            warnings.warn("at planning, " + ", ".join(f"{v:.1f} % of the {o}" for o, v in late.items()) + " lie outside the "
                          "dose grid (counted as 0 Gy): is the dose grid cropped?", InputWarning, stacklevel=2)
        self.total = {o: np.zeros(len(p)) for o, p in self.points.items()}
        self.weight = 0.0
        self.voxel_cc = geometry.voxel_volume_mm3 / 1000.0

    def add(self, field_mm: np.ndarray, weight: float = 1.0) -> None:
        """One frame: ``field_mm`` (z, y, x, 3) the displacement (mm, planning to frame) on the planning grid. Warns when
        more than ``warn_outside_pct`` % of an organ is carried outside the dose grid (counted as 0 Gy there)."""
        import warnings

        from .errors import InputWarning

        if not (np.isfinite(weight) and 0 <= weight <= 86400.0):
            raise InputError(f"a frame's dose weight must be finite and within 0..86400 (s), got {weight}")
        frame = len(self.outside_pct) - 1
        shares = {}
        for o, ix in self.index.items():
            u = field_mm[ix[:, 0], ix[:, 1], ix[:, 2]]
            values, outside = _sample(self.dose, self.points[o] + u)
            self.total[o] += weight * values
            shares[o] = 100.0 * float(outside.mean())
        self.outside_pct.append(shares)
        late = {o: v for o, v in shares.items() if v > self.warn_outside_pct and v > self.outside_pct[0][o]}
        if late:
            warnings.warn(f"frame {frame}: " + ", ".join(f"{v:.1f} % of the {o}" for o, v in late.items()) + " moved outside "
                          "the dose grid (counted as 0 Gy there): the accumulated dose of "
                          f"{'these organs' if len(late) > 1 else 'this organ'} is too low; use a dose grid that covers the "
                          "motion", InputWarning, stacklevel=2)
        self.weight += weight

    def accumulated(self) -> dict[str, np.ndarray]:
        if self.weight <= 0:
            raise InputError("no frame carried dose (every beam-on weight is zero)")
        return {o: t / self.weight for o, t in self.total.items()}

    def accumulated_image(self) -> sitk.Image:
        """The accumulated dose (Gy) of the tissue at each planning voxel inside the organs (0 elsewhere)."""
        arr = np.zeros(tuple(self.geometry.size[::-1]), dtype=np.float32)
        for o, d in self.accumulated().items():
            ix = self.index[o]
            arr[ix[:, 0], ix[:, 1], ix[:, 2]] = d
        return self.geometry.apply_to(sitk.GetImageFromArray(arr))

    def metrics(self) -> list[dict]:
        acc = self.accumulated()
        rows = []
        for o in self.index:
            p, a = dose_metrics(self.planned[o], self.voxel_cc), dose_metrics(acc[o], self.voxel_cc)
            worst = max(f[o] for f in self.outside_pct)
            for m in METRICS:
                rows.append({"organ": o, "metric": m, "planned": p[m], "accumulated": a[m], "difference": a[m] - p[m],
                             "outside_dose_grid_max_pct": worst})
        return rows

    def dvh(self, bins: int = 200) -> tuple[np.ndarray, dict]:
        """Cumulative DVHs: dose axis (Gy) and organ -> (planned %, accumulated %) of volume receiving at least it."""
        acc = self.accumulated()
        top = max(max(float(v.max()) for v in self.planned.values()), max(float(v.max()) for v in acc.values()))
        axis = np.linspace(0.0, top * 1.02, bins)
        out = {o: (100.0 * (self.planned[o][None, :] >= axis[:, None]).mean(1), 100.0 * (acc[o][None, :] >= axis[:, None]).mean(1))
               for o in self.index}
        return axis, out

    def write(self, folder: str, frames: int) -> None:
        """``dvh.csv``, ``dose_metrics.csv``, ``dvh.png`` and ``accumulated_dose.nii.gz`` into ``folder``."""
        os.makedirs(folder, exist_ok=True)
        axis, curves = self.dvh()
        with open(os.path.join(folder, "dvh.csv.part"), "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["dose_Gy"] + [f"{o}_{k}_pct" for o in curves for k in ("planned", "accumulated")])
            for n, d in enumerate(axis):
                w.writerow([f"{d:.4f}"] + [f"{curves[o][k][n]:.3f}" for o in curves for k in (0, 1)])
        os.replace(os.path.join(folder, "dvh.csv.part"), os.path.join(folder, "dvh.csv"))
        with open(os.path.join(folder, "dose_metrics.csv.part"), "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=["organ", "metric", "planned", "accumulated", "difference", "outside_dose_grid_max_pct"])
            w.writeheader()
            for r in self.metrics():
                w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})
        os.replace(os.path.join(folder, "dose_metrics.csv.part"), os.path.join(folder, "dose_metrics.csv"))
        with open(os.path.join(folder, "dose_coverage.csv.part"), "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["frame"] + [f"{o}_outside_dose_grid_pct" for o in self.index])
            for n, shares in enumerate(self.outside_pct):
                w.writerow(["planning" if n == 0 else n - 1] + [f"{shares[o]:.2f}" for o in self.index])
        os.replace(os.path.join(folder, "dose_coverage.csv.part"), os.path.join(folder, "dose_coverage.csv"))
        sitk.WriteImage(self.accumulated_image(), os.path.join(folder, "accumulated_dose.part.nii.gz"))
        os.replace(os.path.join(folder, "accumulated_dose.part.nii.gz"), os.path.join(folder, "accumulated_dose.nii.gz"))
        self._plot(axis, curves, os.path.join(folder, "dvh.png"), frames)

    def _plot(self, axis, curves, path, frames):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        colours = {"pancreas": "tab:orange", "stomach": "tab:blue", "duodenum": "tab:green", "left_kidney": "tab:purple"}
        fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
        for o, (p, a) in curves.items():
            c = colours.get(o, None)
            ax.plot(axis, p, "--", color=c, lw=1.2, label=f"{o} planned")
            ax.plot(axis, a, "-", color=c, lw=1.8, label=f"{o} accumulated")
        ax.set_xlabel("dose (Gy)")
        ax.set_ylabel("volume receiving at least this dose (%)")
        ax.set_title(f"DVH: planned vs accumulated through the estimated motion ({frames} frames)", fontsize=9)
        ax.set_ylim(0, 101)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
        fig.text(0.01, 0.01, "warpmpm research estimate; not a medical device", fontsize=6, color="grey")
        fig.tight_layout()
        fig.savefig(path + ".part.png")
        plt.close(fig)
        os.replace(path + ".part.png", path)
