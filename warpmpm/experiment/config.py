"""What defines one experiment run: :class:`CaseConfig`, checked once when it is built.

A run reads (or generates) a planning case, simulates a pseudo ground truth, drives the model from
one or more slices and scores the estimate beside the baselines. Every choice is typed and checked in
``__post_init__``, so a bad value is an :class:`~warpmpm.errors.InputError` naming the field before
any work is done (``dataclasses.replace`` checks again).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Literal, get_args

from ..errors import InputError
from ..images import PRESETS, parse_organs
from ..slices import parse_slices
from ..solvers import SolverConfig

__all__ = ["Protocol", "TargetKind", "DriveMode", "Lattice", "Baseline", "RunEstimator", "PROTOCOLS", "TARGET_KINDS",
           "DRIVE_MODES", "BASELINES", "RUN_ESTIMATORS", "AUTO_MODES", "MAX_SEED", "CaseConfig"]

Protocol = Literal["paper", "contact", "field"]
TargetKind = Literal["affine", "gt", "gt-inplane", "registration", "registration-affine", "registration-bspline",
                     "registration-demons", "cine"]
DriveMode = Literal["inplane", "pinned"]
Lattice = Literal["auto", "voxel", "isotropic"]
Baseline = Literal["initial", "propagate", "rigid", "volume_registration", "completion", "slice-driven"]
RunEstimator = Literal["copy", "slice-driven"]

PROTOCOLS: tuple[str, ...] = get_args(Protocol)
TARGET_KINDS: tuple[str, ...] = get_args(TargetKind)
DRIVE_MODES: tuple[str, ...] = get_args(DriveMode)
BASELINES: tuple[str, ...] = get_args(Baseline)
RUN_ESTIMATORS: tuple[str, ...] = get_args(RunEstimator)

#: ``--slices`` values that ask the selection models for the condition (see :mod:`warpmpm.experiment.auto`).
AUTO_MODES = {"auto": "a", "auto:a": "a", "auto:ac": "ac", "auto:as": "as", "auto:asc": "asc"}

#: Largest phantom seed accepted: numpy's seed range, less the offsets the protocols add to it.
MAX_SEED = 2**31 - 1 - 100_000


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


@dataclass(frozen=True)
class CaseConfig:
    """Everything that defines one run (the options of ``warpmpm run`` / ``examples/run_case.py``)."""

    image: str | None = None
    """Planning intensity image (NIfTI, MHA/MHD, NRRD or a DICOM folder); needs ``labels``."""
    labels: str | None = None
    """Label map on the image's grid; None: the built-in phantom."""
    preset: str = "amos"
    """Label convention: ``amos``, ``totalseg_ct`` or ``totalseg_mr`` (see :data:`warpmpm.images.PRESETS`)."""
    phantom_seed: int = 0
    """Seed of the phantom's anatomy; also seeds the GT's material perturbation and the contact scenario."""
    phantom_resolution: float = 1.0
    """Phantom voxel-size factor (2: voxels twice as wide, 8x fewer)."""
    organs: str = "psdl"
    """Organ combination in the paper's letters (``p``, ``ps``, ... ``psdl``); the pancreas always."""
    slices: str | None = None
    """Driving slices as ``axial:12,sagittal:40`` (voxel indices of the input volume), an ``auto`` mode,
    or None for the mid-pancreas axial slice."""
    protocol: Protocol = "paper"
    """Ground-truth protocol: the paper's 8 slice affines or contact-driven motion (both simulated by the MPM: regression
    tests of the seed's experiment), or ``field``: a displacement field given as ``truth_field`` (a finite-element truth
    of ``warpmpm make-truth``, or one registered from a 4D scan)."""
    truth_field: str | None = None
    """The truth as a displacement field on the planning grid (:mod:`warpmpm.fields`); needs ``protocol="field"``."""
    deformation: int = 1
    """Paper deformation type 1..8; under ``contact`` it numbers the scenario (>= 1)."""
    targets: TargetKind = "affine"
    """Where the driven particles' targets come from (:mod:`warpmpm.experiment.target_kinds`): the slice affine
    fitted to the GT, the GT's 3D positions (an upper bound no image gives), their in-plane part (the
    ceiling of any 2D registration), or registration of synthetic captured slices (organ-aware, or one
    affine per slice)."""
    cine_thickness_mm: float = 6.0
    """``cine`` targets: the slice thickness (mm) of the captured planes (an MR-Linac's cine: 5-7 mm)."""
    cine_linear_prior: float = 0.0
    """``cine`` targets: the tracker's :attr:`~warpmpm.tracker.TrackerConfig.registration_linear_prior` (the tracker's
    default is 10, for frames 0.1-0.3 s apart). A run's frame jumps from planning to the truth in one step; measured on
    the finite-element truths' frame of largest motion (``benchmarks/registration_ceiling.py``, docs/results.md), the
    prior 10 fails there where 0 does not (CT sample, held-out truth, one sagittal plane: pancreas 20.82 mm against
    1.55, the true in-plane motion's copy 1.57), and the seed's paper protocol scales its planes by 20 %."""
    registration: Literal["itk", "gauss-newton"] = "itk"
    """The slice registration's optimiser for the ``registration*`` targets
    (:func:`warpmpm.registration.register_slices`): ITK's gradient descent or Gauss-Newton, the same correlation
    metric."""
    plane_check: bool = True
    """``registration*`` targets, one registration pass: check each (plane, organ) pair's registered motion against the
    captured planes before it drives anything, and drop the pairs that make the planes match worse
    (:mod:`warpmpm.plane_check`); the ``propagate_planes`` baseline copies the same checked motion."""
    registration_passes: int = 1
    """With several driving planes (``registration*`` targets), how many times the slices are registered: each
    later pass against the planning image moved by the last pass's motion of every particle, all planes combined,
    so motion through one plane that another measured is in its reference; a pass is kept only while the rendered
    planes match the captured ones better (:func:`warpmpm.targets.registration_targets`). 1: once, against the
    planning image. One plane: always once."""
    drive: DriveMode = "pinned"
    """``inplane``: a slice drives only the components in its plane; ``pinned``: also the through-plane
    coordinate (held where it was). ``gt`` targets are always driven in 3D."""
    device: str | None = None
    """Warp device: ``cpu``, ``cuda`` or ``cuda:N``; None: CUDA when available."""
    particle_step: int = 1
    """In-plane particle sampling step (1: one particle per voxel, the paper's choice)."""
    lattice: Lattice = "auto"
    """Where the particles sit: ``voxel`` (one per sampled voxel), ``isotropic`` (a lattice inside the
    interpolated organ shapes, for thick-slice scans), ``auto`` (isotropic when the voxel gaps differ by
    more than 2.5x; see :mod:`warpmpm.model`)."""
    perturb: bool = True
    """Simulate the GT with materials perturbed by up to +-30 % per organ (no inverse crime)."""
    literal: bool = False
    """Read the paper's r, g literally as r/2pi radians instead of degrees."""
    max_steps: int = 6000
    """Steps per estimate before it is reported not converged."""
    wait_settled: bool = False
    """Run each estimate on until the whole model has settled, not only the driven slice
    (:class:`~warpmpm.driving.ConvergenceConfig`)."""
    estimator: RunEstimator = "copy"
    """Which registered estimator (:mod:`warpmpm.estimators`) is ``results.estimate``; each also appears under its own
    name. ``copy`` (default): every organ the planes measured moved by the in-plane motion they show of it (combined over
    the planes), an organ they do not measure by the whole slice's; the measured best: on an independent finite-element
    truth the seed's slice-driven MPM was 1.9-11x the copy's error on every seen organ (31 of 31 organ-runs, true
    in-plane motion given) and the tracker's MPM ends on the copy on every series measured
    (``docs/decisions/2026-12-04-estimators.md``). ``slice-driven``: the seed's MPM driven at the planes' particles, to
    reproduce the paper (``examples/seed_experiment.py``, the sweeps)."""
    materials: str | None = None
    """The estimators' materials (:mod:`warpmpm.materials`: ``paper``, ``tissue`` or a JSON file): the slice-driven
    MPM's (default ``paper``, the seed's) and the completion's (default ``tissue``); None: each its own default. The
    truth keeps its own (the seed's protocols: the paper's table perturbed; a field: whatever made it)."""
    baselines: tuple[Baseline, ...] = ("initial", "propagate", "rigid", "volume_registration", "completion", "slice-driven")
    """Baselines scored beside the estimate (``slice-driven``: the seed's MPM under its own name when it is not the
    estimate)."""
    exclude_driven: bool | None = False
    """Leave the driven particles out of ``error_mm``, p95 and Dice. Default False: every particle of the organ is
    scored, whatever the number of planes (``error_offslice_mm`` always leaves the driven ones out: both are reported).
    None is read as False."""
    rrd_every: int = 20
    """Record particle positions every this many steps (scalars every step)."""
    solver: SolverConfig = field(default_factory=SolverConfig)
    """The estimator's solver settings; the GT refines them (:func:`warpmpm.groundtruth.gt_solver_config`)."""
    gt_contact: Literal["sticky", "sliding"] | None = None
    """Contact between organs in the ground truth; None: the estimator's (``solver.explicit.contact``). A truth with
    sliding organs scored against a sticky estimator (and the reverse) measures what the contact model costs."""

    gt_wait_settled: bool = False
    """Contact protocol: simulate the ground truth until its whole body has settled (an elastic equilibrium, up
    to ``max_steps``; the settled mode of the estimator), instead of stopping when the driven neighbour has
    arrived. The paper protocol drives every particle, so its truth is the same either way."""

    def __post_init__(self):
        if self.labels is None and self.image is not None:
            raise InputError("--image needs --labels (the label map defines the organs)")
        for name in ("image", "labels"):
            path = getattr(self, name)
            if path is not None and not os.path.exists(path):
                raise InputError(f"--{name} file not found: {path}")
            if path is not None and not (os.path.isfile(path) or os.path.isdir(path)):
                raise InputError(f"--{name} {path} is not a regular file (a device or a pipe?); give an image file or a "
                                 "DICOM series folder")
        if isinstance(self.preset, str) and self.preset not in PRESETS:
            raise InputError(f"unknown label preset {self.preset!r}; choose one of {sorted(PRESETS)}")
        if not _is_int(self.phantom_seed) or not (0 <= self.phantom_seed <= MAX_SEED):
            raise InputError(f"phantom seed must be an integer in 0..{MAX_SEED}, got {self.phantom_seed!r}")
        if not (isinstance(self.phantom_resolution, (int, float)) and math.isfinite(self.phantom_resolution)
                and 0.25 <= self.phantom_resolution <= 16):
            raise InputError(f"phantom resolution must be a finite number in 0.25..16, got {self.phantom_resolution!r}")
        from ..registration import BACKENDS

        if self.registration not in BACKENDS:
            raise InputError(f"unknown slice registration backend {self.registration!r}; use {' or '.join(BACKENDS)}")
        from ..targets import MAX_PASSES

        if not _is_int(self.registration_passes) or not (1 <= self.registration_passes <= MAX_PASSES):
            raise InputError(f"--registration-passes must be a whole number from 1 to {MAX_PASSES}, got {self.registration_passes!r}")
        parse_organs(self.organs)
        if self.slices is not None and self.slices != "" and not self.slices.startswith("auto"):
            parse_slices(self.slices)
        elif self.slices is not None and self.slices.startswith("auto") and self.slices not in AUTO_MODES:
            raise InputError(f"unknown --slices {self.slices!r}; use one of {', '.join(AUTO_MODES)}")
        if self.protocol not in PROTOCOLS:
            raise InputError(f"unknown protocol {self.protocol!r}; use {' or '.join(PROTOCOLS)}")
        if (self.protocol == "field") != (self.truth_field is not None):
            raise InputError("--truth-field and --protocol field go together: give the field (the protocol follows), "
                             "or drop --protocol field")
        if self.truth_field is not None and not os.path.exists(self.truth_field):
            raise InputError(f"--truth-field file not found: {self.truth_field}")
        if not _is_int(self.deformation):
            raise InputError(f"deformation must be an integer, got {self.deformation!r}")
        if self.protocol == "paper" and self.deformation not in range(1, 9):
            raise InputError(f"deformation must be 1..8 under the paper protocol, got {self.deformation}")
        if self.protocol == "contact" and not (1 <= self.deformation <= 10_000):
            raise InputError(f"the contact scenario number (--deformation) must be in 1..10000, got {self.deformation}")
        if self.drive not in DRIVE_MODES:
            raise InputError(f"unknown drive mode {self.drive!r}; use {' or '.join(DRIVE_MODES)}")
        if not (isinstance(self.cine_thickness_mm, (int, float)) and math.isfinite(self.cine_thickness_mm)
                and 0.5 <= self.cine_thickness_mm <= 30):
            raise InputError(f"--cine-thickness-mm must be a finite number in 0.5..30, got {self.cine_thickness_mm!r}")
        if not (isinstance(self.cine_linear_prior, (int, float)) and math.isfinite(self.cine_linear_prior)
                and self.cine_linear_prior >= 0):
            raise InputError(f"--cine-linear-prior must be a finite number >= 0, got {self.cine_linear_prior!r}")
        if self.targets not in TARGET_KINDS:
            raise InputError(f"unknown targets {self.targets!r}; use {', '.join(TARGET_KINDS)}")
        if self.device is not None and self.device != "cpu" and not str(self.device).startswith("cuda"):
            raise InputError(f"unknown device {self.device!r}; use cpu or cuda")
        if not _is_int(self.particle_step) or self.particle_step < 1:
            raise InputError(f"particle step must be an integer >= 1, got {self.particle_step!r}")
        if self.lattice not in ("auto", "voxel", "isotropic"):
            raise InputError(f"unknown particle lattice {self.lattice!r}; use auto, voxel or isotropic")
        if self.gt_wait_settled and self.protocol != "contact":
            raise InputError("--gt-wait-settled applies to the contact protocol only: the paper protocol drives every "
                             "particle, so its ground truth has nothing left to settle; drop it or use --protocol contact")
        if self.gt_contact not in (None, "sticky", "sliding"):
            raise InputError(f"unknown ground-truth contact {self.gt_contact!r}; use sticky or sliding")
        if not _is_int(self.max_steps) or self.max_steps < 1:
            raise InputError(f"max steps must be an integer >= 1, got {self.max_steps!r}")
        if self.materials is not None:
            from ..materials import material_table

            material_table(self.materials)
        if self.estimator not in RUN_ESTIMATORS:
            raise InputError(f"unknown estimator {self.estimator!r} for a run; use {' or '.join(RUN_ESTIMATORS)} (the "
                             "completion is the baseline 'completion')")
        bad = [b for b in self.baselines if b not in BASELINES]
        if bad:
            raise InputError(f"unknown baseline(s) {bad}; use {', '.join(BASELINES)}")
        if not _is_int(self.rrd_every) or self.rrd_every < 1:
            raise InputError(f"--rrd-every must be an integer >= 1, got {self.rrd_every!r}")

    @property
    def is_auto(self) -> bool:
        """True when the slices (and organs) are to be chosen by the selection models."""
        return self.slices is not None and self.slices.startswith("auto")
