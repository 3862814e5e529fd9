"""Dose from motion: what each organ received through the estimated motion, accumulated over a cine series.

The planned dose ``D(y)`` (Gy) is fixed in the room (the scanner's frame of reference, world LPS mm); the tissue moves.
The tissue at planning position ``x`` sits at ``x + u_f(x)`` in frame ``f`` (the estimate's displacement, planning to
frame), so it receives there ``D(x + u_f(x))``. Accumulated over the series with weights ``w_f`` (equal, or each frame's
beam-on time), the dose of that tissue is

    D_acc(x) = sum_f w_f D(x + u_f(x)) / sum_f w_f,

evaluated at the centre of every planning voxel inside an organ (trilinear in the dose grid; outside the dose grid the
dose is 0). The planned DVH is ``D(x)`` over the same voxels: the two differ only by the motion. Dose-volume figures
per organ: ``D95``/``D98`` (the least dose to the best-covered 95 % / 98 % of the organ), ``D0.5cc``/``D1cc`` (the
least dose to the hottest 0.5 / 1 cm^3), ``Dmax`` and ``Dmean`` (Gy); the DVH is cumulative (volume % receiving at
least each dose).

Reads RT Dose (DICOM; DoseGridScaling, GridFrameOffsetVector) or a dose image on any grid (NIfTI/MHA/NRRD, in Gy).
"""

from __future__ import annotations

import csv
import os

import numpy as np
import SimpleITK as sitk

from .errors import InputError
from .images import Geometry, read_volume

__all__ = ["read_dose", "DoseAccumulator", "dose_metrics", "METRICS"]

METRICS = ("D98_Gy", "D95_Gy", "D1cc_Gy", "D0.5cc_Gy", "Dmax_Gy", "Dmean_Gy")


def read_dose(path: str) -> sitk.Image:
    """A dose (Gy) as a 3D image in world LPS mm: an RT Dose file, or an image any SimpleITK reads (values in Gy)."""
    if not os.path.exists(path):
        raise InputError(f"dose not found: {path}")
    if os.path.isfile(path) and path.lower().endswith(".dcm"):
        import pydicom

        try:
            ds = pydicom.dcmread(path)
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"cannot read the dose {path}: {exc}") from None
        if str(ds.get("Modality", "")) != "RTDOSE":
            raise InputError(f"{path} is not an RT Dose (modality {ds.get('Modality', 'missing')})")
        if str(ds.get("DoseUnits", "GY")).upper() != "GY":
            raise InputError(f"{path}: dose units {ds.DoseUnits}; Gy (GY) is required")
        frames = int(ds.get("NumberOfFrames", 1))
        arr = ds.pixel_array.reshape(frames, int(ds.Rows), int(ds.Columns)).astype(np.float64) * float(ds.DoseGridScaling)
        iop = np.array([float(x) for x in ds.ImageOrientationPatient])
        offsets = np.array([float(x) for x in ds.get("GridFrameOffsetVector", [0.0])])
        if len(offsets) != frames:
            raise InputError(f"{path}: {len(offsets)} grid frame offsets for {frames} frames")
        dz = float(np.diff(offsets).mean()) if frames > 1 else float(ds.get("SliceThickness", 1.0) or 1.0)
        if frames > 1 and not np.allclose(np.diff(offsets), dz, atol=1e-3):
            raise InputError(f"{path}: its dose planes are not evenly spaced (GridFrameOffsetVector)")
        normal = np.cross(iop[:3], iop[3:])
        ipp = np.array([float(x) for x in ds.ImagePositionPatient]) + offsets[0] * normal
        if dz < 0:  # frames in decreasing order along the normal: flip so that the third axis runs along it
            arr, dz, ipp = arr[::-1], -dz, ipp + offsets[-1] * normal - offsets[0] * normal
        sp = [float(x) for x in ds.PixelSpacing]  # between rows, between columns
        img = sitk.GetImageFromArray(arr.astype(np.float32))
        img.SetSpacing((sp[1], sp[0], dz))
        img.SetOrigin(tuple(ipp))
        img.SetDirection(tuple(np.stack([iop[:3], iop[3:], normal], 1).ravel()))
        plans = ds.get("ReferencedRTPlanSequence", [])
        if plans:
            img.SetMetaData("plan_uid", str(plans[0].ReferencedSOPInstanceUID))
        return img
    img = sitk.Cast(read_volume(path), sitk.sitkFloat32)
    arr = sitk.GetArrayViewFromImage(img)
    if not np.isfinite(arr).all() or arr.min() < 0:
        raise InputError(f"dose {path} holds negative or non-finite values")
    return img


def _sample(dose: sitk.Image, points_mm: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    g = Geometry.of(dose)
    q = g.world_to_index(points_mm)
    return ndimage.map_coordinates(sitk.GetArrayViewFromImage(dose), q[:, ::-1].T, order=1, mode="constant", cval=0.0)


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

    def __init__(self, dose: sitk.Image, geometry: Geometry, masks: dict[str, np.ndarray]):
        self.dose = dose
        self.geometry = geometry
        self.index = {o: np.argwhere(m) for o, m in masks.items() if np.any(m)}
        self.points = {o: geometry.index_to_world(ix[:, ::-1].astype(np.float64)) for o, ix in self.index.items()}
        self.planned = {o: _sample(dose, p) for o, p in self.points.items()}
        if all(float(np.max(v)) <= 0 for v in self.planned.values()):
            raise InputError("the dose is zero on every organ: is it of this plan, and on this scan's frame of reference?")
        self.total = {o: np.zeros(len(p)) for o, p in self.points.items()}
        self.weight = 0.0
        self.voxel_cc = geometry.voxel_volume_mm3 / 1000.0

    def add(self, field_mm: np.ndarray, weight: float = 1.0) -> None:
        """One frame: ``field_mm`` (z, y, x, 3) the displacement (mm, planning to frame) on the planning grid."""
        if not (np.isfinite(weight) and weight >= 0):
            raise InputError(f"a frame's dose weight must be finite and >= 0, got {weight}")
        for o, ix in self.index.items():
            u = field_mm[ix[:, 0], ix[:, 1], ix[:, 2]]
            self.total[o] += weight * _sample(self.dose, self.points[o] + u)
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
            for m in METRICS:
                rows.append({"organ": o, "metric": m, "planned": p[m], "accumulated": a[m], "difference": a[m] - p[m]})
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
            w = csv.DictWriter(f, fieldnames=["organ", "metric", "planned", "accumulated", "difference"])
            w.writeheader()
            for r in self.metrics():
                w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})
        os.replace(os.path.join(folder, "dose_metrics.csv.part"), os.path.join(folder, "dose_metrics.csv"))
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
