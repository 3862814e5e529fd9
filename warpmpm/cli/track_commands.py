"""The product's commands: ``track`` (your scan and cine series in, per-frame 3D organ motion out), ``make-cine``,
``make-truth``, ``evaluate-track`` and ``cine-info``."""

from __future__ import annotations

import os

from ..errors import InputError

__all__ = ["cmd_estimators", "cmd_track", "cmd_make_cine", "cmd_make_truth", "cmd_evaluate_track", "cmd_cine_info"]


def _planning_case(image, labels, preset):
    from ..session import planning_case

    return planning_case(image, labels, None, preset)


def _point(text: str, option: str):
    try:
        p = [float(v) for v in text.split(",")]
    except ValueError:
        p = []
    if len(p) != 3 or not all(abs(v) < 1e4 for v in p):
        raise InputError(f"{option} {text!r}: three finite numbers in mm, e.g. {option}=-10,20,35")
    return p


def _arguments(a) -> dict:
    """The command's arguments, as recorded in the output folder's record file."""
    return {k: v for k, v in vars(a).items() if isinstance(v, (str, int, float, bool, type(None), list))}


def cmd_track(a) -> int:
    """``warpmpm track``: the arguments parsed into :func:`warpmpm.session.track`."""
    from ..session import track
    from ..solvers import SolverConfig
    from ..tracker import TrackerConfig

    cfg = TrackerConfig(estimator=a.estimator, materials=a.materials, preset=None if a.rtstruct else a.preset,
                        organs=a.organs, particle_step=a.particle_step, max_steps=a.max_steps,
                        predict=not a.no_predict, wait_settled=a.wait_settled, registration=a.registration,
                        registration_linear_prior=a.linear_prior, reference=a.reference,
                        solver=SolverConfig(device=a.device, method=a.solver, cpu_threads=a.threads))
    outputs = ["labels", "displacement"] if a.displacement else ["labels"]
    if a.rrd:
        from ..errors import optional

        optional("rerun", "a Rerun recording (--rrd)")
        from viewer.recording import RerunOutput

        outputs.append(RerunOutput(a.rrd))
    res = track(a.image, a.cine, a.out, labels=a.labels, rtstruct=a.rtstruct, preset=a.preset, structures=a.structure,
                config=cfg, outputs=outputs, dicom=a.dicom, modality=a.modality, dose=a.dose, beam_on=a.beam_on,
                max_dose_gy=a.max_dose_gy, dose_coverage_warn_pct=a.dose_coverage_warn,
                assume_registered=a.assume_registered,
                trackrad_centre_mm=_point(a.trackrad_centre, "--trackrad-centre") if a.trackrad_centre else None,
                overwrite=a.overwrite, progress=lambda t: print(t, flush=True), arguments=_arguments(a))
    print(f"latency per frame after the first: median {res.latency_s['median']:.2f} s, p95 {res.latency_s['p95']:.2f} s; "
          f"wrote {a.out}")
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
    given = None
    if a.slices:
        from ..slices import parse_slices

        given = {}
        for s in parse_slices(a.slices):
            if s.orientation not in planes:
                raise InputError(f"--slices {a.slices}: {s.orientation} is not one of the imaged planes (--plane {a.plane})")
            if s.orientation in given:
                raise InputError(f"--slices {a.slices}: {s.orientation} is given twice")
            given[s.orientation] = s.index
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
                  seed=a.seed, particle_step=a.particle_step, fmt=a.format, truth_fields=fields, slices=given,
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
        if "error_mm" in r:  # nearest / global are scored on the organs no frame measured only
            print(f"| {name} | {r['error_mm']:.2f} | {r['p95_mm']:.2f} | {r['dice']:.3f} | {r['centroid_error_mm']:.2f} |")
    organs = list(ev["results"]["estimate"]["organs"])
    unseen = [o for o, s in ev["results"]["estimate"]["organs"].items() if not s.get("seen", True)]
    print("\nevery organ, mean error mm over the frames (p95); nearest / global: the baselines of an organ no frame measured:\n"
          "| method | " + " | ".join(o + (" (on no plane)" if o in unseen else "") for o in organs) + " |\n|---|" + "---|" * len(organs))
    for name, r in ev["results"].items():
        print(f"| {name} | " + " | ".join(f"{r['organs'][o]['error_mm']:.2f} ({r['organs'][o]['p95_mm']:.2f})" if o in r["organs"]
                                          else "" for o in organs) + " |")
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
