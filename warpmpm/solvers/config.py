"""The solvers' configurations, units in the field names and a docstring on every field; measured defaults (their
measurements: docs/decisions/2026-12-03-solver-defaults.md).

:class:`SolverConfig` is a small composite: how a frame's equilibrium is found (``method``), the device and threads,
and one config per part: :class:`GridConfig` (the background grid), :class:`ExplicitConfig` (the explicit MLS-MPM
stepper: time step, damping, contact), :class:`QuasiStaticConfig` (the Newton / conjugate-gradient solver) and
:class:`AccelerationConfig` (the rigid-mode acceleration of the explicit relaxation)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from ..errors import InputError

__all__ = ["MIN_LAYERS_PER_CELL", "RIGID_MODE_AGGREGATE_MM", "RIGID_MODE_BASIS", "RIGID_MODE_BASES", "GridConfig",
           "ExplicitConfig", "QuasiStaticConfig", "AccelerationConfig", "SolverConfig"]

#: Fewest particle layers a derived grid cell spans along any axis (``GridConfig.min_layers_per_cell``): with one
#: layer a cell the layers next to a driven slice move in a mode the grid does not see (docs/decisions/2026-12-03-solver-defaults.md).
MIN_LAYERS_PER_CELL = 1.5

#: Edge (mm) of the cubes each organ is cut into for the coarse space of the rigid-mode acceleration
#: (:mod:`warpmpm.solvers.rigid_modes`); measured against whole organs, 40 mm cubes and no acceleration in docs/decisions/2026-12-03-solver-defaults.md.
RIGID_MODE_AGGREGATE_MM = 25.0

#: The motions of each cube of the rigid-mode acceleration's coarse space (``AccelerationConfig.basis``): the 6
#: rigid ones; the 12 affine ones settle in fewer steps at more work a step, within the machine's drift of the same
#: time (docs/decisions/2026-12-03-solver-defaults.md).
RIGID_MODE_BASIS = "rigid"
#: the coarse bases there are
RIGID_MODE_BASES = ("rigid", "affine")


def _finite(owner, name: str, lo: float = 0.0, strict: bool = True, optional: bool = False) -> None:
    v = getattr(owner, name)
    if v is None and optional:
        return
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (v > lo if strict else v >= lo)
    if not ok:
        raise InputError(f"{type(owner).__name__}.{name} must be a finite number {'>' if strict else '>='} {lo:g}, got {v!r}")


@dataclass(frozen=True)
class GridConfig:
    """The background grid (:func:`warpmpm.solvers.grid.grid_layout`)."""

    particles_per_cell: float = 4.0
    """Particles per grid cell used to derive the cell size from the particle volume,
    ``dx = max((ppc * V_p)^(1/3), min_layers_per_cell * largest gap between neighbouring particles)``. 4 keeps more than
    one quadrature point per cell (1 ppc gives MPM's ringing 'null modes') while keeping the cell near the slice
    thickness, so organs closer than about one cell touch through the shared grid."""
    cell_size_mm: float | None = None
    """An explicit grid cell size (mm), overriding ``particles_per_cell``."""
    margin_mm: float = 10.0
    """Free space (mm) around the scene's bounding box (and any extra points given) for motion: the estimate's grid
    already covers the targets and a tracker's whole reach. A particle that would still leave it stops the run with an
    error naming this field."""
    wall_cells: int = 3
    """Thickness of the slip-wall layer at the domain faces, in cells."""
    cell_at_least_gap: bool = True
    """Never make a derived cell smaller than ``min_layers_per_cell`` times the largest gap between neighbouring
    particles, nor an explicit ``cell_size_mm`` smaller than the gap itself (a thick-slice scan must not fall apart into
    sheets). Only a simulation that drives every particle (the ground truth) may turn it off."""
    min_layers_per_cell: float = MIN_LAYERS_PER_CELL
    """With ``cell_at_least_gap``, how many particle layers a derived cell spans at least along every axis (one layer a
    cell leaves a mode the grid does not see). The ground truth's finer grid keeps 1.0."""

    def __post_init__(self):
        _finite(self, "particles_per_cell")
        _finite(self, "cell_size_mm", optional=True)
        _finite(self, "margin_mm", strict=False)
        _finite(self, "min_layers_per_cell", lo=1.0, strict=False)
        if not isinstance(self.wall_cells, int) or self.wall_cells < 1:
            raise InputError(f"GridConfig.wall_cells must be an integer >= 1, got {self.wall_cells!r}")


@dataclass(frozen=True)
class ExplicitConfig:
    """The explicit MLS-MPM stepper (:class:`~warpmpm.solvers.explicit.MPMSolver`): time step, damping, contact."""

    cfl: float = 0.5
    """Courant number of the derived time step ``dt = cfl * dx / c``."""
    cfl_limit: float = 0.6
    """Largest Courant number accepted (for ``cfl`` and a user's ``dt_s``)."""
    dt_s: float | None = None
    """A fixed time step (s); refused when above the stable limit."""
    mass_scaling: bool = True
    """Give every material the stiffest one's wave speed (a fictitious density ``(lambda + 2 mu) / c^2``): the
    equilibrium does not depend on densities, and the soft pancreas then relaxes as fast in steps as the stiffest organ."""
    damping_per_s: float | None = None
    """Grid velocity damping rate (1/s); None derives it from the scene: ``damping_factor * 2 pi c_s / L`` with ``c_s``
    the median (scaled) shear wave speed and ``L`` the scene's size. 0: no damping under every rule."""
    damping_factor: float = 4.0
    """Multiplier of the derived damping (at 1 the slowest mode of the scene stays under-damped)."""
    damping_rule: Literal["auto", "adaptive", "fixed"] = "auto"
    """``"adaptive"``: critical damping of the mode the body is moving in, measured every step from the motion itself
    (the Rayleigh quotient of the stiffness along the particles' velocities,
    :func:`warpmpm.solvers.explicit_kernels.stiffness_rayleigh`), within ``damping_bounds``: the whole body comes to rest
    2.5-8x sooner than with the fixed factor 4. ``"fixed"``: ``damping_per_s`` throughout. ``"auto"``: adaptive when a
    frame waits for the body to settle (``ConvergenceConfig.wait_settled``), fixed when it stops on the driven slice
    alone, where the fixed damping makes the body lag less behind the slice."""
    damping_bounds: tuple[float, float] = (1.0 / 16.0, 16.0)
    """Lowest and highest adaptive damping, as multiples of the derived ``damping_per_s``."""
    damping_memory_steps: float = 10.0
    """Steps over which the adaptive rule averages its Rayleigh quotient."""
    check_every: int | None = None
    """Read the NaN / out-of-grid flag back every this many steps; None: every step on the CPU (free), every 50 on CUDA
    (a read-back synchronises the GPU with the host)."""
    contact: Literal["sticky", "sliding"] = "sticky"
    """How organs that touch interact. ``"sticky"``: one grid velocity field for all, touching organs move together.
    ``"sliding"``: a grid velocity field per organ; where organs meet, motion toward each other along the contact normal
    is removed and tangential motion is free or Coulomb-limited by ``friction``
    (:func:`warpmpm.solvers.explicit_kernels.grid_update_fields`); organs may separate. Costs a grid per organ."""
    friction: float = 0.0
    """Coulomb friction coefficient of ``"sliding"`` contact (0: frictionless)."""
    bonded: tuple[tuple[str, ...], ...] = (("pancreas", "duodenum"),)
    """Groups of organs that stay bonded under ``"sliding"`` contact (one velocity field each group): by default the
    pancreas and the duodenum, whose head sits in the duodenal loop; without any bond a frictionless pancreas pushed by a
    neighbour floats away as a free body. ``()``: every organ slides."""

    def __post_init__(self):
        _finite(self, "cfl_limit")
        _finite(self, "cfl")
        _finite(self, "dt_s", optional=True)
        _finite(self, "damping_per_s", strict=False, optional=True)
        _finite(self, "damping_factor", strict=False)
        _finite(self, "friction", strict=False)
        _finite(self, "damping_memory_steps", lo=1.0, strict=False)
        if self.damping_rule not in ("auto", "adaptive", "fixed"):
            raise InputError(f"ExplicitConfig.damping_rule must be 'auto', 'adaptive' or 'fixed', got {self.damping_rule!r}")
        lo_hi = self.damping_bounds
        if (not isinstance(lo_hi, tuple) or len(lo_hi) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in lo_hi)
                or not 0 < lo_hi[0] <= 1 <= lo_hi[1]):
            raise InputError(f"ExplicitConfig.damping_bounds must be (low, high) with 0 < low <= 1 <= high, got {lo_hi!r}")
        if self.contact not in ("sticky", "sliding"):
            raise InputError(f"ExplicitConfig.contact must be 'sticky' or 'sliding', got {self.contact!r}")
        groups = self.bonded
        if not isinstance(groups, tuple) or not all(isinstance(g, tuple) and all(isinstance(o, str) for o in g) for g in groups):
            raise InputError(f"ExplicitConfig.bonded must be a tuple of tuples of organ names, got {groups!r}")
        named = [o for g in groups for o in g]
        if len(named) != len(set(named)):
            raise InputError(f"ExplicitConfig.bonded names an organ in two groups: {groups!r}")
        if self.cfl_limit > 1.0:
            raise InputError(f"ExplicitConfig.cfl_limit must be at most 1 (explicit MPM is unstable above), got {self.cfl_limit}")
        if self.cfl > self.cfl_limit:
            raise InputError(f"ExplicitConfig.cfl {self.cfl} is above the stable limit cfl_limit {self.cfl_limit}: the time step "
                             f"dt = cfl dx / c would make the simulation blow up; use cfl <= {self.cfl_limit}")
        if self.check_every is not None and (not isinstance(self.check_every, int) or self.check_every < 1):
            raise InputError(f"ExplicitConfig.check_every must be an integer >= 1, got {self.check_every!r}")


@dataclass(frozen=True)
class QuasiStaticConfig:
    """Settings of the quasi-static solve (:mod:`warpmpm.solvers.quasistatic`; ``SolverConfig(method="quasistatic")``)."""

    max_newton_iterations: int = 30
    """Newton iterations before a frame is reported not settled."""
    cg_tolerance: float = 1e-2
    """Relative residual (in the preconditioner's norm) at which each iteration's conjugate-gradient solve stops (an
    inexact Newton step: the next iteration corrects what this one left)."""
    max_cg_iterations: int = 300
    """Conjugate-gradient iterations per Newton iteration at most."""
    penalty: float = 0.09
    """Drive stiffness per driven particle, as a multiple of its own stiffness ``(lambda + 2 mu) V0 4/dx^2``. The
    default 0.09 is the spring of the explicit solver's PD drive (``m Kp`` with its default gains under mass
    scaling: ``0.36 (lambda + 2 mu) V0 / dx^2``), so both solvers seek the same equilibrium (docs/decisions/2026-12-03-solver-defaults.md)."""
    regularization: float = 1e-3
    """Mass-proportional term ``k_reg M`` added to the stiffness, as a multiple of the stiffness scale at a full node
    (an implicit pseudo-time step): a node at a stencil's fringe, which carries little weight, and a part of the body
    nothing holds stay in place instead of making the system singular. It slows the softest modes, never moves the
    equilibrium (docs/decisions/2026-12-03-solver-defaults.md)."""
    settle_mm: float = 0.01
    """Settled when an iteration moves no particle by more than this (mm) and the motion still to come, extrapolated
    from how fast the iterations' moves decay, is below it too (the regularisation slows the softest modes, so a small
    move alone does not mean the body has arrived)."""
    drive_tol_mm: float = 0.02
    """With ``exact_drive``, settled also needs the driven particles' RMS distance to their targets below this (mm)."""
    exact_drive: bool = False
    """Update an augmented-Lagrangian multiplier after every iteration so the driven particles end exactly on their
    targets; False: a pure penalty spring (as the explicit PD drive is one)."""
    max_move_cells: float = 0.5
    """An iteration moves no particle by more than this many cells (a longer step is scaled down)."""
    coarse_modes: Literal["none", "rigid"] = "rigid"
    """Two-level preconditioner: ``"rigid"`` adds a coarse correction over each organ's rigid motions to the Jacobi one
    (the slow modes of a scene whose stiff organs hang on a soft one); ``"none"``: Jacobi alone."""
    auto_newton_iterations: int = 3
    """``SolverConfig(method="auto")``: Newton iterations the quasi-static solve gets before the frame goes on with
    explicit steps from where it stopped (it also stops at the first iteration whose linear solve reaches
    ``auto_max_cg_iterations``): a frame that starts near its equilibrium (a predicted tracker frame) is done at the
    quasi-static price, one that does not costs little more than the explicit steps."""
    auto_max_cg_iterations: int = 40
    """``method="auto"``: conjugate-gradient iterations per Newton iteration before the quasi-static start gives up
    (docs/decisions/2026-12-03-solver-defaults.md)."""
    max_strain_step: float = 0.2
    """... and changes no particle's deformation by more than this (Frobenius norm of the displacement gradient of
    the step): the small-strain stiffness is the Hessian at rest, so a longer step could invert an element."""

    def __post_init__(self):
        for name in ("max_newton_iterations", "max_cg_iterations", "auto_newton_iterations", "auto_max_cg_iterations"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise InputError(f"QuasiStaticConfig.{name} must be a positive integer, got {v!r}")
        for name in ("cg_tolerance", "penalty", "regularization", "settle_mm", "drive_tol_mm", "max_move_cells", "max_strain_step"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                raise InputError(f"QuasiStaticConfig.{name} must be a finite number > 0, got {v!r}")
        if self.coarse_modes not in ("none", "rigid"):
            raise InputError(f"QuasiStaticConfig.coarse_modes must be 'none' or 'rigid', got {self.coarse_modes!r}")
        if self.cg_tolerance >= 1:
            raise InputError(f"QuasiStaticConfig.cg_tolerance must be below 1, got {self.cg_tolerance}")


@dataclass(frozen=True)
class AccelerationConfig:
    """The rigid-mode acceleration of the explicit relaxation (:mod:`warpmpm.solvers.rigid_modes`): a coarse level over
    organ cubes whose slow modes (stiff organs swinging on the soft pancreas, as heavy as they are stiff under mass
    scaling) are accelerated to the body's slowest deformation; the equilibrium is unchanged, the step stays stable. It
    starts once the driven slice has arrived, and a guard switches it off where it grows unstable
    (``DriveResult.acceleration``). Sticky contact only."""

    mode: Literal["auto", "on", "off"] = "auto"
    """``"auto"``: on when a frame waits for the body to settle (``ConvergenceConfig.wait_settled``) and the contact is
    sticky; ``"on"``: also when a frame stops on the driven slice alone; ``"off"``: never."""
    aggregate_mm: float | None = RIGID_MODE_AGGREGATE_MM
    """Edge (mm) of the cubes each organ is cut into; None: whole organs (smaller cubes: fewer steps, a longer set-up
    and more work a step)."""
    basis: Literal["rigid", "affine"] = RIGID_MODE_BASIS
    """The motions of each cube: ``"rigid"`` (6) or ``"affine"`` (12: also stretches and shears)."""

    def __post_init__(self):
        _finite(self, "aggregate_mm", optional=True)
        if self.basis not in RIGID_MODE_BASES:
            raise InputError(f"AccelerationConfig.basis must be one of {', '.join(RIGID_MODE_BASES)}, got {self.basis!r}")
        if self.mode not in ("auto", "on", "off"):
            raise InputError(f"AccelerationConfig.mode must be 'auto', 'on' or 'off', got {self.mode!r}")


#: the flat keywords of the SolverConfig before it became a composite, and where each lives now
_MOVED = {**{k: f"GridConfig({k}=...)" for k in ("particles_per_cell", "cell_size_mm", "margin_mm", "wall_cells",
                                                  "cell_at_least_gap", "min_layers_per_cell")},
          **{k: f"ExplicitConfig({k}=...)" for k in ("cfl", "cfl_limit", "dt_s", "mass_scaling", "damping_per_s", "damping_factor",
                                                      "damping_rule", "damping_bounds", "damping_memory_steps", "check_every",
                                                      "contact", "friction", "bonded")},
          "rigid_mode_acceleration": "AccelerationConfig(mode=...)", "rigid_mode_aggregate_mm": "AccelerationConfig(aggregate_mm=...)",
          "rigid_mode_basis": "AccelerationConfig(basis=...)"}


class _NamesMovedFields(type):
    """Builds a SolverConfig, refusing a keyword of the flat config it was with the place the setting has now."""

    def __call__(cls, *args, **kwargs):
        moved = [k for k in kwargs if k in _MOVED]
        if moved:
            where = {"GridConfig": "grid", "ExplicitConfig": "explicit", "AccelerationConfig": "acceleration"}
            raise InputError("SolverConfig is a composite now: " + "; ".join(
                f"{k} -> SolverConfig({where[_MOVED[k].split('(')[0]]}={_MOVED[k]})" for k in moved))
        return super().__call__(*args, **kwargs)


@dataclass(frozen=True)
class SolverConfig(metaclass=_NamesMovedFields):
    """How a frame's equilibrium is found, on which device, and each part's settings."""

    method: Literal["explicit", "quasistatic", "auto"] = "explicit"
    """``"explicit"``: dynamic relaxation by explicit MLS-MPM steps under the PID drive, stopped by
    :class:`~warpmpm.solvers.convergence.ConvergenceConfig` (the paper's method). ``"quasistatic"``: Newton iterations
    with a matrix-free conjugate gradient on the same grid (:mod:`warpmpm.solvers.quasistatic`): the settled equilibrium
    directly. ``"auto"``: those iterations first, for at most ``QuasiStaticConfig.auto_newton_iterations``, and explicit
    steps from where they stopped when the frame has not settled (the tracker's default: a predicted frame starts in
    equilibrium). Both but the first handle sticky contact only."""
    grid: GridConfig = field(default_factory=GridConfig)
    """The background grid."""
    explicit: ExplicitConfig = field(default_factory=ExplicitConfig)
    """The explicit stepper: time step, damping, contact."""
    quasistatic: QuasiStaticConfig = field(default_factory=QuasiStaticConfig)
    """The Newton / conjugate-gradient solver (``method`` ``"quasistatic"`` or ``"auto"``)."""
    acceleration: AccelerationConfig = field(default_factory=AccelerationConfig)
    """The rigid-mode acceleration of the explicit relaxation."""
    device: str | None = None
    """Warp device (``"cpu"``, ``"cuda"``, ``"cuda:0"``); None: CUDA when available."""
    cpu_threads: int | None = None
    """On the CPU, threads an explicit step splits its particle and grid kernels over, and the quasi-static solver its
    particle kernels (:mod:`warpmpm.solvers.parallel`: each thread scatters into a grid copy of its own). None: the
    environment variable ``WARPMPM_CPU_THREADS`` when set, else every core this process may use, at most 2; 1: the
    single-core path. Ignored on CUDA and inside a graph capture. The answers agree with one thread to float32 rounding."""

    def __post_init__(self):
        for name, cls in (("grid", GridConfig), ("explicit", ExplicitConfig), ("quasistatic", QuasiStaticConfig),
                          ("acceleration", AccelerationConfig)):
            if not isinstance(getattr(self, name), cls):
                raise InputError(f"SolverConfig.{name} must be a {cls.__name__}, got {type(getattr(self, name)).__name__}")
        if self.method not in ("explicit", "quasistatic", "auto"):
            raise InputError(f"SolverConfig.method must be 'explicit', 'quasistatic' or 'auto', got {self.method!r}")
        if self.method in ("quasistatic", "auto") and self.explicit.contact != "sticky":
            raise InputError(f"SolverConfig.method {self.method!r} handles sticky contact only; use ExplicitConfig(contact='sticky') "
                             "or the explicit method")
        if self.acceleration.mode == "on" and self.explicit.contact != "sticky":
            raise InputError("AccelerationConfig.mode 'on' handles sticky contact only (one grid field); use "
                             "ExplicitConfig(contact='sticky') or AccelerationConfig(mode='auto' / 'off')")
        if self.cpu_threads is not None and (not isinstance(self.cpu_threads, int) or isinstance(self.cpu_threads, bool)
                                             or not 1 <= self.cpu_threads <= 64):
            raise InputError(f"SolverConfig.cpu_threads must be an integer from 1 to 64 (or None: the machine's cores, at most 2), "
                             f"got {self.cpu_threads!r}")
