"""What a track writes frame after frame: outputs registered by name, as the estimators are (:data:`OUTPUTS`).

Every track writes ``track.csv`` (one row a frame), ``particles.npz`` (the planning particles and every frame's
estimate) and its record ``track.json``. The rest is chosen by the user, each an :class:`TrackOutput`:

=================  ==========================================================================================
``labels``         ``labels/frame_NNNN.nii.gz``: the estimated label map on the planning grid (input label values)
``displacement``   ``displacement/frame_NNNN.nii.gz``: the 3D displacement field, mm, world LPS, planning grid
``dicom``          ``dicom/``: per frame an RTSTRUCT and a deformable REG on the planning series (``--dicom``)
``dose``           ``dose/``: the planned dose deformed by each frame's field, accumulated per organ (DVHs, ``--dose``)
``rrd``            a Rerun recording of the frames (``--rrd``; :class:`viewer.recording.RerunOutput`, registered when
                   the viewer is imported: the package never imports the viewer)
=================  ==========================================================================================

Adding one is a subclass with a ``name`` and :func:`register_output`; the session (:func:`warpmpm.session.track`)
takes instances or names. An output that needs the frame's 3D displacement field sets ``needs_field``; the field is
computed once a frame for all of them.
"""

from __future__ import annotations

import os
from typing import ClassVar

import numpy as np
import SimpleITK as sitk

from .errors import InputError

__all__ = ["OUTPUTS", "TrackOutput", "LabelMaps", "DisplacementFields", "DicomObjects", "AccumulatedDose",
           "make_outputs", "register_output", "write_image"]


class TrackOutput:
    """One kind of file a track writes, frame after frame.

    Class attributes: ``name`` (the registry's key), ``writes`` (one line: which files, in which units),
    ``needs_field`` (True: :meth:`frame` gets the frame's 3D displacement field, (Z, Y, X, 3) mm, world LPS, on the
    planning grid; False: None).
    """

    name: ClassVar[str] = ""
    writes: ClassVar[str] = ""
    needs_field: ClassVar[bool] = False

    def begin(self, tracker, out_dir: str) -> None:
        """Before the first frame (``out_dir``: the track's working folder, moved into place when all is written)."""

    def frame(self, tracker, out_dir: str, n: int, frame, positions_mm: np.ndarray, labels: np.ndarray,
              field_mm: np.ndarray | None) -> None:
        """After frame ``n``: its estimate (every particle, mm), its label map on the planning grid, its field."""

    def end(self, tracker, out_dir: str, rows: list[dict]) -> None:
        """After the last frame, with every frame's ``track.csv`` row."""

    def close(self, ok: bool) -> None:
        """Always, last (``ok``: whether the track finished); release what :meth:`begin` opened."""


#: name -> output class (the ``outputs`` a session may name)
OUTPUTS: dict[str, type[TrackOutput]] = {}


def register_output(cls: type[TrackOutput]) -> type[TrackOutput]:
    """Class decorator: add an output to :data:`OUTPUTS` under its ``name``."""
    if not cls.name or cls.name in OUTPUTS:
        raise ValueError(f"output name {cls.name!r} is empty or taken")
    OUTPUTS[cls.name] = cls
    return cls


def write_image(img: sitk.Image, path: str) -> None:
    """Write ``img`` to ``path`` (.nii.gz) through a temporary name: a reader never sees half a file."""
    tmp = path[: -len(".nii.gz")] + ".part.nii.gz"
    sitk.WriteImage(img, tmp)
    os.replace(tmp, path)


@register_output
class LabelMaps(TrackOutput):
    name = "labels"
    writes = "labels/frame_NNNN.nii.gz: each frame's estimated label map on the planning grid, the input's label values"

    def begin(self, tracker, out_dir):
        os.makedirs(os.path.join(out_dir, "labels"), exist_ok=True)

    def frame(self, tracker, out_dir, n, frame, positions_mm, labels, field_mm):
        img = tracker.case.geometry.apply_to(sitk.GetImageFromArray(labels.astype(np.uint8)))
        write_image(img, os.path.join(out_dir, "labels", f"frame_{n:04d}.nii.gz"))


@register_output
class DisplacementFields(TrackOutput):
    name = "displacement"
    writes = "displacement/frame_NNNN.nii.gz: each frame's 3D displacement field (vector image, mm, world LPS, planning grid)"
    needs_field = True

    def begin(self, tracker, out_dir):
        os.makedirs(os.path.join(out_dir, "displacement"), exist_ok=True)

    def frame(self, tracker, out_dir, n, frame, positions_mm, labels, field_mm):
        img = tracker.case.geometry.apply_to(sitk.GetImageFromArray(field_mm, isVector=True))
        write_image(img, os.path.join(out_dir, "displacement", f"frame_{n:04d}.nii.gz"))


@register_output
class AccumulatedDose(TrackOutput):
    """The planned dose deformed by each frame's field and accumulated per organ, each frame weighted by its beam-on
    time (:class:`warpmpm.dose.DoseAccumulator`).

    Args:
        accumulator: the planned dose on the planning grid with the organ masks (:class:`~warpmpm.dose.DoseAccumulator`).
        weights: per frame, its beam-on time (s); None: 1 each.
    """

    name = "dose"
    writes = "dose/: per organ the planned and accumulated DVHs and dose metrics (Gy), the dose-grid coverage per frame"
    needs_field = True

    def __init__(self, accumulator, weights=None):
        self.accumulator, self.weights = accumulator, weights

    def frame(self, tracker, out_dir, n, frame, positions_mm, labels, field_mm):
        self.accumulator.add(field_mm, 1.0 if self.weights is None else float(self.weights[n]))

    def end(self, tracker, out_dir, rows):
        self.accumulator.write(os.path.join(out_dir, "dose"), len(rows))


@register_output
class DicomObjects(TrackOutput):
    """Per frame a DICOM RTSTRUCT and a deformable spatial registration on the planning series; with
    :class:`AccumulatedDose` beside it, the accumulated dose as RT Dose (``dicom/RD_accumulated.dcm``, Gy).

    Args:
        writer: :class:`warpmpm.dicom_rt.FrameDicomWriter` (the planning series' reference, the ROI names).
        dose: the :class:`AccumulatedDose` output of the same track, or None.
    """

    name = "dicom"
    writes = "dicom/: per frame RS (RTSTRUCT) and REG (deformable registration); RD_accumulated.dcm with a dose"
    needs_field = True

    def __init__(self, writer, dose: AccumulatedDose | None = None):
        self.writer, self.dose = writer, dose

    def frame(self, tracker, out_dir, n, frame, positions_mm, labels, field_mm):
        self.writer.write(out_dir, n, labels, tracker.label_values, field_mm, frame.time_s)

    def end(self, tracker, out_dir, rows):
        if self.dose is None:
            return
        from .dicom_rt import write_rtdose

        acc = self.dose.accumulator
        plan = acc.dose.GetMetaData("plan_uid") if acc.dose.HasMetaDataKey("plan_uid") else None
        write_rtdose(os.path.join(out_dir, "dicom", "RD_accumulated.dcm"), self.writer.ref,
                     sitk.GetArrayFromImage(acc.accumulated_image()), plan_uid=plan, description="warpmpm accumulated dose (organs only)")


#: the argument of :func:`warpmpm.session.track` that makes each output needing inputs
_ARGUMENT = {"dose": "dose=PATH", "dicom": "dicom=True", "rrd": "viewer.recording.RerunOutput(PATH) in outputs"}


def make_outputs(items) -> list[TrackOutput]:
    """Instances for ``items`` (names of :data:`OUTPUTS` taking no arguments, or instances); :class:`InputError` naming
    the registered ones for an unknown name."""
    out = []
    for it in items:
        if isinstance(it, TrackOutput):
            out.append(it)
            continue
        cls = OUTPUTS.get(it)
        if cls is None:
            raise InputError(f"output {it!r} is not one of {', '.join(OUTPUTS)}")
        try:
            out.append(cls())
        except TypeError:
            raise InputError(f"output {it!r} needs its inputs: give warpmpm.track {_ARGUMENT.get(it, 'an instance of it')} "
                             "instead of naming it") from None
    names = [o.name for o in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"output {dup[0]!r} is asked for twice")
    return out
