"""The ``warpmpm`` command's parser: every subcommand's options, their defaults read from the configs
(:class:`~warpmpm.experiment.config.CaseConfig`, :class:`~warpmpm.tracker.TrackerConfig`) so ``--help`` shows them."""

from __future__ import annotations

import argparse
import dataclasses


__all__ = ["build_parser"]


# --------------------------------------------------------------------------------------------
# Shared option groups (parent parsers)
# --------------------------------------------------------------------------------------------

def _default(config_cls, name):
    """A config field's default: the one source of every subcommand's default (``--help`` shows it)."""
    f = config_cls.__dataclass_fields__[name]
    return f.default_factory() if callable(getattr(f, "default_factory", None)) and f.default_factory is not dataclasses.MISSING else f.default


def _experiment_default(name):
    from ..experiment.config import CaseConfig

    return _default(CaseConfig, name)


def _tracker_default(name):
    from ..tracker import TrackerConfig

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


def _device(text: str) -> str:
    """``--device``: ``cpu``, ``cuda`` or ``cuda:N`` (argparse refuses anything else in one line)."""
    import re

    if text in ("cpu", "cuda") or re.fullmatch(r"cuda:\d{1,2}", text):
        return text
    raise argparse.ArgumentTypeError(f"{text!r}: use cpu, cuda or cuda:N (N the GPU's number, e.g. cuda:1)")


def _device_options() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("device and console")
    g.add_argument("--device", default=None, type=_device, metavar="{cpu,cuda,cuda:N}",
                   help="Warp device: cpu, cuda (the first GPU) or cuda:N (GPU N); default: CUDA when available")
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
    from ..registration import BACKENDS

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
    d.add_argument("--estimator", default=_experiment_default("estimator"), choices=["copy", "slice-driven"],
                   help="which estimator is results.estimate (both are scored, each under its own name): copy, each organ "
                   "moved by the motion the planes show of it (default: the measured best); slice-driven, the seed's MPM "
                   "(examples/seed_experiment.py reproduces the paper with it)")
    d.add_argument("--materials", default=None, metavar="paper|tissue|FILE",
                   help="the estimators' materials (slice-driven: default paper; completion: default tissue), or a JSON file "
                   "(docs/how-to/change-materials.md); the truth keeps its own")
    d.add_argument("--organs", default="psdl", help="organ combination: p, ps, pd, pl, psd, psl, pdl, psdl")
    d.add_argument("--slices", default=None, help="driving slices, e.g. axial:12,sagittal:40 (input-volume voxel indices); "
                   "'auto': the axial slice and organ combination the selection model ranks best; 'auto:as', 'auto:ac', "
                   "'auto:asc': psdl, that axial slice plus the best sagittal and/or coronal slice; default: mid-pancreas axial")
    d.add_argument("--targets", default=_experiment_default("targets"), choices=["affine", "registration-demons", "registration",
                                                                                   "gt", "gt-inplane", "registration-affine",
                                                                                   "registration-bspline", "cine"],
                   help="slice motion: an affine fitted to the truth on each slice (the seed's protocol; default %(default)s), "
                   "'cine': the planes imaged as cine frames (--cine-thickness-mm) and followed by the tracker's own frame "
                   "pipeline (what `warpmpm track` gives for them), "
                   "organ-aware registration of the captured slices refined organ by organ by demons fields (what images give), "
                   "the organ-aware affines alone, the truth's 3D positions (upper bound), its in-plane part (the ceiling of 2D "
                   "registration), one registered affine per slice, or a registered B-spline field")
    d.add_argument("--cine-thickness-mm", type=float, default=_experiment_default("cine_thickness_mm"),
                   help="--targets cine: the captured planes' slice thickness, mm (default %(default)s)")
    d.add_argument("--cine-linear-prior", type=float, default=_experiment_default("cine_linear_prior"),
                   help="--targets cine: the tracker's --linear-prior (default %(default)s: a run's frame is one jump from "
                   "planning, where the tracker's 10 fails; docs/results.md)")
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
    from ..registration import BACKENDS

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

    q = sub.add_parser("sweep-planes", help="cine-plane placements on finite-element truths (resumable CSV)",
                       description="Where to image: for each case, truth seed and load, a finite-element truth is made and every "
                       "placement of the cine planes (one sagittal plane across the pancreas; a sagittal and a coronal plane across it, "
                       "every pair of their positions) is scored for the copy of the planes' motion, rigid "
                       "tracking and the completion solve, every organ, beside what each organ shows on the planes. One CSV row "
                       "per placement, resumable; the first placement of each family is the rule without a model (each plane "
                       "where it shows the most pancreas).")
    q.add_argument("--labels", default=None, help="a labelled planning scan (else the built-in phantom, one per --phantom-seeds)")
    q.add_argument("--image", default=None, help="its image")
    q.add_argument("--preset", default="amos", choices=["amos", "totalseg_ct", "totalseg_mr"], help="label convention")
    q.add_argument("--phantom-seeds", default="0", help="comma-separated phantom seeds when no --labels")
    q.add_argument("--phantom-resolution", type=float, default=1.0, help="phantom voxel size factor (2: 8x fewer voxels)")
    q.add_argument("--particle-step", type=int, default=None, help="in-plane particle sampling step (default 2 for the phantom, else 1)")
    q.add_argument("--truth-seeds", default="0", help="comma-separated seeds of the finite-element truths (materials, breathing)")
    q.add_argument("--loads", default="breathing", help="comma-separated loads of the truths, each '+'-joined (breathing, "
                   "breathing+push, ...)")
    q.add_argument("--families", default="sagittal,sagittal+coronal", help="placement families: sagittal, sagittal+coronal")
    q.add_argument("--positions", type=int, default=5, help="positions of each plane across the pancreas, besides the rule's (default %(default)s)")
    q.add_argument("--truth-cell-mm", type=float, default=None, help="the truth's mesh cell (mm; default: TruthConfig's)")
    q.add_argument("--out", default="runs/planes.csv")
    q.add_argument("--workers", type=int, default=1, help="parallel tasks (one per case x truth seed x load)")
    q.add_argument("--scheduler", default=None, help="'local' for a Dask LocalCluster of --workers, or a Dask scheduler address")
    q.add_argument("--refresh-features", action="store_true", help="run no truth: recompute the placement features of these "
                   "cases' rows in --out from their planning scans (after the features changed) and rewrite it whole")

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

    pp = sub.add_parser("plan-planes", help="where to image: the cine-plane placements ranked for a planning scan",
                        description="Where to image: placements of the cine planes across the pancreas (one sagittal "
                        "plane; a sagittal and a coronal plane) ranked by each organ's error, simulated on a finite-element "
                        "breathing truth of this scan (default) or predicted by the plane-placement model (--method model); "
                        "the rule without a model (each plane where it shows the most pancreas) is named with its rank. Slice indices are the planning scan's (what --slices and the "
                        "MR-Linac take). With no arguments: the built-in phantom.")
    pi = pp.add_argument_group("planning scan")
    pi.add_argument("--image", default=None, help="planning image (a file, or a DICOM series folder with --rtstruct)")
    pi.add_argument("--labels", default=None, help="its organ label map (else the built-in phantom)")
    pi.add_argument("--rtstruct", default=None, help="the planning RT Structure Set instead of --labels")
    pi.add_argument("--structure", action="append", default=[], metavar="ORGAN=NAME",
                    help="which structure of --rtstruct is an organ, e.g. --structure pancreas=GTV_Panc")
    pi.add_argument("--preset", default="amos", choices=["amos", "totalseg_ct", "totalseg_mr"], help="label convention")
    pi.add_argument("--phantom-seed", type=int, default=0, help="the built-in phantom's seed (no --labels)")
    pi.add_argument("--phantom-resolution", type=float, default=1.0, help="phantom voxel size factor (2: 8x fewer voxels)")
    pi.add_argument("--particle-step", type=int, default=None, help="in-plane particle sampling step (default 2 for the "
                    "phantom, else 1)")
    pr = pp.add_argument_group("ranking")
    pr.add_argument("--method", default="simulate", choices=["simulate", "model"],
                    help="simulate (default): rank a grid of placements by the error of copying their planes' motion on a "
                    "finite-element breathing truth of this scan (about a minute); model: rank every placement by the placement "
                    "model's prediction (under 100 ms; measured no better than the rule, see its report)")
    pr.add_argument("--families", default="sagittal,sagittal+coronal", help="placement families: sagittal (one plane, "
                    "MRIdian-like), sagittal+coronal (Unity-like)")
    pr.add_argument("--rank-by", default="pancreas", help="comma-separated organs whose mean predicted error ranks the "
                    "placements (pancreas, stomach, duodenum, left_kidney)")
    pr.add_argument("--top", type=int, default=10, help="placements printed (default %(default)s)")
    pr.add_argument("--stride", type=int, default=1, help="every n-th slice across the pancreas (default every slice)")
    pr.add_argument("--motion-mm", type=float, default=None, help="the organs' expected motion (mm): predicted errors in mm "
                    "instead of fractions of the motion")
    pr.add_argument("--model", default=None, help="a plane-placement model of `warpmpm train-planes` (default: the shipped one)")
    ps = pp.add_argument_group("simulation (--method simulate: about a minute, once at planning)")
    ps.add_argument("--positions", type=int, default=4, help="positions of each plane across the pancreas besides the "
                    "rule's (default %(default)s)")
    ps.add_argument("--truth-seed", type=int, default=0, help="the truth's seed (materials, breathing)")
    ps.add_argument("--truth-cell-mm", type=float, default=None, help="the truth's mesh cell (mm; default: TruthConfig's; "
                    "coarser is faster)")
    po = pp.add_argument_group("outputs")
    po.add_argument("--picture", default=None, help="PNG of the best placements' planes over the organs")
    po.add_argument("--json", default=None, help="every placement ranked, with its predictions and features")
    pp.add_argument("--verbose", action="store_true", help="show Warp's and ITK's own messages")

    tp = sub.add_parser("train-planes", help="train the plane-placement model from plane-sweep CSVs",
                        description="Train the plane-placement model (one XGBoost regressor per organ, Optuna-tuned on "
                        "folds by case) from `warpmpm sweep-planes` CSVs; report it split by case (held-out cases, and "
                        "leave one case out) against the rule without a model.")
    tp.add_argument("csv", nargs="+")
    tp.add_argument("--test-cases", default=None, help="comma-separated cases to hold out (default: a random quarter)")
    tp.add_argument("--method", default="copy", choices=["copy", "completion", "rigid"], help="whose error the model predicts")
    tp.add_argument("--max-trials", type=int, default=60)
    tp.add_argument("--patience", type=int, default=20, help="stop tuning after this many trials without a better CV R2")
    tp.add_argument("--storage", default=None, help="Optuna storage, e.g. sqlite:///runs/planes.db (tuning resumes from it)")
    tp.add_argument("--out", default="plane_placement.json")
    tp.add_argument("--report", default=None, help="write the report as JSON here")
    tp.add_argument("--verbose", action="store_true", help="show Warp's and ITK's own messages")

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
    ki.add_argument("--assume-registered", action="store_true",
                   help="the cine and the dose are in the planning scan's coordinates although their DICOM Frame of Reference "
                   "differs from the planning series' (you registered them): a warning instead of a refusal. Another "
                   "patient's files are refused all the same")
    ki.add_argument("--max-dose-gy", type=float, default=120.0,
                   help="the largest dose a voxel of --dose may hold (Gy, default %(default)s): a dose above it (cGy labelled "
                   "Gy, a wrong DoseGridScaling) is refused")
    ki.add_argument("--dose-coverage-warn", type=float, default=1.0,
                   help="warn when more than this percentage of an organ's voxels is carried outside the dose grid in a "
                   "frame (default %(default)s %%); each organ's share per frame is in dose/dose_coverage.csv")
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
    from ..estimators import ESTIMATORS

    ka.add_argument("--estimator", default=_tracker_default("estimator"), choices=list(ESTIMATORS),
                   help="what turns a frame's observed motion into every organ's (`warpmpm estimators` lists them with their "
                   "measurements): copy (default, the measured best): each organ moved by what the planes show of it; "
                   "slice-driven: the seed's MPM driven at the plane's particles (--solver, --max-steps, --wait-settled, "
                   "--no-predict set it); completion: the whole abdomen's equilibrium driven by the planes' observed motion, "
                   "set up once before the first frame (40-90 s)")
    ka.add_argument("--materials", default=None, metavar="paper|tissue|FILE",
                    help="the organs' materials for the estimators that use any (slice-driven, completion): the seed "
                    "paper's table, every tissue at the middle of its published range, or a JSON file (docs/how-to/"
                    "change-materials.md); default: each estimator's own (slice-driven paper, completion tissue)")
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
                       "on sagittal (and coronal) planes where each shows the largest section of the pancreas (or where --slices puts them); "
                       "--out/cine the frames, --out/truth the truth.")
    c.add_argument("--image", default=None, help="planning image (default: the built-in phantom)")
    c.add_argument("--labels", default=None)
    c.add_argument("--preset", default="amos", choices=["amos", "totalseg_ct", "totalseg_mr"])
    c.add_argument("--phantom-resolution", type=float, default=2.0)
    c.add_argument("--plane", default="sagittal", help="sagittal, coronal, or sagittal,coronal (interleaved)")
    c.add_argument("--slices", default=None, help="where each plane lies, as planning-volume slice indices, e.g. "
                   "sagittal:40,coronal:62 (what `warpmpm plan-planes` prints); a plane not named lies where it shows the "
                   "largest section of the pancreas")
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

    sub.add_parser("estimators", help="list the tracker's estimators: what each uses, what it measured, which is the default",
                   description="The registered estimators (warpmpm.estimators.ESTIMATORS) of `warpmpm track --estimator`, one "
                   "line each: its name, what it uses, and what it measured (where).")
    v = sub.add_parser("view", help="open, summarise or picture a Rerun recording")
    v.add_argument("rrd")
    v.add_argument("--summary", action="store_true", help="print entities, timelines and counts (no display needed)")
    v.add_argument("--screenshot", metavar="PNG", help="save a picture of the viewer showing the recording (Xvfb when no display)")
    return p
