"""The product's commands: ``track`` (your scan and cine series in, per-frame 3D organ motion out), ``make-cine``,
``make-truth``, ``evaluate-track`` and ``cine-info``."""

from __future__ import annotations

import os
import sys

from ..errors import InputError

__all__ = ["cmd_estimators", "cmd_track", "cmd_make_cine", "cmd_make_truth", "cmd_evaluate_track", "cmd_cine_info"]


def _planning_case(image, labels, preset):
    from ..images import load_case

    if labels is None or image is None:
        raise InputError("--image and --labels are both needed (the planning image and its organ labels)")
    return load_case(labels, image, preset)


def _point(text: str, option: str):
    try:
        p = [float(v) for v in text.split(",")]
    except ValueError:
        p = []
    if len(p) != 3 or not all(abs(v) < 1e4 for v in p):
        raise InputError(f"{option} {text!r}: three finite numbers in mm, e.g. {option}=-10,20,35")
    return p


def _structure_mapping(items) -> dict[str, str]:
    organs = ("pancreas", "stomach", "duodenum", "left_kidney")
    out = {}
    for item in items:
        organ, sep, name = item.partition("=")
        organ = organ.strip()
        if not sep or not name.strip():
            raise InputError(f"--structure {item!r}: write ORGAN=NAME, e.g. --structure pancreas=GTV_Panc")
        if organ not in organs:
            raise InputError(f"--structure {item!r}: the organ must be one of {', '.join(organs)}")
        out[organ] = name.strip()
    return out


def _beam_on(path: str, n_frames: int) -> list[float]:
    import csv

    import numpy as np

    if not os.path.isfile(path):
        raise InputError(f"--beam-on file not found (or not a regular file): {path}")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:  # a spreadsheet's byte-order mark is accepted
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


def _planning_reference(a, case):
    """The planning series' reference (UIDs, patient) when the planning image is a DICOM series; None otherwise. Read
    once and kept in ``case.meta["dicom"]`` (as a structure set's case already has it): the cine check, the dose check
    and the DICOM writer all ask."""
    from ..dicom_rt import read_series_reference

    if "dicom" not in case.meta:
        case.meta["dicom"] = read_series_reference(a.image) if os.path.isdir(a.image) else None
    return case.meta["dicom"]


def _check_same_patient(ref, what: str, path: str, frame_of_reference: str, patient: str, registered: bool) -> None:
    """Refuse ``what`` (the cine, the dose) of another patient than the planning series, and on another frame of
    reference unless the user says it is registered (then warn)."""
    import warnings

    from ..errors import InputWarning

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


def _dicom_writer(case, a, work, frames=()):
    """The planning series the DICOM outputs refer to: the user's (a DICOM --image), else the planning image written as one."""
    from ..dicom_rt import FrameDicomWriter, write_series
    from ..images import grid_differences

    ref = _planning_reference(a, case)
    if ref is not None:
        diff = grid_differences(ref.geometry, case.geometry)
        if diff:
            raise InputError(f"--dicom: the DICOM series {a.image} is not on the planning grid ({'; '.join(diff)})")
    else:
        ref = write_series(case.intensity_image(), os.path.join(work, "dicom", "planning"), modality=a.modality)
    names = case.meta.get("roi_names") or {}
    cine_for = next((f.frame_of_reference for f in frames if getattr(f, "frame_of_reference", "")), None)
    return FrameDicomWriter(ref, names, cine_for)


def _arguments(a) -> dict:
    """The command's arguments, as recorded in the output folder's record file."""
    return {k: v for k, v in vars(a).items() if isinstance(v, (str, int, float, bool, type(None), list))}


def cmd_track(a) -> int:
    from ..cine import read_cine
    from ..experiment.run import check_device

    check_device(a.device)

    bad = sorted(set(a.organs) - set("psdl"))
    if bad or not a.organs:
        raise InputError(f"--organs {a.organs!r}: letters from p (pancreas), s (stomach), d (duodenum), l (left kidney); "
                         f"{', '.join(repr(b) for b in bad) or 'none given'} is not one")
    if a.max_steps < 1:
        raise InputError(f"--max-steps must be at least 1, got {a.max_steps}")
    if a.rtstruct:
        from ..dicom_rt import case_from_rtstruct

        if a.labels:
            raise InputError("give the organs once: --labels (a label map) or --rtstruct (a structure set), not both")
        case = case_from_rtstruct(a.image, a.rtstruct, _structure_mapping(a.structure), a.organs)
    else:
        if a.structure:
            raise InputError("--structure names structures of an --rtstruct; with --labels use --preset")
        case = _planning_case(a.image, a.labels, a.preset)
    from ..cine import is_trackrad, read_trackrad

    if is_trackrad(a.cine):
        frames = read_trackrad(a.cine, _point(a.trackrad_centre, "--trackrad-centre") if a.trackrad_centre else None)
    else:
        if a.trackrad_centre:
            raise InputError(f"--trackrad-centre places a TrackRAD case; {a.cine} is not one (its frames carry their own position)")
        frames = read_cine(a.cine)
    ref = _planning_reference(a, case)
    first = next((f for f in frames if f.frame_of_reference or f.patient), None)
    if first is not None:
        _check_same_patient(ref, "the cine", a.cine, first.frame_of_reference, first.patient, a.assume_registered)
    from ..output_folder import OutputFolder

    # checked and locked before any work: never an input, never a folder this tool did not write, one writer at a time
    folder = OutputFolder(a.out, kind="track", overwrite=a.overwrite, record={"arguments": _arguments(a)},
                          inputs=[("--image", a.image), ("--labels", a.labels), ("--rtstruct", a.rtstruct), ("--cine", a.cine),
                                  ("--dose", a.dose), ("--beam-on", a.beam_on)])
    try:
        return _track_into(a, case, frames, folder)
    finally:
        folder.release()


def _track_into(a, case, frames, folder) -> int:
    from ..solvers import SolverConfig
    from ..tracker import Tracker, TrackerConfig

    cfg = TrackerConfig(estimator=a.estimator, preset=None if a.rtstruct else a.preset,
                        organs=a.organs, particle_step=a.particle_step, max_steps=a.max_steps, displacement=a.displacement,
                        predict=not a.no_predict, wait_settled=a.wait_settled, registration=a.registration,
                        registration_linear_prior=a.linear_prior, reference=a.reference,
                        solver=SolverConfig(device=a.device, method=a.solver, cpu_threads=a.threads))
    dose, weights = None, None
    if a.beam_on and not a.dose:
        raise InputError("--beam-on weights the frames' dose: give --dose too")
    if a.dose:
        from ..dose import DoseAccumulator, read_dose

        organs_wanted = [o for o, c in zip(("pancreas", "stomach", "duodenum", "left_kidney"), "psdl") if c in a.organs]
        masks = {o: case.labels == v for o, v in case.label_map.items() if o in organs_wanted}
        planned = read_dose(a.dose, a.max_dose_gy)
        meta = {k: planned.GetMetaData(k) if planned.HasMetaDataKey(k) else "" for k in ("frame_of_reference", "patient")}
        _check_same_patient(_planning_reference(a, case), "the dose", a.dose, meta["frame_of_reference"], meta["patient"],
                            a.assume_registered)
        dose = DoseAccumulator(planned, case.geometry, masks, warn_outside_pct=a.dose_coverage_warn)
        weights = _beam_on(a.beam_on, len(frames)) if a.beam_on else None
    tracker = Tracker(case, frames, cfg)
    print(f"{len(frames)} frames on {len({f.plane for f in frames})} plane(s); model {tracker.model.n:,} particles "
          f"({tracker.model.letters}), {len(tracker.driven):,} on the frames' planes", file=sys.stderr)
    if tracker.estimator.summary():
        print(tracker.estimator.summary(), file=sys.stderr)
    recorder = None
    if a.rrd:
        from ..errors import optional
        from ..experiment.io import check_output_path

        optional("rerun", "a Rerun recording (--rrd)")
        from viewer.recording import TrackRecorder

        recorder = TrackRecorder(check_output_path(a.rrd, "--rrd"), tracker.model)
    # written into a folder beside --out and moved into place at the end: an interrupted or failed track leaves no
    # half-written --out, and --overwrite replaces the old track whole (two tracks are never mixed)
    with folder as work:
        dicom = _dicom_writer(case, a, work, frames) if a.dicom else None
        rows = tracker.run(work, progress=lambda t: print(t, flush=True), recorder=recorder, dicom=dicom, dose=dose,
                           dose_weights=weights)
        if dose is not None and dicom is not None:
            import SimpleITK as sitk

            from ..dicom_rt import write_rtdose

            plan = dose.dose.GetMetaData("plan_uid") if dose.dose.HasMetaDataKey("plan_uid") else None
            write_rtdose(os.path.join(work, "dicom", "RD_accumulated.dcm"), dicom.ref,
                         sitk.GetArrayFromImage(dose.accumulated_image()), plan_uid=plan,
                         description="warpmpm accumulated dose (organs only)")
    import numpy as np

    lat = np.array([r["latency_s"] for r in rows[1:]] or [rows[0]["latency_s"]])
    print(f"latency per frame after the first: median {np.median(lat):.2f} s, p95 {np.percentile(lat, 95):.2f} s; wrote {a.out}")
    return 0


def cmd_estimators(a) -> int:
    """``warpmpm estimators``: the registered estimators, one line each (the default marked)."""
    from ..estimators import ESTIMATORS
    from ..tracker import TrackerConfig

    default = TrackerConfig().estimator
    for name, cls in ESTIMATORS.items():
        mark = " (default)" if name == default else ""
        print(f"{name}{mark}: uses {cls.uses}; measured: {cls.measured}")
    return 0


def cmd_make_cine(a) -> int:
    from ..experiment.cine_series import check_cine_parameters, make_cine
    from ..phantom import make_phantom

    planes = tuple(p.strip() for p in a.plane.split(",") if p.strip())
    fields, fps = None, a.fps
    if a.truth is not None:
        import glob
        import json

        folder = os.path.join(a.truth, "fields") if os.path.isdir(os.path.join(a.truth, "fields")) else a.truth
        fields = sorted(glob.glob(os.path.join(folder, "frame_*.nii*")))
        if not fields:
            raise InputError(f"--truth {a.truth} holds no displacement field (frame_NNNN.nii.gz, or fields/frame_NNNN.nii.gz)")
        record = os.path.join(a.truth, "truth.json")
        if os.path.exists(record):
            with open(record) as fh:
                fps = float(json.load(fh)["config"]["fps"])
        if a.labels is None and a.image is None:
            raise InputError("--truth needs the planning case it was made on (--image and --labels): its fields are on that grid")
    check_cine_parameters(planes, len(fields) if fields else a.frames, fps, 4.0, a.thickness_mm, a.pixel_mm, a.format)  # before anything is written
    if a.seed < 0:
        raise InputError(f"--seed must be a whole number >= 0, got {a.seed}")
    if a.image is not None and a.labels is None:
        raise InputError("--image needs --labels (without both, the built-in phantom is used)")
    import math

    if not (math.isfinite(a.phantom_resolution) and 0.25 <= a.phantom_resolution <= 16):
        raise InputError(f"--phantom-resolution must be a finite number in 0.25..16 (mm), got {a.phantom_resolution}")
    if not 1 <= a.particle_step <= 16:
        raise InputError(f"--particle-step must be a whole number in 1..16, got {a.particle_step}")
    from ..output_folder import OutputFolder

    # never an input, never a folder that holds anything (two series are never mixed), one writer at a time; written
    # beside --out and moved into place at the end: a failed or interrupted series leaves nothing behind
    with OutputFolder(a.out, kind="cine", record={"arguments": _arguments(a)},
                      inputs=[("--image", a.image), ("--labels", a.labels), ("--truth", a.truth)]) as work:
        if a.labels is None:  # the phantom: its planning image and labels go beside the series, for `warpmpm track`
            from ..images import write_case

            os.makedirs(os.path.join(work, "planning"))
            paths = os.path.join(work, "planning", "labels.nii.gz"), os.path.join(work, "planning", "image.nii.gz")
            write_case(make_phantom(resolution=a.phantom_resolution), *paths)
            case = _planning_case(paths[1], paths[0], "amos")  # as the tracker will read it (float32 geometry)
        else:
            case = _planning_case(a.image, a.labels, a.preset)
        make_cine(case, work, planes=planes, frames=a.frames, fps=fps, thickness_mm=a.thickness_mm, pixel_mm=a.pixel_mm,
                  seed=a.seed, particle_step=a.particle_step, fmt=a.format, truth_fields=fields,
                  progress=lambda t: print(t, flush=True))
    print(f"wrote {a.out}/cine and {a.out}/truth")
    return 0


def cmd_make_truth(a) -> int:
    from ..output_folder import OutputFolder
    from ..truth_fem import TruthConfig

    cfg = TruthConfig(loads=tuple(x.strip() for x in a.load.split(",") if x.strip()), frames=a.frames, fps=a.fps, seed=a.seed,
                      cell_mm=a.cell_mm, margin_mm=a.margin_mm, interface_mm=a.interface_mm)
    # checked and locked before the solve: never an input, never a folder that holds anything (a truth is never mixed
    # with another), one writer at a time
    folder = OutputFolder(a.out, kind="truth", record={"arguments": _arguments(a)}, make_parent=True,
                          inputs=[("--image", a.image), ("--labels", a.labels)])
    try:
        return _make_truth_into(a, cfg, folder)
    finally:
        folder.release()


def _make_truth_into(a, cfg, folder) -> int:
    from ..phantom import make_phantom
    from ..truth_fem import make_truth
    from ..truth_fem.series import write_truth_files

    if a.labels is None:
        if a.image is not None:
            raise InputError("--image needs --labels (without both, the built-in phantom is used)")
        import math

        from ..experiment.config import MAX_SEED

        if not (0 <= a.phantom_seed <= MAX_SEED):
            raise InputError(f"--phantom-seed must be a whole number in 0..{MAX_SEED}, got {a.phantom_seed}")
        if not (math.isfinite(a.phantom_resolution) and 0.25 <= a.phantom_resolution <= 16):
            raise InputError(f"--phantom-resolution must be a finite number in 0.25..16 (mm), got {a.phantom_resolution}")
        case, preset = make_phantom(seed=a.phantom_seed, resolution=a.phantom_resolution), "amos"
    else:
        case, preset = _planning_case(a.image, a.labels, a.preset), a.preset
    series = make_truth(case, preset, cfg, progress=lambda t: print(t, flush=True))
    with folder as work:
        write_truth_files(series, work)
    m = series.record["mesh"]
    print(f"wrote {a.out}/fields ({cfg.frames} frames) and {a.out}/truth.json: {m['n_elements']:,} elements of "
          f"{max(m['cell_mm']):.1f} mm, {m['n_unknowns']:,} unknowns, largest residual "
          f"{max(f['residual'] for f in series.record['frames']):.1e}")
    return 0


def cmd_evaluate_track(a) -> int:
    from ..experiment.cine_series import evaluate_track
    from ..experiment.io import write_json_atomic

    ev = evaluate_track(a.track, a.truth)
    print("| method | error mm | p95 mm | Dice | centroid error mm |\n|---|---|---|---|---|")
    for name, r in ev["results"].items():
        print(f"| {name} | {r['error_mm']:.2f} | {r['p95_mm']:.2f} | {r['dice']:.3f} | {r['centroid_error_mm']:.2f} |")
    print("\nevery organ, mean error mm over the frames (p95):\n| method | " + " | ".join(ev["results"]["estimate"]["organs"]) + " |\n|---|"
          + "---|" * len(ev["results"]["estimate"]["organs"]))
    for name, r in ev["results"].items():
        print(f"| {name} | " + " | ".join(f"{s['error_mm']:.2f} ({s['p95_mm']:.2f})" for s in r["organs"].values()) + " |")
    print(f"latency: median {ev['latency_s']['median']:.2f} s, p95 {ev['latency_s']['p95']:.2f} s")
    if a.json:
        write_json_atomic(a.json, ev)
    png = a.png or (os.path.splitext(a.json)[0] + ".png" if a.json else None)
    if png:
        from ..experiment.cine_series import plot_track_errors

        plot_track_errors(ev, png)
        print(f"wrote {png}")
    return 0


def cmd_cine_info(a) -> int:
    import json

    from ..cine import IMAGE_SUFFIXES, cine_info

    from ..cine import is_trackrad, read_trackrad

    paths, stacks = [], []
    for p in a.files:
        if os.path.isdir(p) and is_trackrad(p):
            frames = read_trackrad(p, (0.0, 0.0, 0.0))
            f = frames[0]
            size, sp = f.image.GetSize(), f.image.GetSpacing()
            stacks.append({"file": p, "format": "trackrad", "plane": "sagittal", "size": [int(size[0]), int(size[1])],
                           "spacing_mm": [float(sp[0]), float(sp[1])], "thickness_mm": f.thickness_mm, "origin_mm": None,
                           "row_direction": [float(x) for x in f.e_u], "column_direction": [float(x) for x in f.e_v],
                           "time_s": 0.0, "time_from": "the frame rate", "frames": len(frames),
                           "fps": (len(frames) - 1) / frames[-1].time_s if len(frames) > 1 else None,
                           "note": "TrackRAD keeps no patient position or thickness: placed by --trackrad-centre, 5 mm assumed"})
            continue
        if os.path.isdir(p):
            inside = sorted(os.path.join(p, f) for f in os.listdir(p) if f.lower().endswith(IMAGE_SUFFIXES))
            if not inside:
                raise InputError(f"no cine frames (Unity .bin, DICOM, NIfTI, MHA or NRRD files) in {p}")
            paths += inside
        else:
            paths.append(p)
    info = cine_info(paths) + stacks
    if a.json:
        print(json.dumps(info, indent=1))
        return 0

    def vec(v, fmt="{:+.3f}"):
        return "(" + ", ".join(fmt.format(x) for x in v) + ")"

    print(f"{'file':<28} {'format':<9} {'plane':<11} {'size':>9} {'pixel mm':>13} {'thick':>6} {'first pixel (mm, LPS)':>28} "
          f"{'row direction':>24} {'column direction':>24} {'time s':>12}")
    for f in info:
        if f["format"] == "trackrad":
            print(f"{os.path.basename(os.path.normpath(f['file']))[-28:]:<28} {'trackrad':<9} {'sagittal':<11} {f['size'][0]:>4}x{f['size'][1]:<4} "
                  f"{f['spacing_mm'][0]:>6.3f}x{f['spacing_mm'][1]:<6.3f} {f['thickness_mm']:>6.2f} {'(none: --trackrad-centre)':>28} "
                  f"{vec(f['row_direction']):>24} {vec(f['column_direction']):>24} {f['frames']:>5} frames at {f['fps'] or 0:.2f} fps")
            continue
        t = "-" if f["time_s"] is None else f"{f['time_s']:.4f}"
        print(f"{os.path.basename(f['file'])[-28:]:<28} {f['format']:<9} {f['plane']:<11} {f['size'][0]:>4}x{f['size'][1]:<4} "
              f"{f['spacing_mm'][0]:>6.3f}x{f['spacing_mm'][1]:<6.3f} {f['thickness_mm']:>6.2f} {vec(f['origin_mm'], '{:.2f}'):>28} "
              f"{vec(f['row_direction']):>24} {vec(f['column_direction']):>24} {t:>12}")
    print("times: seconds of the day from the file's own clock (Unity .bin: its acquisition counter, UTC; DICOM: "
          "AcquisitionDateTime/Time or ContentTime), else the time in a Unity export's file name; '-': none in the file")
    return 0
