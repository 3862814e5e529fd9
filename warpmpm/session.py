"""A track session from Python: :func:`track` is what ``warpmpm track`` does, the command only parses its arguments.

    import warpmpm

    result = warpmpm.track("planning/image.nii.gz", "cine/", "track/", labels="planning/labels.nii.gz",
                           outputs=("labels", "displacement"))
    result.latency_s["median"], result.record["estimator"]

The session reads and checks every input before any work (the planning scan with its labels or structure set, the
cine, a dose, a beam-on file; patient and frame of reference against the planning series), tracks the series with a
registered estimator (:mod:`warpmpm.estimators`, :class:`~warpmpm.tracker.TrackerConfig`), writes the outputs asked
for (:mod:`warpmpm.outputs`) into a folder that never replaces what this tool did not write
(:class:`~warpmpm.output_folder.OutputFolder`), and records the run in ``track.json``: package version (and commit),
the full configuration, the estimator, every input with its sha256, the machine, timings and every warning.
"""

from __future__ import annotations

import csv
import os
import warnings
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from .errors import InputError, InputWarning

__all__ = ["TrackResult", "track", "planning_case", "read_beam_on", "structure_mapping", "check_organ_letters"]

ORGAN_NAMES = ("pancreas", "stomach", "duodenum", "left_kidney")


@dataclass
class TrackResult:
    """What :func:`track` wrote and measured.

    Attributes:
        out: the track folder. rows: every frame's ``track.csv`` row. latency_s: ``median`` and ``p95`` of a frame's
        latency after the first (s; registration and rendering included). record: the content of ``track.json``.
        n_particles: the planning model's particles. n_driven: those that may lie on a plane during the series.
    """

    out: str
    rows: list[dict]
    latency_s: dict
    record: dict = field(default_factory=dict)
    n_particles: int = 0
    n_driven: int = 0


def check_organ_letters(organs: str) -> None:
    """:class:`InputError` unless ``organs`` is a non-empty string of the letters p, s, d, l."""
    bad = sorted(set(organs) - set("psdl"))
    if bad or not organs:
        raise InputError(f"--organs {organs!r}: letters from p (pancreas), s (stomach), d (duodenum), l (left kidney); "
                         f"{', '.join(repr(b) for b in bad) or 'none given'} is not one")


def structure_mapping(items) -> dict[str, str]:
    """``ORGAN=NAME`` items (``--structure``) as a dict; :class:`InputError` naming a malformed one."""
    out = {}
    for item in items or ():
        organ, sep, name = item.partition("=")
        organ = organ.strip()
        if not sep or not name.strip():
            raise InputError(f"--structure {item!r}: write ORGAN=NAME, e.g. --structure pancreas=GTV_Panc")
        if organ not in ORGAN_NAMES:
            raise InputError(f"--structure {item!r}: the organ must be one of {', '.join(ORGAN_NAMES)}")
        out[organ] = name.strip()
    return out


def planning_case(image, labels=None, rtstruct=None, preset="amos", structures=None, organs="psdl"):
    """The planning case: the image with a label map (``labels``, label values by ``preset``) or a DICOM structure set
    (``rtstruct``, structure names by ``structures``: organ -> ROI name, or ``ORGAN=NAME`` items)."""
    from .images import load_case

    if rtstruct:
        from .dicom_rt import case_from_rtstruct

        if labels:
            raise InputError("give the organs once: --labels (a label map) or --rtstruct (a structure set), not both")
        mapping = structures if isinstance(structures, dict) else structure_mapping(structures)
        return case_from_rtstruct(image, rtstruct, mapping, organs)
    if structures:
        raise InputError("--structure names structures of an --rtstruct; with --labels use --preset")
    if labels is None or image is None:
        raise InputError("--image and --labels are both needed (the planning image and its organ labels)")
    return load_case(labels, image, preset)


def read_beam_on(path: str, n_frames: int) -> list[float]:
    """Each frame's beam-on time (s) from a CSV with columns ``frame,beam_on_s`` (a spreadsheet's byte-order mark
    accepted); :class:`InputError` naming the file, the line and the fix for anything else."""
    if not os.path.isfile(path):
        raise InputError(f"--beam-on file not found (or not a regular file): {path}")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            text = f.read()
    except UnicodeDecodeError:
        raise InputError(f"--beam-on {path} is not a text CSV (it is not UTF-8); save it as CSV with columns "
                         "frame,beam_on_s") from None
    if "\x00" in text:
        raise InputError(f"--beam-on {path} is not a text CSV (it holds NUL bytes); save it as CSV with columns frame,beam_on_s")
    weights = [None] * n_frames
    reader = csv.DictReader(text.splitlines())
    fields = [f.strip() for f in (reader.fieldnames or [])]
    if not {"frame", "beam_on_s"} <= set(fields):
        raise InputError(f"--beam-on {path}: columns frame,beam_on_s are required (it has {reader.fieldnames})")
    reader.fieldnames = fields
    for line, row in enumerate(reader, start=2):
        try:
            n, t = int(row["frame"]), float(row["beam_on_s"])
        except (TypeError, ValueError):
            raise InputError(f"--beam-on {path}, line {line}: frame must be an integer and beam_on_s a number") from None
        if not 0 <= n < n_frames:
            raise InputError(f"--beam-on {path}, line {line}: frame {n} is not one of the cine's {n_frames} frames (0-{n_frames - 1})")
        if not (np.isfinite(t) and 0 <= t <= 3600.0):
            raise InputError(f"--beam-on {path}, line {line}: beam_on_s {t} must be a number of seconds in 0..3600 (one "
                             "frame's beam-on time, in seconds: mend that line)")
        if weights[n] is not None:
            raise InputError(f"--beam-on {path}, line {line}: frame {n} is given twice")
        weights[n] = t
    missing = [n for n, w in enumerate(weights) if w is None]
    if missing:
        raise InputError(f"--beam-on {path} gives no beam_on_s for frames {missing[:10]}{' ...' if len(missing) > 10 else ''}")
    if sum(weights) <= 0:
        raise InputError(f"--beam-on {path}: every frame's beam_on_s is 0: no frame carried dose")
    return weights


def planning_reference(image, case):
    """The planning series' reference (UIDs, patient) when the planning image is a DICOM series; None otherwise. Read
    once and kept in ``case.meta["dicom"]`` (as a structure set's case already has it)."""
    from .dicom_rt import read_series_reference

    if "dicom" not in case.meta:
        case.meta["dicom"] = read_series_reference(image) if os.path.isdir(image) else None
    return case.meta["dicom"]


def check_same_patient(ref, what: str, path: str, frame_of_reference: str, patient: str, registered: bool) -> None:
    """Refuse ``what`` (the cine, the dose) of another patient than the planning series, and on another frame of
    reference unless the user says it is registered (then warn)."""
    if ref is None:
        return
    if patient and ref.patient_id and patient != ref.patient_id:
        raise InputError(f"{what} {path} is of patient {patient!r}, the planning series {ref.patient_id!r}: another "
                         "patient's files are never combined; check the export")
    own_frame = "FrameOfReferenceUID" not in ref.extra.get("generated_uids", ())  # a series without one: nothing to check
    if own_frame and frame_of_reference and ref.frame_of_reference_uid and frame_of_reference != ref.frame_of_reference_uid:
        text = (f"{what} {path} is on frame of reference {frame_of_reference}, the planning series on "
                f"{ref.frame_of_reference_uid}")
        if not registered:
            raise InputError(f"{text}: its coordinates are another scanner session's. Register it to the planning scan, "
                             "or add --assume-registered if they are already in the planning scan's coordinates")
        warnings.warn(f"{text}; taken as in the planning scan's coordinates (--assume-registered)", InputWarning, stacklevel=2)


def _dicom_writer(case, image, work, frames, modality):
    """The planning series the DICOM outputs refer to: the user's (a DICOM image), else the planning image written as one."""
    from .dicom_rt import FrameDicomWriter, write_series
    from .images import grid_differences

    ref = planning_reference(image, case)
    if ref is not None:
        diff = grid_differences(ref.geometry, case.geometry)
        if diff:
            raise InputError(f"--dicom: the DICOM series {image} is not on the planning grid ({'; '.join(diff)})")
    else:
        ref = write_series(case.intensity_image(), os.path.join(work, "dicom", "planning"), modality=modality)
    names = case.meta.get("roi_names") or {}
    cine_for = next((f.frame_of_reference for f in frames if getattr(f, "frame_of_reference", "")), None)
    return FrameDicomWriter(ref, names, cine_for)


def _read_frames(cine, trackrad_centre_mm):
    from .cine import is_trackrad, read_cine, read_trackrad

    if is_trackrad(cine):
        return read_trackrad(cine, trackrad_centre_mm)
    if trackrad_centre_mm is not None:
        raise InputError(f"--trackrad-centre places a TrackRAD case; {cine} is not one (its frames carry their own position)")
    return read_cine(cine)


def track(image, cine, out, *, labels=None, rtstruct=None, preset: str = "amos", structures=None, config=None,
          outputs=("labels",), dicom: bool = False, modality: str = "MR", dose=None, beam_on=None,
          max_dose_gy: float = 120.0, dose_coverage_warn_pct: float = 1.0, assume_registered: bool = False,
          trackrad_centre_mm=None, overwrite: bool = False, progress=None, arguments: dict | None = None) -> TrackResult:
    """Track a cine series against a labelled planning scan and write the results into the folder ``out``.

    Args:
        image: the planning image (a volume file or a DICOM series folder).
        cine: the cine folder (2D DICOM or Elekta Unity ``.bin`` frames, NIfTI frames, or a TrackRAD case).
        out: the track folder (refused when it holds anything but an earlier track of this tool's, and that only with
            ``overwrite``).
        labels: the organ label map on the planning grid (label values by ``preset``), or
        rtstruct: a DICOM structure set on the planning series (``structures``: organ -> ROI name where the names
            differ from the usual ones).
        config: :class:`~warpmpm.tracker.TrackerConfig` (the estimator, the registration, the organs ...; default: the
            measured best).
        outputs: names of :data:`warpmpm.outputs.OUTPUTS` taking no inputs (``labels``, ``displacement``) or
            :class:`~warpmpm.outputs.TrackOutput` instances (a Rerun recording: ``viewer.recording.RerunOutput(PATH)``);
            ``dicom`` and ``dose`` are made from the arguments of those names.
        dicom: per frame a DICOM RTSTRUCT and REG on the planning series (``modality``: of the series written when
            the planning image is not DICOM).
        dose: the planned dose (DICOM RT Dose or a volume in Gy) to accumulate per organ; ``beam_on``: a CSV of each
            frame's beam-on time (s); ``max_dose_gy``: a dose above is refused (cGy read as Gy);
            ``dose_coverage_warn_pct``: warn when more of an organ than this leaves the dose grid in a frame.
        assume_registered: accept a cine or dose on another frame of reference than the planning series (warned).
        trackrad_centre_mm: where a TrackRAD case's sagittal frames lie (world LPS, mm).
        progress: called with one line per frame (None: silent).
        arguments: what to record as the run's arguments in ``track.json`` (the CLI's; default: this call's).

    Returns:
        :class:`TrackResult`. Raises :class:`~warpmpm.errors.InputError` naming the input and the fix before any
        work for a bad input; nothing is left half-written.
    """
    from .experiment.run import check_device
    from .output_folder import OutputFolder
    from .outputs import AccumulatedDose, DicomObjects, make_outputs
    from .tracker import Tracker, TrackerConfig

    cfg = config or TrackerConfig()
    if not isinstance(cfg, TrackerConfig):
        raise InputError(f"config must be a warpmpm.tracker.TrackerConfig, got {type(cfg).__name__}")
    check_device(cfg.solver.device)
    check_organ_letters(cfg.organs)
    if cfg.max_steps < 1:
        raise InputError(f"--max-steps must be at least 1, got {cfg.max_steps}")
    if beam_on and not dose:
        raise InputError("--beam-on weights the frames' dose: give --dose too")
    chosen = make_outputs([o for o in outputs if o not in ("dicom", "dose")])
    if rtstruct and cfg.preset is not None:
        cfg = replace(cfg, preset=None)  # a structure set's case knows its own labels
    case = planning_case(image, labels, rtstruct, preset, structures, cfg.organs)
    frames = _read_frames(cine, trackrad_centre_mm)
    ref = planning_reference(image, case)
    first = next((f for f in frames if f.frame_of_reference or f.patient), None)
    if first is not None:
        check_same_patient(ref, "the cine", cine, first.frame_of_reference, first.patient, assume_registered)
    call = arguments if arguments is not None else {
        "image": image, "cine": cine, "out": out, "labels": labels, "rtstruct": rtstruct, "preset": preset,
        "outputs": [o if isinstance(o, str) else o.name for o in outputs], "dicom": dicom, "dose": dose, "beam_on": beam_on,
        "max_dose_gy": max_dose_gy, "dose_coverage_warn_pct": dose_coverage_warn_pct,
        "assume_registered": assume_registered, "overwrite": overwrite}
    # checked and locked before any work: never an input, never a folder this tool did not write, one writer at a time
    record = {"arguments": call, "estimator": cfg.estimator, "config": _config_record(cfg)}
    if cfg.materials is not None:  # the table itself, with its sources: the file may change after the track
        from .materials import material_table

        record["materials"] = material_table(cfg.materials).to_json()
    folder = OutputFolder(out, kind="track", overwrite=overwrite, record=record,
                          inputs=[("--image", image), ("--labels", labels), ("--rtstruct", rtstruct), ("--cine", cine),
                                  ("--dose", dose), ("--beam-on", beam_on)])
    try:
        dose_out = None
        if dose:
            from .dose import DoseAccumulator, read_dose

            wanted = [o for o, c in zip(ORGAN_NAMES, "psdl") if c in cfg.organs]
            masks = {o: case.labels == v for o, v in case.label_map.items() if o in wanted}
            planned = read_dose(dose, max_dose_gy)
            meta = {k: planned.GetMetaData(k) if planned.HasMetaDataKey(k) else "" for k in ("frame_of_reference", "patient")}
            check_same_patient(ref, "the dose", dose, meta["frame_of_reference"], meta["patient"], assume_registered)
            dose_out = AccumulatedDose(DoseAccumulator(planned, case.geometry, masks, warn_outside_pct=dose_coverage_warn_pct),
                                       read_beam_on(beam_on, len(frames)) if beam_on else None)
        tracker = Tracker(case, frames, cfg)
        say = progress or (lambda text: None)
        say(f"{len(frames)} frames on {len({f.plane for f in frames})} plane(s); model {tracker.model.n:,} particles "
            f"({tracker.model.letters}), {len(tracker.driven):,} on the frames' planes; estimator {cfg.estimator}")
        if tracker.estimator.summary():
            say(tracker.estimator.summary())
        extra = []
        # written into a folder beside `out` and moved into place at the end: an interrupted or failed track leaves
        # no half-written `out`, and `overwrite` replaces the old track whole (two tracks are never mixed)
        with folder as work:
            if dicom:
                extra.append(DicomObjects(_dicom_writer(case, image, work, frames, modality), dose_out))
            if dose_out is not None:
                extra.insert(0, dose_out)
            rows = tracker.run(work, progress=progress, outputs=chosen + extra)
            lat = np.array([r["latency_s"] for r in rows[1:]] or [rows[0]["latency_s"]])
            latency = {"median": float(np.median(lat)), "p95": float(np.percentile(lat, 95))}
            folder.record.update(outputs=[o.name for o in chosen + extra], frames=len(rows), setup_s=tracker.estimator.setup_s,
                                 latency_s=latency, n_particles=tracker.model.n, n_driven=int(len(tracker.driven)))
        return TrackResult(out=out, rows=rows, latency_s=latency, record=folder.last_record, n_particles=tracker.model.n,
                           n_driven=int(len(tracker.driven)))
    finally:
        folder.release()


def _config_record(cfg) -> dict:
    """The tracker's configuration as plain JSON values (nested configs included)."""
    def plain(v):
        if isinstance(v, dict):
            return {str(k): plain(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if isinstance(v, (str, int, float, bool, type(None))):
            return v
        return str(v)

    return plain(asdict(cfg))
