"""Stream a run to a Rerun ``.rrd`` file.

Entities (all positions in mm, world coordinates):

- ``planning/<organ>``: the planning particles, coloured by organ (static).
- ``estimate/<organ>``: the estimate every ``every``-th step and at convergence (timelines ``step``, ``frame``).
- ``gt/<organ>``: the ground-truth positions (static).
- ``error/pancreas``: the final estimate's pancreas coloured by per-particle error (colour scale in ``error/scale``).
- ``slices/<orientation>_<index>/plane``: the driving slice as a thin box in 3D; ``.../image``: its 2D image;
  ``.../targets``: arrows from each driven particle to its target.
- ``metrics/rel_residual``, ``metrics/rms_residual_mm``, ``metrics/pancreas_error_mm``: scalars per step.
- ``run/params``: the run's parameters and final table (Markdown).
"""

from __future__ import annotations

import json

import numpy as np
import rerun as rr

ORGAN_COLOURS = {"pancreas": (235, 170, 40), "stomach": (90, 160, 230), "duodenum": (120, 200, 110), "left_kidney": (200, 80, 90)}

# 5-stop perceptual scale (dark blue -> teal -> green -> yellow), like viridis.
_STOPS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=np.float64)


def error_colours(err_mm: np.ndarray, vmax_mm: float) -> np.ndarray:
    """RGB colours of errors on a 0..vmax_mm viridis-like scale."""
    t = np.clip(np.asarray(err_mm) / max(vmax_mm, 1e-9), 0, 1) * (len(_STOPS) - 1)
    i = np.minimum(t.astype(int), len(_STOPS) - 2)
    f = (t - i)[:, None]
    return ((1 - f) * _STOPS[i] + f * _STOPS[i + 1]).astype(np.uint8)


class RunLogger:
    """Writes one run to ``path``. ``every``: log positions every this many steps (scalars every step)."""

    def __init__(self, path: str, model, gt_pos: np.ndarray | None = None, every: int = 20, application: str = "warpmpm"):
        self.rec = rr.RecordingStream(application)
        self.rec.save(path)
        self.model = model
        self.gt_pos = gt_pos
        self.every = max(1, int(every))
        self.frame = 0
        self.pancreas = model.organ_slice("pancreas")

    def _points(self, prefix: str, positions: np.ndarray, static: bool = False) -> None:
        for n, organ in enumerate(self.model.organs):
            sel = self.model.organ_index == n
            self.rec.log(f"{prefix}/{organ}", rr.Points3D(positions[sel], colors=ORGAN_COLOURS.get(organ, (200, 200, 200)), radii=0.6),
                         static=static)

    def log_planning(self) -> None:
        self._points("planning", self.model.positions_mm, static=True)
        if self.gt_pos is not None:
            self._points("gt", self.gt_pos, static=True)

    def log_slices(self, slices, driven: np.ndarray, targets: np.ndarray, prep=None) -> None:
        from warpmpm.driving import driven_indices, in_plane_axes

        for s in slices:
            name = f"slices/{s.orientation}_{s.index}"
            on = driven_indices(self.model, [s])
            pts = self.model.positions_mm[on]
            e_u, e_v = in_plane_axes(self.model, s.orientation)
            normal = np.cross(e_u, e_v)
            centre = pts.mean(0)
            half = np.abs(e_u) * np.ptp(pts @ e_u) / 2 + np.abs(e_v) * np.ptp(pts @ e_v) / 2 + np.abs(normal) * 0.5 + 5.0 * (np.abs(e_u) + np.abs(e_v))
            self.rec.log(f"{name}/plane", rr.Boxes3D(centers=[centre], half_sizes=[half], colors=[(255, 255, 255)]), static=True)
            sel = np.isin(driven, on)
            self.rec.log(f"{name}/targets", rr.Arrows3D(origins=self.model.positions_mm[driven[sel]],
                                                         vectors=targets[sel] - self.model.positions_mm[driven[sel]],
                                                         colors=(255, 60, 60)), static=True)
            if prep is not None and prep.case.image is not None:
                from warpmpm.registration import extract_slice
                import SimpleITK as sitk

                img = extract_slice(prep.case.image, prep.case.geometry, s.orientation, s.index, prep.input_centre_mm)
                arr = sitk.GetArrayFromImage(img)
                lo, hi = np.percentile(arr, [1, 99])
                self.rec.log(f"{name}/image", rr.Image(np.clip((arr - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)),
                             static=True)

    def step_callback(self, estimator, step: int, rel: float, rms_mm: float) -> None:
        self.rec.set_time("frame", sequence=self.frame)
        self.rec.set_time("step", sequence=step)
        self.rec.log("metrics/rel_residual", rr.Scalars(rel))
        self.rec.log("metrics/rms_residual_mm", rr.Scalars(rms_mm))
        if step % self.every == 0:
            pos = estimator.positions_mm()
            self._points("estimate", pos)
            if self.gt_pos is not None:
                err = np.linalg.norm(pos[self.pancreas] - self.gt_pos[self.pancreas], axis=1).mean()
                self.rec.log("metrics/pancreas_error_mm", rr.Scalars(err))

    def log_result(self, result, out: dict) -> None:
        self.rec.set_time("frame", sequence=self.frame)
        self.rec.set_time("step", sequence=result.steps)
        self._points("estimate", result.positions_mm)
        if self.gt_pos is not None:
            err = np.linalg.norm(result.positions_mm[self.pancreas] - self.gt_pos[self.pancreas], axis=1)
            vmax = float(np.percentile(err, 95))
            self.rec.log("error/pancreas", rr.Points3D(result.positions_mm[self.pancreas], colors=error_colours(err, vmax), radii=0.8))
            self.rec.log("error/scale", rr.TextDocument(f"error colour scale: 0 mm (dark blue) to {vmax:.2f} mm (yellow, the 95th percentile)"),
                         static=True)
            self.rec.log("metrics/pancreas_error_mm", rr.Scalars(float(err.mean())))
        from warpmpm.runner import format_table

        clean = {k: v for k, v in out.items() if not k.startswith("_")}
        text = "# warpmpm run\n\n" + format_table(clean) + "\n\n```json\n" + json.dumps(clean, indent=1, default=str) + "\n```\n"
        self.rec.log("run/params", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
        self.frame += 1

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
