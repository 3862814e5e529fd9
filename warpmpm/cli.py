"""The ``warpmpm`` command: ``run | sweep | multi | train | view | track | make-cine | evaluate-track``.

    warpmpm run                                  # the seed's experiment on the built-in phantom (= examples/seed_experiment.py)
    warpmpm run --labels L.nii.gz --image I.nii.gz --preset totalseg_mr --json out.json --rrd out.rrd
    warpmpm sweep --phantom-seeds 0,1 --organs all --out runs/sweep.csv --workers 2
    warpmpm multi --phantom-seeds 0,1 --out runs/multi.csv
    warpmpm train runs/sweep.csv --out runs/selection_error.json
    warpmpm view out.rrd [--summary | --screenshot out.png]
    warpmpm make-cine --out runs/cine --frames 8                  # a synthetic series with its truth
    warpmpm track --image I --labels L --cine runs/cine/cine --out runs/track
    warpmpm evaluate-track --track runs/track --truth runs/cine/truth

Exit codes: 0 success; 1 some sweep tasks failed (their rows are missing; re-run to retry); 2 bad
input (one ``error:`` line naming it, nothing written); 3 the simulation failed; 130 interrupted
(Ctrl-C: one line, no partial output); 141 standard output closed by its reader (``| head``: no traceback,
and what was still to be written may be missing, as with a shell's SIGPIPE).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from dataclasses import replace

from .errors import InputError, SimulationError

__all__ = ["build_parser", "config_from_args", "cmd_run", "cmd_sweep", "cmd_multi", "cmd_train", "cmd_view",
           "cmd_track", "cmd_make_cine", "cmd_make_truth", "cmd_evaluate_track", "COMMANDS", "main", "run_main"]

EXIT_TASKS_FAILED, EXIT_INPUT, EXIT_SIMULATION, EXIT_INTERRUPTED, EXIT_PIPE_CLOSED = 1, 2, 3, 130, 141


# --------------------------------------------------------------------------------------------
# Shared option groups (parent parsers)
# --------------------------------------------------------------------------------------------

def _default(config_cls, name):
    """A config field's default: the one source of every subcommand's default (``--help`` shows it)."""
    f = config_cls.__dataclass_fields__[name]
    return f.default_factory() if callable(getattr(f, "default_factory", None)) and f.default_factory is not dataclasses.MISSING else f.default


def _experiment_default(name):
    from .experiment.config import CaseConfig

    return _default(CaseConfig, name)


def _tracker_default(name):
    from .tracker import TrackerConfig

    return _default(TrackerConfig, name)


def _case_options() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("case")
    g.add_argument("--image", help="planning image (NIfTI, MHA/MHD, NRRD or a DICOM folder)")
    g.add_argument("--labels", help="label map on the image's grid; without it the built-in phantom is used")
    g.add_argument("--preset", default="amos", choices=["amos", "totalseg_ct", "totalseg_mr"], help="label convention")
    g.add_argument("--phantom-resolution", type=float, default=1.0, help="phantom voxel size factor (2: 8x fewer voxels)")
    g.add_argument("--particle-step", type=int, default=None,
                   help="in-plane particle sampling step (default 2 for the phantom in `run`, else 1)")
    g.add_argument("--lattice", default="auto", choices=["auto", "voxel", "isotropic"],
                   help="particle lattice: one per voxel, or isotropic inside the interpolated organs (auto: for thick slices)")
    g.add_argument("--protocol", default="paper", choices=["paper", "contact", "field"],
                   help="ground-truth protocol: the seed's MPM-made truths (paper, contact) or a displacement field (field, "
                   "set by --truth-field)")
    return p


def _device_options() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("device and console")
    g.add_argument("--device", default=None, choices=["cpu", "cuda"], help="Warp device (default: CUDA when available)")
    g.add_argument("--verbose", action="store_true", help="show Warp's and ITK's own messages (module loads, warnings)")
    return p


def _selector_options() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("selection models (default: the ones shipped with warpmpm)")
    g.add_argument("--selector", default=None, help="axial slice + organ combination model (error target)")
    g.add_argument("--plane-selector", default=None, help="sagittal/coronal Dice-rank model")
    return p


def _task_options() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("cases and tasks")
    g.add_argument("--phantom-seeds", default="0", help="comma-separated phantom seeds when no --labels")
    g.add_argument("--deformations", default="1,2,3,4,5,6,7,8")
    g.add_argument("--workers", type=int, default=1, help="parallel tasks (one per case x deformation)")
    g.add_argument("--scheduler", default=None, help="'local' for a Dask LocalCluster of --workers, or a Dask scheduler address")
    return p


def _add_run_options(p: argparse.ArgumentParser) -> None:
    from .registration import BACKENDS

    t = p.add_argument_group("the truth of the run (the seed's experiment)")
    t.add_argument("--phantom-seed", type=int, default=0, help="seed of the phantom (and of the GT perturbations)")
    t.add_argument("--truth-field", default=None,
                   help="the truth as a displacement field on the planning grid (mm, world LPS, the displacement of the tissue at "
                   "each planning voxel): a frame of `warpmpm make-truth`, or your own (e.g. registered from a 4D-CT/MRI)")
    t.add_argument("--deformation", type=int, default=1, help="paper deformation type 1..8 (under contact: the scenario number)")
    t.add_argument("--no-perturb", action="store_true", help="simulate the GT with the estimator's nominal materials (debugging)")
    t.add_argument("--literal-angles", action="store_true", help="read the paper's r, g literally as r/2pi radians")
    t.add_argument("--gt-wait-settled", action="store_true",
                   help="contact protocol: simulate the ground truth until its whole body has settled (an elastic equilibrium; slow)")
    t.add_argument("--gt-contact", default=None, choices=["sticky", "sliding"], help="contact in the ground truth (default: --contact)")
    d = p.add_argument_group("what drives the estimate")
    d.add_argument("--organs", default="psdl", help="organ combination: p, ps, pd, pl, psd, psl, pdl, psdl")
    d.add_argument("--slices", default=None, help="driving slices, e.g. axial:12,sagittal:40 (input-volume voxel indices); "
                   "'auto': the axial slice and organ combination the selection model ranks best; 'auto:as', 'auto:ac', "
                   "'auto:asc': psdl, that axial slice plus the best sagittal and/or coronal slice; default: mid-pancreas axial")
    d.add_argument("--targets", default=_experiment_default("targets"), choices=["affine", "registration-demons", "registration",
                                                                                   "gt", "gt-inplane", "registration-affine",
                                                                                   "registration-bspline"],
                   help="slice motion: an affine fitted to the truth on each slice (the seed's protocol; default %(default)s), "
                   "organ-aware registration of the captured slices refined organ by organ by demons fields (what images give), "
                   "the organ-aware affines alone, the truth's 3D positions (upper bound), its in-plane part (the ceiling of 2D "
                   "registration), one registered affine per slice, or a registered B-spline field")
    d.add_argument("--registration", default=_experiment_default("registration"), choices=list(BACKENDS),
                   help="the slice registration's optimiser (registration targets): ITK's gradient descent or Gauss-Newton, "
                   "the same correlation metric")
    d.add_argument("--drive", default=_experiment_default("drive"), choices=["inplane", "pinned"],
                   help="inplane: a slice drives only its in-plane components; pinned: the through-plane coordinate too")
    d.add_argument("--no-plane-check", action="store_true",
                   help="drive every plane's registered motion, unchecked (default: each plane's motion of each organ is checked "
                   "against the captured planes first and dropped, with a warning, when it makes them match worse)")
    o = p.add_argument_group("output")
    o.add_argument("--no-volume-registration", action="store_true", help="skip the (slow) 3D registration baseline")
    o.add_argument("--json", help="write the results as JSON to this file")
    o.add_argument("--rrd", help="write a Rerun recording of the run to this .rrd file")
    o.add_argument("--rrd-every", type=int, default=20, help="log particle positions every this many steps (scalars every step)")
    o.add_argument("--quiet", action="store_true", help="no progress lines on stderr (the model's size, the GT, the estimate)")
    a = p.add_argument_group("advanced: solver variants, measured and not the default (docs/decisions/)")
    a.add_argument("--registration-passes", type=int, default=_experiment_default("registration_passes"),
                   help="with several driving planes: register them this many times, each later pass against the planning image "
                   "moved by the last pass's combined motion (kept while the planes match better); default 1")
    a.add_argument("--max-steps", type=int, default=_experiment_default("max_steps"), help="steps before the estimate stops "
                   "(default %(default)s)")
    a.add_argument("--wait-settled", action="store_true",
                   help="the settled mode: run each estimate on until the whole model has settled, not only the driven slice, with "
                   "adaptive (critical) damping and a PD drive (checked against the FEM reference; slower)")
    a.add_argument("--solver", default=_experiment_default("solver").method, choices=["explicit", "quasistatic", "auto"],
                   help="how the estimate's equilibrium is found: explicit MPM steps stopped by the paper's rule (default), "
                   "Newton / conjugate-gradient iterations to the settled equilibrium, or auto: those iterations first and "
                   "explicit steps from where they stopped when the frame has not settled after a few (sticky contact only; "
                   "the ground truth stays explicit)")
    a.add_argument("--contact", default="sticky", choices=["sticky", "sliding"],
                   help="contact between organs in the estimate: one shared grid velocity (sticky) or a field per organ "
                   "that lets touching organs slide and separate (sliding)")
    a.add_argument("--friction", type=float, default=0.0, help="Coulomb friction of sliding contact (0: frictionless)")
    a.add_argument("--threads", type=int, default=None, help="CPU threads a step or a Newton iteration is split over (default: WARPMPM_CPU_THREADS, else the cores, at most 2; 1: one core); ignored on CUDA")


def build_parser() -> argparse.ArgumentParser:
    """The ``warpmpm`` parser with its subcommands."""
    from .registration import BACKENDS

    # fresh parent parsers per subcommand: argparse shares a parent's actions, so one subcommand's
    # set_defaults (the sweep's phantom resolution) would otherwise change every other's
    case, device, selector, tasks = _case_options, _device_options, _selector_options, _task_options
    p = argparse.ArgumentParser(prog="warpmpm", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", parents=[case(), device(), selector()], help="one whole case: GT, estimate, baselines, table",
                       description="Estimate 3D pancreas motion from 2D slices with a multi-organ MPM model; prints the "
                       "estimate beside the baselines. With no arguments: the built-in phantom.")
    _add_run_options(r)

    s = sub.add_parser("sweep", parents=[case(), device(), tasks()], help="brute-force sweep (resumable CSV)",
                       description="Brute-force sweep in the paper's form: cases x deformations x organ combinations x "
                       "driving slices; one CSV row per simulation, resumable; prints the paper-form summary (also "
                       "written beside the CSV as .md).")
    s.set_defaults(phantom_resolution=2.0)
    s.add_argument("--organs", default="psdl", help="comma-separated combinations, or 'all'")
    s.add_argument("--orientations", default="axial")
    s.add_argument("--targets", default=_experiment_default("targets"), choices=["affine", "gt", "gt-inplane", "registration",
                                                                                  "registration-affine", "registration-bspline",
                                                                                  "registration-demons"])
    s.add_argument("--drive", default=_experiment_default("drive"), choices=["inplane", "pinned"])
    s.add_argument("--exclude-driven", action="store_true",
                   help="leave the driven particles out of the metrics (the multi-direction rule; default: only with several slices)")
    s.add_argument("--slice-stride", type=int, default=1)
    s.add_argument("--max-steps", type=int, default=_experiment_default("max_steps"),
                   help="steps per estimate before it is reported not converged")
    s.add_argument("--out", default="runs/sweep.csv")

    m = sub.add_parser("multi", parents=[case(), device(), tasks(), selector()], help="the paper's multi-direction protocol",
                       description="The paper's multi-direction validation (psdl, GT targets, driven particles excluded): "
                       "axial only, + coronal, + sagittal, + both, slices chosen by the selection models.")
    m.set_defaults(phantom_resolution=3.0)
    m.add_argument("--top", type=int, default=3, help="sagittal and coronal candidates tried")
    m.add_argument("--out", default="runs/multi.csv")

    t = sub.add_parser("train", help="train a selection model from sweep CSVs",
                       description="Train the condition-selection models from sweep CSVs and report them in the paper's form.")
    t.add_argument("csv", nargs="+")
    t.add_argument("--target", default="error_mm", choices=["error_mm", "dice", "dice_rank"])
    t.add_argument("--orientations", default=None, help="keep only these orientations (default: axial, or sagittal,coronal for dice_rank)")
    t.add_argument("--patience", type=int, default=100, help="stop tuning after this many trials without a better CV R2")
    t.add_argument("--max-trials", type=int, default=1000)
    t.add_argument("--test-cases", default=None, help="comma-separated cases to hold out (default: a random 20 %% of the cases)")
    t.add_argument("--storage", default=None, help="Optuna storage, e.g. sqlite:///runs/selection.db (tuning resumes from it)")
    t.add_argument("--splits", default="case,row", help="which splits to tune and report; the model saved is the first")
    t.add_argument("--out", default="selection_model.json")
    t.add_argument("--report", default=None, help="write the report as JSON here")

    k = sub.add_parser("track", parents=[device()], help="track a cine series: 2D frames in, 3D organ motion out",
                       description="Track a cine series (a folder of 2D NIfTI/MHA/DICOM frames placed in 3D) from a planning "
                       "image and its organ labels: per frame the estimated label map, optionally the displacement field, "
                       "and a row of track.csv in --out.")
    ki = k.add_argument_group("inputs")
    ki.add_argument("--image", required=True, help="planning image (a file, or a DICOM series folder)")
    ki.add_argument("--labels", default=None, help="organ label map on the planning image's grid (or give --rtstruct)")
    ki.add_argument("--rtstruct", default=None, help="the planning RT Structure Set (with --image a DICOM series folder): the "
                   "organs found by name (Pancreas, Stomach, Duodenum, Kidney_L and common variants) instead of --labels")
    ki.add_argument("--structure", action="append", default=[], metavar="ORGAN=NAME",
                   help="which structure is an organ (pancreas, stomach, duodenum, left_kidney), e.g. --structure pancreas=GTV_Panc; "
                   "repeat for each organ whose name is not a common one")
    ki.add_argument("--preset", default="amos", choices=["amos", "totalseg_ct", "totalseg_mr"])
    ki.add_argument("--cine", required=True, help="folder of cine frames: Elekta Unity .bin, DICOM (Unity, MRIdian), or NIfTI/MHA/NRRD "
                   "frames one voxel thick")
    ki.add_argument("--trackrad-centre", default=None, metavar="X,Y,Z",
                   help="a TrackRAD case as --cine keeps no patient position: the point (mm, LPS, in the planning scan) the "
                   "sagittal frames are centred on (write --trackrad-centre=X,Y,Z when X is negative)")
    ko = k.add_argument_group("outputs")
    ko.add_argument("--out", required=True, help="output folder (created)")
    ko.add_argument("--overwrite", action="store_true", help="replace an --out folder that already holds a track (whole)")
    ko.add_argument("--displacement", action="store_true", help="also write each frame's 3D displacement field")
    ko.add_argument("--dicom", action="store_true", help="also write, per frame, OUT/dicom/frame_NNNN/RS.dcm (the estimated organs, an "
                   "RT Structure Set) and REG.dcm (the displacement, a Deformable Spatial Registration), referring to the planning "
                   "series (a planning image given as NIfTI/MHA/NRRD is written once as OUT/dicom/planning/)")
    ko.add_argument("--modality", default="MR", choices=["MR", "CT"], help="modality of OUT/dicom/planning/ when --dicom writes it")
    ko.add_argument("--dose", default=None, help="the planned dose: an RT Dose (.dcm) or a dose image in Gy on any grid; each organ's "
                   "dose through each frame's estimated motion is accumulated over the series: OUT/dose/dvh.csv, dose_metrics.csv "
                   "(pancreas D95/D98, duodenum and stomach D0.5cc/D1cc/Dmax, ...), dvh.png, accumulated_dose.nii.gz")
    ko.add_argument("--beam-on", default=None, metavar="CSV", help="with --dose: a CSV with columns frame,beam_on_s (the beam-on time "
                   "of each frame, s) to weight the frames by; default: equal weights")
    ko.add_argument("--rrd", default=None, help="also write a Rerun recording: the cine frames in their 3D planes beside the estimate")
    ka = k.add_argument_group("advanced: the model, the solver and the registration (defaults measured: docs/decisions/)")
    ka.add_argument("--organs", default="psdl")
    ka.add_argument("--particle-step", type=int, default=1)
    ka.add_argument("--solver", default=_tracker_default("solver").method, choices=["auto", "explicit", "quasistatic"],
                   help="how each frame's equilibrium is found: auto (default): Newton / conjugate-gradient iterations to the "
                   "settled equilibrium, going on with explicit MPM steps when a frame has not settled after a few; explicit "
                   "MPM steps alone; or the Newton iterations alone")
    ka.add_argument("--max-steps", type=int, default=_tracker_default("max_steps"),
                   help="steps per frame before it is reported not converged (default %(default)s)")
    ka.add_argument("--wait-settled", action="store_true",
                   help="the settled mode: run each estimate on until the whole model has settled, not only the driven slice, with "
                   "adaptive (critical) damping and a PD drive (checked against the FEM reference; slower)")
    ka.add_argument("--registration", default=_tracker_default("registration"), choices=list(BACKENDS),
                   help="the slice registration's optimiser: Gauss-Newton (default) or ITK's gradient descent (same correlation metric)")
    ka.add_argument("--linear-prior", type=float, default=_tracker_default("registration_linear_prior"),
                   help="Gauss-Newton registration: how strongly a frame's scale/shear/rotation is kept near the identity (whole "
                   "slice) or the whole slice's (each organ); 0: none")
    ka.add_argument("--reference", default=_tracker_default("reference"), choices=["estimate", "previous-frame"],
                   help="what each frame is registered against: the current estimate rendered on the frame's plane (default; "
                   "registration errors do not add up) or the plane's last frame (the first: the planning image)")
    ka.add_argument("--no-predict", action="store_true",
                   help="start each frame from the last estimate, not from the frame's per-organ motion applied to every particle")
    ka.add_argument("--threads", type=int, default=None, help="CPU threads a step or a Newton iteration is split over (default: WARPMPM_CPU_THREADS, else the cores, at most 2; 1: one core); ignored on CUDA")

    c = sub.add_parser("make-cine", help="a synthetic cine series with its 3D truth (for tests and benchmarks)",
                       description="Breathing plus a contact push, each frame's truth simulated with perturbed materials, frames "
                       "on sagittal (and coronal) planes through the pancreas; --out/cine the frames, --out/truth the truth.")
    c.add_argument("--image", default=None, help="planning image (default: the built-in phantom)")
    c.add_argument("--labels", default=None)
    c.add_argument("--preset", default="amos", choices=["amos", "totalseg_ct", "totalseg_mr"])
    c.add_argument("--phantom-resolution", type=float, default=2.0)
    c.add_argument("--plane", default="sagittal", help="sagittal, coronal, or sagittal,coronal (interleaved)")
    c.add_argument("--frames", type=int, default=8)
    c.add_argument("--fps", type=float, default=4.0)
    c.add_argument("--thickness-mm", type=float, default=6.0)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--particle-step", type=int, default=1)
    c.add_argument("--pixel-mm", type=float, default=2.0, help="in-plane pixel size of the frames (mm; an MR-Linac cine: 1.5-2.5)")
    c.add_argument("--format", default="dicom", choices=["dicom", "nifti"], help="frames as 2D MR DICOM (default) or NIfTI (one voxel thick)")
    c.add_argument("--truth", default=None, help="the truth as displacement fields: a `warpmpm make-truth` folder (its fields/ and "
                   "fps) or a folder of frame_NNNN.nii.gz fields on the planning grid; default: breathing and a push simulated here")
    c.add_argument("--out", required=True)

    f = sub.add_parser("make-truth", help="a finite-element truth series: displacement fields of the abdomen under breathing and loads",
                       description="Solve the elastic equilibrium of the abdomen around the organs (finite elements, an independent "
                       "solver; surrounding tissue, the back held, the diaphragm side moved) frame by frame, and write "
                       "OUT/fields/frame_NNNN.nii.gz (mm, world LPS, at each planning voxel) and OUT/truth.json.")
    f.add_argument("--image", default=None, help="planning image (default: the built-in phantom)")
    f.add_argument("--labels", default=None, help="organ label map on the image's grid (one multi-label file)")
    f.add_argument("--preset", default="amos", choices=["amos", "totalseg_ct", "totalseg_mr"],
                   help="label convention (totalseg_*: the vertebrae are held too)")
    f.add_argument("--phantom-seed", type=int, default=0, help="seed of the built-in phantom's anatomy")
    f.add_argument("--phantom-resolution", type=float, default=1.0, help="phantom voxel size factor")
    f.add_argument("--load", default="breathing", help="comma-separated loads: breathing, drift, filling, push, peristalsis")
    f.add_argument("--frames", type=int, default=16, help="frames of the series; frame n is at n / fps seconds")
    f.add_argument("--fps", type=float, default=4.0, help="frames per second")
    f.add_argument("--seed", type=int, default=0, help="seeds the materials, the breathing cycles and the loads")
    f.add_argument("--cell-mm", type=float, default=5.0, help="edge of the finite elements (mm)")
    f.add_argument("--margin-mm", type=float, default=30.0, help="tissue meshed around the organs (mm)")
    f.add_argument("--interface-mm", type=float, default=3.0, help="sliding layer between organs (mm; 0: bonded)")
    f.add_argument("--out", required=True, help="output folder (created; must not exist or be empty)")

    e = sub.add_parser("evaluate-track", help="score a track against a synthetic series' truth")
    e.add_argument("--track", required=True)
    e.add_argument("--truth", required=True)
    e.add_argument("--json", default=None)
    e.add_argument("--png", default=None, help="plot of the pancreas error against frame for each method (default: beside --json)")

    ci = sub.add_parser("cine-info", help="what is read of cine frames: plane, size, spacing, thickness, position, axes, time",
                        description="Read cine frames (Elekta Unity .bin, DICOM, NIfTI/MHA/NRRD) as `warpmpm track` reads them and "
                        "print, per frame: its plane, size (columns x rows), pixel spacing and slice thickness (mm), the world "
                        "position of its first pixel (mm, LPS), its row and column directions and its acquisition time (s).")
    ci.add_argument("files", nargs="+", metavar="FILE", help="cine frame files (or folders of them)")
    ci.add_argument("--json", action="store_true", help="print a JSON list of objects (plane, size, spacing_mm, thickness_mm, "
                    "origin_mm, row_direction, column_direction, time_s, ...) instead of a table")

    v = sub.add_parser("view", help="open, summarise or picture a Rerun recording")
    v.add_argument("rrd")
    v.add_argument("--summary", action="store_true", help="print entities, timelines and counts (no display needed)")
    v.add_argument("--screenshot", metavar="PNG", help="save a picture of the viewer showing the recording (Xvfb when no display)")
    return p


# --------------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------------

def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    return f"warning: {message}\n"


def _quiet(verbose: bool) -> None:
    """Show only what the user asked for: no Warp banner or module-load lines, no ITK warnings; our own
    warnings as one ``warning:`` line each."""
    import warnings

    import warp as wp

    if not verbose:
        warnings.formatwarning = _one_line_warning

    wp.config.log_level = wp.LOG_INFO if verbose else wp.LOG_ERROR
    if verbose:
        return
    import SimpleITK as sitk

    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    # Warp's native library prints "CUDA driver not found" straight to file descriptor 2 on a machine
    # without a GPU, whatever the log level: initialise it with that descriptor muted (a run that asks
    # for CUDA still gets a clear error from warpmpm when none is there).
    sys.stderr.flush()
    saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def config_from_args(a):
    """The :class:`~warpmpm.experiment.config.CaseConfig` of ``warpmpm run``'s options (checked)."""
    from .experiment.config import CaseConfig
    from .solvers import SolverConfig

    step = a.particle_step if a.particle_step is not None else (2 if a.labels is None else 1)
    baselines = ("initial", "propagate", "rigid", "completion") + (() if a.no_volume_registration else ("volume_registration",))
    protocol = "field" if a.truth_field is not None else a.protocol
    return CaseConfig(image=a.image, labels=a.labels, preset=a.preset, phantom_seed=a.phantom_seed, phantom_resolution=a.phantom_resolution,
                      organs=a.organs, slices=a.slices, protocol=protocol, truth_field=a.truth_field, deformation=a.deformation, targets=a.targets, drive=a.drive,
                      registration=a.registration, registration_passes=a.registration_passes, plane_check=not a.no_plane_check,
                      device=a.device, particle_step=step, lattice=a.lattice, perturb=not a.no_perturb, literal=a.literal_angles, max_steps=a.max_steps, wait_settled=a.wait_settled,
                      baselines=baselines, rrd_every=a.rrd_every, gt_contact=a.gt_contact, gt_wait_settled=a.gt_wait_settled,
                      solver=SolverConfig(contact=a.contact, friction=a.friction, method=a.solver, cpu_threads=a.threads))


def cmd_run(a) -> int:
    from .experiment.auto import auto_condition
    from .experiment.io import check_output_path, write_json_atomic
    from .experiment.run import run_case
    from .experiment.tables import format_table

    cfg = config_from_args(a)
    for path, option in ((a.json, "--json"), (a.rrd, "--rrd")):
        if path:
            check_output_path(path, option)
    selection = None
    if cfg.is_auto:
        organs, slices, selection = auto_condition(cfg, a.selector, a.plane_selector)
        cfg = replace(cfg, organs=organs, slices=slices)
    recorder = None
    if a.rrd:
        from viewer.recording import RerunRecorder

        recorder = RerunRecorder(a.rrd, every=cfg.rrd_every)
    from .experiment.run import Progress

    def tell(text, end="\n"):
        print(text, end=end, file=sys.stderr, flush=True)

    out = run_case(cfg, recorder, Progress(None if a.quiet else tell, live=sys.stderr.isatty()))
    out.selection = selection
    print(format_table(out))
    if selection is not None:
        print(f"selected {out.organs} {','.join(out.slices)} in {selection['selection_ms']:.2f} ms "
              f"(predicted {selection['predicted']:.2f})")
    if a.json:
        write_json_atomic(a.json, out)
        print(f"wrote {a.json}")
    if a.rrd:
        print(f"wrote {a.rrd} (open with: warpmpm view {a.rrd})")
    return 0


def _tasks_common(a):
    from .experiment.sweep import sweep_cases

    if a.workers < 1:
        raise InputError(f"--workers must be at least 1, got {a.workers}")
    try:
        deformations = [int(x) for x in a.deformations.split(",")]
    except ValueError:
        raise InputError(f"--deformations must be comma-separated integers, got {a.deformations!r}") from None
    cases = sweep_cases(a.labels, a.image, a.preset, a.phantom_seeds, a.phantom_resolution)
    return cases, deformations


def _write_table(out_csv: str, table: str) -> None:
    from .experiment.io import check_output_path

    path = os.path.splitext(check_output_path(out_csv, "--out"))[0] + ".md"
    tmp = path + ".part"
    with open(tmp, "w") as f:
        f.write(table + "\n")
    os.replace(tmp, path)


def cmd_sweep(a) -> int:
    from .experiment.config import CaseConfig
    from .experiment.sweep import sweep
    from .experiment.tables import summarize
    from .images import COMBINATIONS

    if a.slice_stride < 1:
        raise InputError(f"--slice-stride must be at least 1, got {a.slice_stride}")
    cases, deformations = _tasks_common(a)
    combos = COMBINATIONS if a.organs == "all" else tuple(a.organs.split(","))
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    base = CaseConfig(particle_step=1 if a.particle_step is None else a.particle_step, lattice=a.lattice, device=a.device, targets=a.targets, drive=a.drive, max_steps=a.max_steps,
                      exclude_driven=True if a.exclude_driven else None)
    for combo in combos:
        replace(base, organs=combo)  # each combination checked before any task starts
    rows, failed = sweep(cases, deformations, combos, tuple(a.orientations.split(",")), a.out, protocol=a.protocol,
                         slice_stride=a.slice_stride, base=base, scheduler=a.scheduler, workers=a.workers)
    table = summarize(rows)
    print(table)
    _write_table(a.out, table)
    return EXIT_TASKS_FAILED if failed else 0


def cmd_multi(a) -> int:
    from .experiment.config import CaseConfig
    from .experiment.multi_direction import multi_direction
    from .experiment.tables import summarize_multi
    from .selection import DEFAULT_PLANE_SELECTOR, DEFAULT_SELECTOR

    if a.top < 1:
        raise InputError(f"--top must be at least 1, got {a.top}")
    cases, deformations = _tasks_common(a)
    d = os.path.dirname(os.path.abspath(a.out))
    if not os.path.isdir(d):
        raise InputError(f"output folder {d} for --out does not exist")
    base = CaseConfig(particle_step=1 if a.particle_step is None else a.particle_step, lattice=a.lattice, device=a.device,
                      protocol=a.protocol)
    rows, failed = multi_direction(cases, deformations, a.selector or DEFAULT_SELECTOR, a.plane_selector or DEFAULT_PLANE_SELECTOR,
                                   a.out, base=base, top=a.top, workers=a.workers, scheduler=a.scheduler)
    table = summarize_multi(rows)
    print(table)
    _write_table(a.out, table)
    return EXIT_TASKS_FAILED if failed else 0


def cmd_train(a) -> int:
    from .experiment.train import train

    return train(a)


def cmd_view(a) -> int:
    from viewer.__main__ import main as view_main

    argv = [a.rrd] + (["--summary"] if a.summary else []) + (["--screenshot", a.screenshot] if a.screenshot else [])
    return view_main(argv)


def _planning_case(image, labels, preset):
    from .images import load_case

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
        raise InputError(f"--beam-on file not found: {path}")
    weights = [None] * n_frames
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if not reader.fieldnames or not {"frame", "beam_on_s"} <= set(reader.fieldnames):
            raise InputError(f"--beam-on {path}: columns frame,beam_on_s are required (it has {reader.fieldnames})")
        for line, row in enumerate(reader, start=2):
            try:
                n, t = int(row["frame"]), float(row["beam_on_s"])
            except (TypeError, ValueError):
                raise InputError(f"--beam-on {path}, line {line}: frame must be an integer and beam_on_s a number") from None
            if not 0 <= n < n_frames:
                raise InputError(f"--beam-on {path}, line {line}: frame {n} is not one of the cine's {n_frames} frames (0-{n_frames - 1})")
            if not (np.isfinite(t) and t >= 0):
                raise InputError(f"--beam-on {path}, line {line}: beam_on_s {t} must be finite and >= 0")
            if weights[n] is not None:
                raise InputError(f"--beam-on {path}, line {line}: frame {n} is given twice")
            weights[n] = t
    missing = [n for n, w in enumerate(weights) if w is None]
    if missing:
        raise InputError(f"--beam-on {path} gives no beam_on_s for frames {missing[:10]}{' ...' if len(missing) > 10 else ''}")
    return weights


def _remove_dead_tracks(parent: str) -> None:
    """Remove the working folders (``.track-*``) that killed tracks left in ``parent``: those whose process is gone."""
    import shutil

    for name in os.listdir(parent):
        path = os.path.join(parent, name)
        if not (name.startswith(".track-") and os.path.isdir(path)):
            continue
        try:
            pid = int(open(os.path.join(path, "pid")).read().strip())
        except (OSError, ValueError):
            continue  # not ours, or still being created: left alone
        try:
            os.kill(pid, 0)
            continue  # still running
        except ProcessLookupError:
            pass
        except PermissionError:
            continue
        shutil.rmtree(path, ignore_errors=True)
        print(f"removed {path}: the unfinished work of a track that was killed", file=sys.stderr)


def _dicom_writer(case, a, work, frames=()):
    """The planning series the DICOM outputs refer to: the user's (a DICOM --image), else the planning image written as one."""
    from .dicom_rt import FrameDicomWriter, read_series_reference, write_series
    from .images import grid_differences

    ref = case.meta.get("dicom")
    if ref is None and os.path.isdir(a.image):
        ref = read_series_reference(a.image)
    if ref is not None:
        diff = grid_differences(ref.geometry, case.geometry)
        if diff:
            raise InputError(f"--dicom: the DICOM series {a.image} is not on the planning grid ({'; '.join(diff)})")
    else:
        ref = write_series(case.intensity_image(), os.path.join(work, "dicom", "planning"), modality=a.modality)
    names = case.meta.get("roi_names") or {}
    cine_for = next((f.frame_of_reference for f in frames if getattr(f, "frame_of_reference", "")), None)
    return FrameDicomWriter(ref, names, cine_for)


def cmd_track(a) -> int:
    from .cine import read_cine
    from .solvers import SolverConfig
    from .tracker import Tracker, TrackerConfig

    bad = sorted(set(a.organs) - set("psdl"))
    if bad or not a.organs:
        raise InputError(f"--organs {a.organs!r}: letters from p (pancreas), s (stomach), d (duodenum), l (left kidney); "
                         f"{', '.join(repr(b) for b in bad) or 'none given'} is not one")
    if a.max_steps < 1:
        raise InputError(f"--max-steps must be at least 1, got {a.max_steps}")
    if a.rtstruct:
        from .dicom_rt import case_from_rtstruct

        if a.labels:
            raise InputError("give the organs once: --labels (a label map) or --rtstruct (a structure set), not both")
        case = case_from_rtstruct(a.image, a.rtstruct, _structure_mapping(a.structure), a.organs)
    else:
        if a.structure:
            raise InputError("--structure names structures of an --rtstruct; with --labels use --preset")
        case = _planning_case(a.image, a.labels, a.preset)
    from .cine import is_trackrad, read_trackrad

    if is_trackrad(a.cine):
        frames = read_trackrad(a.cine, _point(a.trackrad_centre, "--trackrad-centre") if a.trackrad_centre else None)
    else:
        if a.trackrad_centre:
            raise InputError(f"--trackrad-centre places a TrackRAD case; {a.cine} is not one (its frames carry their own position)")
        frames = read_cine(a.cine)
    out = os.path.abspath(a.out)
    parent = os.path.dirname(out)
    if not os.path.isdir(parent):
        raise InputError(f"output folder {parent} for --out does not exist")
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(f"--out {a.out} is a file; name a folder")
    if os.path.isdir(out) and os.listdir(out) and not a.overwrite:
        raise InputError(f"--out {a.out} already holds files (an earlier track?); name a new folder, or add --overwrite to "
                         "replace it whole")
    cfg = TrackerConfig(organs=a.organs, particle_step=a.particle_step, max_steps=a.max_steps, displacement=a.displacement,
                        predict=not a.no_predict, wait_settled=a.wait_settled, registration=a.registration,
                        registration_linear_prior=a.linear_prior, reference=a.reference,
                        solver=SolverConfig(device=a.device, method=a.solver, cpu_threads=a.threads))
    dose, weights = None, None
    if a.beam_on and not a.dose:
        raise InputError("--beam-on weights the frames' dose: give --dose too")
    if a.dose:
        from .dose import DoseAccumulator, read_dose

        organs_wanted = [o for o, c in zip(("pancreas", "stomach", "duodenum", "left_kidney"), "psdl") if c in a.organs]
        masks = {o: case.labels == v for o, v in case.label_map.items() if o in organs_wanted}
        dose = DoseAccumulator(read_dose(a.dose), case.geometry, masks)
        weights = _beam_on(a.beam_on, len(frames)) if a.beam_on else None
    tracker = Tracker(case, frames, cfg)
    print(f"{len(frames)} frames on {len({f.plane for f in frames})} plane(s); model {tracker.model.n:,} particles "
          f"({tracker.model.letters}), {len(tracker.driven):,} on the frames' planes", file=sys.stderr)
    recorder = None
    if a.rrd:
        from .experiment.io import check_output_path
        from viewer.recording import TrackRecorder

        recorder = TrackRecorder(check_output_path(a.rrd, "--rrd"), tracker.model)
    # written into a folder beside --out and moved into place at the end: an interrupted or failed track leaves no
    # half-written --out, and --overwrite replaces the old track whole (two tracks are never mixed)
    import shutil
    import tempfile

    _remove_dead_tracks(parent)
    work = tempfile.mkdtemp(prefix=".track-", dir=parent)
    with open(os.path.join(work, "pid"), "w") as fh:  # whose it is: a later track removes it if this one was killed
        fh.write(str(os.getpid()))
    try:
        dicom = _dicom_writer(case, a, work, frames) if a.dicom else None
        rows = tracker.run(work, progress=lambda t: print(t, flush=True), recorder=recorder, dicom=dicom, dose=dose,
                           dose_weights=weights)
        if dose is not None and dicom is not None:
            import SimpleITK as sitk

            from .dicom_rt import write_rtdose

            plan = dose.dose.GetMetaData("plan_uid") if dose.dose.HasMetaDataKey("plan_uid") else None
            write_rtdose(os.path.join(work, "dicom", "RD_accumulated.dcm"), dicom.ref,
                         sitk.GetArrayFromImage(dose.accumulated_image()), plan_uid=plan,
                         description="warpmpm accumulated dose (organs only)")
        os.remove(os.path.join(work, "pid"))
        if os.path.isdir(out):
            shutil.rmtree(out)
        os.replace(work, out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    import numpy as np

    lat = np.array([r["latency_s"] for r in rows[1:]] or [rows[0]["latency_s"]])
    print(f"latency per frame after the first: median {np.median(lat):.2f} s, p95 {np.percentile(lat, 95):.2f} s; wrote {a.out}")
    return 0


def cmd_make_cine(a) -> int:
    from .experiment.cine_series import check_cine_parameters, make_cine
    from .phantom import make_phantom

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
    if os.path.exists(a.out) and not os.path.isdir(a.out):
        raise InputError(f"--out {a.out} is a file; name a new folder")
    if os.path.isdir(a.out) and os.listdir(a.out):
        raise InputError(f"--out {a.out} already holds files; name a new or empty folder (two series are never mixed)")
    if a.image is not None and a.labels is None:
        raise InputError("--image needs --labels (without both, the built-in phantom is used)")
    import math
    import shutil
    import tempfile

    if not (math.isfinite(a.phantom_resolution) and 0.25 <= a.phantom_resolution <= 16):
        raise InputError(f"--phantom-resolution must be a finite number in 0.25..16 (mm), got {a.phantom_resolution}")
    if not 1 <= a.particle_step <= 16:
        raise InputError(f"--particle-step must be a whole number in 1..16, got {a.particle_step}")
    out = os.path.abspath(a.out)
    if not os.path.isdir(os.path.dirname(out)):
        raise InputError(f"the folder {os.path.dirname(out)} for --out does not exist")
    # written beside --out and moved into place at the end: a failed or interrupted series leaves nothing behind
    work = tempfile.mkdtemp(prefix=".make-cine-", dir=os.path.dirname(out))
    try:
        if a.labels is None:  # the phantom: its planning image and labels go beside the series, for `warpmpm track`
            from .images import write_case

            os.makedirs(os.path.join(work, "planning"))
            paths = os.path.join(work, "planning", "labels.nii.gz"), os.path.join(work, "planning", "image.nii.gz")
            write_case(make_phantom(resolution=a.phantom_resolution), *paths)
            case = _planning_case(paths[1], paths[0], "amos")  # as the tracker will read it (float32 geometry)
        else:
            case = _planning_case(a.image, a.labels, a.preset)
        make_cine(case, work, planes=planes, frames=a.frames, fps=fps, thickness_mm=a.thickness_mm, pixel_mm=a.pixel_mm,
                  seed=a.seed, particle_step=a.particle_step, fmt=a.format, truth_fields=fields,
                  progress=lambda t: print(t, flush=True))
        if os.path.isdir(out):
            os.rmdir(out)  # empty (checked above)
        os.replace(work, out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"wrote {a.out}/cine and {a.out}/truth")
    return 0


def cmd_make_truth(a) -> int:
    from .phantom import make_phantom
    from .truth_fem import TruthConfig, make_truth, write_truth

    cfg = TruthConfig(loads=tuple(x.strip() for x in a.load.split(",") if x.strip()), frames=a.frames, fps=a.fps, seed=a.seed,
                      cell_mm=a.cell_mm, margin_mm=a.margin_mm, interface_mm=a.interface_mm)
    out = os.path.abspath(a.out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(f"--out {a.out} is a file; name a new folder")
    if os.path.isdir(out) and os.listdir(out):
        raise InputError(f"--out {a.out} already holds files; name a new or empty folder (a truth is never mixed with another)")
    if a.labels is None:
        if a.image is not None:
            raise InputError("--image needs --labels (without both, the built-in phantom is used)")
        import math

        from .experiment.config import MAX_SEED

        if not (0 <= a.phantom_seed <= MAX_SEED):
            raise InputError(f"--phantom-seed must be a whole number in 0..{MAX_SEED}, got {a.phantom_seed}")
        if not (math.isfinite(a.phantom_resolution) and 0.25 <= a.phantom_resolution <= 16):
            raise InputError(f"--phantom-resolution must be a finite number in 0.25..16 (mm), got {a.phantom_resolution}")
        case, preset = make_phantom(seed=a.phantom_seed, resolution=a.phantom_resolution), "amos"
    else:
        case, preset = _planning_case(a.image, a.labels, a.preset), a.preset
    series = make_truth(case, preset, cfg, progress=lambda t: print(t, flush=True))
    write_truth(series, a.out)
    m = series.record["mesh"]
    print(f"wrote {a.out}/fields ({cfg.frames} frames) and {a.out}/truth.json: {m['n_elements']:,} elements of "
          f"{max(m['cell_mm']):.1f} mm, {m['n_unknowns']:,} unknowns, largest residual "
          f"{max(f['residual'] for f in series.record['frames']):.1e}")
    return 0


def cmd_evaluate_track(a) -> int:
    from .experiment.cine_series import evaluate_track
    from .experiment.io import write_json_atomic

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
        from .experiment.cine_series import plot_track_errors

        plot_track_errors(ev, png)
        print(f"wrote {png}")
    return 0


def cmd_cine_info(a) -> int:
    import json

    from .cine import IMAGE_SUFFIXES, cine_info

    from .cine import is_trackrad, read_trackrad

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


COMMANDS = {"run": cmd_run, "cine-info": cmd_cine_info, "sweep": cmd_sweep, "multi": cmd_multi, "train": cmd_train, "view": cmd_view, "track": cmd_track,
            "make-cine": cmd_make_cine, "make-truth": cmd_make_truth, "evaluate-track": cmd_evaluate_track}


def main(argv=None) -> int:
    """Entry point of the ``warpmpm`` console script; returns the exit code (module docstring)."""
    a = build_parser().parse_args(argv)
    _quiet(getattr(a, "verbose", False))
    try:
        return COMMANDS[a.command](a)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except SimulationError as exc:
        print(f"simulation error: {exc}", file=sys.stderr)
        return EXIT_SIMULATION
    except KeyboardInterrupt:
        print("interrupted: nothing was written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # the reader of stdout went away (`warpmpm ... | head`): stop without a traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_PIPE_CLOSED


def run_main(argv=None) -> int:
    """``warpmpm run`` with ``argv`` (what ``examples/seed_experiment.py`` calls)."""
    return main(["run", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())
