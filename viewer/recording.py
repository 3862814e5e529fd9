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

The recording carries a default layout (a Rerun blueprint, :func:`default_blueprint`): the organs in
3D with the driving slices and targets, the pancreas error field beside the GT, the slice image, the
residual and error curves and the run's table; the time panel follows the newest step.
"""

from __future__ import annotations

import json

import numpy as np
import rerun as rr

from warpmpm.outputs import TrackOutput, register_output

ORGAN_COLOURS = {"pancreas": (235, 170, 40), "stomach": (90, 160, 230), "duodenum": (120, 200, 110), "left_kidney": (170, 100, 220)}

# 5-stop perceptual scale (dark blue -> teal -> green -> yellow), like viridis.
_STOPS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=np.float64)


def error_colours(err_mm: np.ndarray, vmax_mm: float) -> np.ndarray:
    """RGB colours of errors on a 0..vmax_mm viridis-like scale."""
    t = np.clip(np.asarray(err_mm) / max(vmax_mm, 1e-9), 0, 1) * (len(_STOPS) - 1)
    i = np.minimum(t.astype(int), len(_STOPS) - 2)
    f = (t - i)[:, None]
    return ((1 - f) * _STOPS[i] + f * _STOPS[i + 1]).astype(np.uint8)


GT_COLOUR = (235, 235, 235, 90)


def default_blueprint(slice_names: list[str] | None = None, centre_mm=None, extent_mm: float | None = None):
    """The layout a recording opens with (users can still rearrange it in the viewer).

    ``centre_mm``, ``extent_mm``: the scene's centre and size, to place the 3D cameras looking at it
    from the patient's right, slightly posterior and superior with superior (+z, LPS) up.
    """
    import rerun.blueprint as rrb

    slice_names = slice_names or []
    eye = None
    if centre_mm is not None and extent_mm:
        d = np.array([-1.0, 0.35, 0.6])
        c = np.asarray(centre_mm, dtype=float)
        eye = rrb.EyeControls3D(position=c + 1.6 * extent_mm * d / np.linalg.norm(d), look_target=c, eye_up=(0.0, 0.0, 1.0))
    side = [rrb.Spatial3DView(name="pancreas error (mm) vs GT (grey)", origin="/", contents=["+ /error/**", "+ /gt/pancreas"])]
    side += [rrb.Spatial2DView(name=f"driving slice {n}", origin=f"/slices/{n}/image") for n in slice_names[:2]]
    side += [rrb.TimeSeriesView(name="residual and error", origin="/metrics")]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="estimate, driving slices and targets", origin="/",
                              contents=["+ /estimate/**"] + [f"+ /slices/{n}/{part}" for n in slice_names for part in ("plane", "targets")],
                              eye_controls=eye),
            rrb.Vertical(*side),
            rrb.Vertical(rrb.TextDocumentView(name="run", origin="/run/params"), rrb.TextDocumentView(name="colour scale", origin="/error/scale"),
                         row_shares=[4, 1]),
            column_shares=[5, 4, 3],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="step", play_state="following", state="collapsed"),
    )


def rerun_executable() -> str:
    """The ``rerun`` command of this environment (on PATH, else beside the running Python)."""
    import os
    import shutil
    import sys

    return shutil.which("rerun") or os.path.join(os.path.dirname(sys.executable), "rerun")


def optimize_recording(path: str) -> bool:
    """Compact ``path`` in place with ``rerun rrd optimize``; False (file untouched) when it fails."""
    import os
    import subprocess
    import warnings

    exe = rerun_executable()
    tmp = path + ".optimizing"
    try:
        with open(tmp, "wb") as f:
            proc = subprocess.run([exe, "rrd", "optimize", path], stdout=f, stderr=subprocess.PIPE, timeout=600)
        if proc.returncode == 0 and os.path.getsize(tmp) > 0:
            os.replace(tmp, path)
            return True
        warnings.warn(f"rerun rrd optimize failed ({proc.stderr.decode(errors='replace').strip()[-200:]}); recording left as written")
    except (OSError, subprocess.SubprocessError) as e:
        warnings.warn(f"could not compact the recording with rerun rrd optimize: {e}")
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return False


class RerunRecorder:
    """A :class:`warpmpm.recorder.Recorder` writing one run to a Rerun ``.rrd`` file.

    The file is written under a temporary name beside ``path`` and renamed to ``path`` only when the
    run closes successfully (``close(ok=True)``): an interrupted or failed run leaves no partial
    recording that a viewer would read as complete. ``every``: log positions every this many steps
    (scalars every step).
    """

    def __init__(self, path: str, every: int = 20, application: str = "warpmpm"):
        import os

        self.path = os.path.abspath(path)
        self.tmp = self.path + ".part"
        self.rec = rr.RecordingStream(application)
        self.rec.save(self.tmp)
        self.every = max(1, int(every))
        self.frame = 0
        self.model = None
        self.gt_pos = None
        self.pancreas = None
        self._closed = False

    def begin(self, model, gt_positions_mm: np.ndarray | None = None) -> None:
        self.model = model
        self.gt_pos = gt_positions_mm
        self.pancreas = model.organ_slice("pancreas")
        self._points("planning", self.model.positions_mm, static=True)
        if self.gt_pos is not None:
            self._points("gt", self.gt_pos, static=True, colour=GT_COLOUR, radius=0.4)

    def _points(self, prefix: str, positions: np.ndarray, static: bool = False, colour=None, radius: float = 0.6) -> None:
        for n, organ in enumerate(self.model.organs):
            sel = self.model.organ_index == n
            c = colour or ORGAN_COLOURS.get(organ, (200, 200, 200))
            self.rec.log(f"{prefix}/{organ}", rr.Points3D(positions[sel], colors=c, radii=radius), static=static)

    def log_slices(self, slices, driven: np.ndarray, targets_mm: np.ndarray, case=None, centre_mm=None) -> None:
        from warpmpm.slices import driven_indices, extract_slice, in_plane_axes

        pos = self.model.positions_mm
        self.rec.send_blueprint(default_blueprint([f"{s.orientation}_{s.index}" for s in slices], pos.mean(0),
                                                  float(np.ptp(pos, axis=0).max())))
        for s in slices:
            name = f"slices/{s.orientation}_{s.index}"
            on = driven_indices(self.model, [s])
            pts = self.model.positions_mm[on]
            e_u, e_v = in_plane_axes(self.model, s.orientation)
            normal = np.cross(e_u, e_v)
            centre = pts.mean(0)
            half = np.abs(e_u) * np.ptp(pts @ e_u) / 2 + np.abs(e_v) * np.ptp(pts @ e_v) / 2 + np.abs(normal) * 0.5 + 5.0 * (np.abs(e_u) + np.abs(e_v))
            self.rec.log(f"{name}/plane", rr.Boxes3D(centers=[centre], half_sizes=[half], colors=[(255, 255, 255, 60)],
                                                      fill_mode="transparentfillmajorwireframe", radii=0.3), static=True)
            sel = np.isin(driven, on)
            self.rec.log(f"{name}/targets", rr.Arrows3D(origins=self.model.positions_mm[driven[sel]],
                                                         vectors=targets_mm[sel] - self.model.positions_mm[driven[sel]],
                                                         colors=(255, 255, 255), radii=0.15), static=True)
            if case is not None and case.image is not None and centre_mm is not None:
                import SimpleITK as sitk

                img = extract_slice(case.image, case.geometry, s.orientation, s.index, centre_mm)
                arr = sitk.GetArrayFromImage(img)
                lo, hi = np.percentile(arr, [1, 99])
                self.rec.log(f"{name}/image", rr.Image(np.clip((arr - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)),
                             static=True)

    def on_step(self, estimator, step: int, rel_residual: float, rms_mm: float) -> None:
        self.rec.set_time("frame", sequence=self.frame)
        self.rec.set_time("step", sequence=step)
        self.rec.log("metrics/rel_residual", rr.Scalars(rel_residual))
        self.rec.log("metrics/rms_residual_mm", rr.Scalars(rms_mm))
        if step % self.every == 0:
            pos = estimator.positions_mm()
            self._points("estimate", pos)
            if self.gt_pos is not None:
                err = np.linalg.norm(pos[self.pancreas] - self.gt_pos[self.pancreas], axis=1).mean()
                self.rec.log("metrics/pancreas_error_mm", rr.Scalars(err))

    def log_result(self, positions_mm: np.ndarray, steps: int, summary: dict, table: str) -> None:
        self.rec.set_time("frame", sequence=self.frame)
        self.rec.set_time("step", sequence=steps)
        self._points("estimate", positions_mm)
        if self.gt_pos is not None:
            err = np.linalg.norm(positions_mm[self.pancreas] - self.gt_pos[self.pancreas], axis=1)
            vmax = float(np.percentile(err, 95))
            self.rec.log("error/pancreas", rr.Points3D(positions_mm[self.pancreas], colors=error_colours(err, vmax), radii=0.8))
            self.rec.log("error/scale", rr.TextDocument(f"error colour scale: 0 mm (dark blue) to {vmax:.2f} mm (yellow, the 95th percentile)"),
                         static=True)
            self.rec.log("metrics/pancreas_error_mm", rr.Scalars(float(err.mean())))
        text = "# warpmpm run\n\n" + table + "\n\n```json\n" + json.dumps(summary, indent=1, default=str) + "\n```\n"
        self.rec.log("run/params", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
        self.frame += 1

    def close(self, ok: bool = True) -> None:
        """Finish the file; on success compact its chunks (``rerun rrd optimize``: the SDK writes a few
        steps per chunk, and a viewer opening the raw file shows the newest step before all of them have
        loaded, seen in Rerun 0.41) and rename it to ``path``; on failure delete it."""
        if self._closed:
            return
        self._closed = True
        finish_recording(self.rec, self.tmp, self.path, ok)


def finish_recording(rec, tmp: str, path: str, ok: bool) -> None:
    """Close a recording written to ``tmp``: on success compact it and rename it to ``path``; on failure delete it."""
    import os

    rec.flush()
    rec.disconnect()
    if not ok:
        if os.path.exists(tmp):
            os.remove(tmp)
        return
    optimize_recording(tmp)
    os.replace(tmp, path)


class TrackRecorder:
    """A Rerun recording of a tracked cine series: per frame (timeline ``frame``) the estimated organs in 3D,
    the cine frame as an image and its plane as a box in 3D. Written under a temporary name and renamed on
    ``close(ok=True)``; ``close(ok=False)`` leaves nothing."""

    def __init__(self, path: str, model, application: str = "warpmpm-track"):
        import os

        self.path = os.path.abspath(path)
        self.tmp = self.path + ".part"
        self.model = model
        self.rec = rr.RecordingStream(application)
        self.rec.save(self.tmp)
        for n, organ in enumerate(model.organs):
            sel = model.organ_index == n
            self.rec.log(f"planning/{organ}", rr.Points3D(model.positions_mm[sel], colors=ORGAN_COLOURS.get(organ), radii=0.6),
                         static=True)

    def on_frame(self, n: int, frame, positions_mm: np.ndarray) -> None:
        self.rec.set_time("frame", sequence=n)
        for k, organ in enumerate(self.model.organs):
            sel = self.model.organ_index == k
            self.rec.log(f"estimate/{organ}", rr.Points3D(positions_mm[sel], colors=ORGAN_COLOURS.get(organ), radii=0.6))
        arr = np.asarray(__import__("SimpleITK").GetArrayFromImage(frame.slice_2d()))
        lo, hi = np.percentile(arr, [1, 99])
        self.rec.log(f"cine/plane_{frame.plane}/image", rr.Image(np.clip((arr - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)))
        size = np.asarray(frame.image.GetSize()) * np.asarray(frame.image.GetSpacing())
        axes = [a for a in range(3) if a != frame.thin_axis]
        half = np.abs(frame.e_u) * size[axes[0]] / 2 + np.abs(frame.e_v) * size[axes[1]] / 2 + np.abs(frame.normal) * frame.thickness_mm / 2
        self.rec.log(f"cine/plane_{frame.plane}/box", rr.Boxes3D(centers=[frame.centre_mm], half_sizes=[half],
                                                                  colors=[(255, 255, 255, 60)], radii=0.3))

    def close(self, ok: bool = True) -> None:
        finish_recording(self.rec, self.tmp, self.path, ok)


@register_output
class RerunOutput(TrackOutput):
    """A track's output (:mod:`warpmpm.outputs`): a Rerun recording of the planning model and every frame's estimate
    (:class:`TrackRecorder`), written to ``path`` (outside the track folder; a failed track leaves none)."""

    name = "rrd"
    writes = "a Rerun recording (.rrd) of the planning model and every frame's estimate, mm, world LPS"

    def __init__(self, path: str):
        from warpmpm.experiment.io import check_output_path

        self.path = check_output_path(path, "--rrd")
        self.recorder = None

    def begin(self, tracker, out_dir):
        self.recorder = TrackRecorder(self.path, tracker.model)

    def frame(self, tracker, out_dir, n, frame, positions_mm, labels, field_mm):
        self.recorder.on_frame(n, frame, positions_mm)

    def close(self, ok):
        if self.recorder is not None:
            self.recorder.close(ok=ok)
            self.recorder = None
