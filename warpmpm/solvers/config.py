"""The solvers' configurations: :class:`SolverConfig` (the explicit stepper, the choice of method, the rigid-mode
acceleration, threads) and :class:`QuasiStaticConfig` (the Newton / conjugate-gradient solver), with units in the field
names and the measured defaults (their measurements: docs/decisions/2026-12-03-solver-defaults.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from ..errors import InputError

__all__ = ["QuasiStaticConfig", "MIN_LAYERS_PER_CELL", "RIGID_MODE_AGGREGATE_MM", "RIGID_MODE_BASIS",
           "RIGID_MODE_BASES", "SolverConfig"]


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


#: Fewest particle layers a derived grid cell spans along any axis (``SolverConfig.min_layers_per_cell``): with one
#: layer a cell the layers next to a driven slice move in a mode the grid does not see (docs/decisions/2026-12-03-solver-defaults.md).
MIN_LAYERS_PER_CELL = 1.5

#: Edge (mm) of the cubes each organ is cut into for the coarse space of the rigid-mode acceleration
#: (:mod:`warpmpm.solvers.rigid_modes`); measured against whole organs, 40 mm cubes and no acceleration in docs/decisions/2026-12-03-solver-defaults.md.
RIGID_MODE_AGGREGATE_MM = 25.0

#: The motions of each cube of the rigid-mode acceleration's coarse space (``SolverConfig.rigid_mode_basis``): the 6
#: rigid ones; the 12 affine ones settle in fewer steps at more work a step, within the machine's drift of the same
#: time (docs/decisions/2026-12-03-solver-defaults.md).
RIGID_MODE_BASIS = "rigid"
#: the coarse bases there are
RIGID_MODE_BASES = ("rigid", "affine")


@dataclass(frozen=True)
class SolverConfig:
    """Solver settings (physical units in the names).

    Attributes:
        particles_per_cell: particles per grid cell used to derive the cell size from the particle
            volume, ``dx = max((ppc * V_p)^(1/3), min_layers_per_cell * largest gap between neighbouring particles)``
            (a thick-slice scan must not fall apart into sheets, and no axis may hold one particle layer a cell).
            The default 4 keeps more than one quadrature point per cell (1 ppc gives the ringing 'null modes' of
            MPM) while keeping the cell near the slice thickness, so organs closer than about one cell touch
            through the shared grid.
        cell_size_mm: explicit grid cell size (overrides ``particles_per_cell``).
        margin_mm: free space around the scene's bounding box (and any extra points given) for motion.
            Default 10 mm: the estimate's grid already covers the targets (and a tracker's whole reach)
            (docs/decisions/2026-12-03-solver-defaults.md). A particle that would still leave it stops the run with an error naming this field.
        wall_cells: thickness of the slip-wall layer at the domain faces, in cells.
        cfl: Courant number of the derived time step ``dt = cfl * dx / c``. Default 0.5 (docs/decisions/2026-12-03-solver-defaults.md).
        cfl_limit: largest Courant number accepted for a user time step.
        dt_s: fixed time step (s); refused when above the stable limit.
        mass_scaling: give all materials the stiffest one's wave speed (see module docstring).
        damping_per_s: grid velocity damping rate (1/s); None derives it from the scene:
            ``damping_factor * 2 pi c_s / L`` with ``c_s`` the median (scaled) shear wave speed and ``L``
            the scene's size.
        damping_factor: multiplier of the derived damping. Default 4: at 1 the slowest mode of the
            scene stays under-damped (docs/decisions/2026-12-03-solver-defaults.md).
        damping_rule: ``"adaptive"``: critical damping of the mode the body is moving in, measured every step
            from the motion itself (adaptive dynamic relaxation: the Rayleigh quotient of the stiffness along the
            particles' velocities, :func:`warpmpm.solvers.explicit_kernels.stiffness_rayleigh`), within ``damping_bounds``; the
            derived ``damping_per_s`` is the first step's value and the bounds' unit. It brings the whole body to
            rest 2.5-8x sooner than the fixed factor 4. ``"fixed"``: ``damping_per_s`` throughout. ``"auto"`` (default): adaptive
            when a frame waits for the body to settle (``ConvergenceConfig.wait_settled``), fixed when it stops on
            the driven slice alone, where the fixed damping makes the body lag less behind the slice (docs/decisions/2026-12-03-solver-defaults.md).
            ``damping_per_s`` 0 means no damping under every rule.
        damping_bounds: lowest and highest adaptive damping, as multiples of the derived ``damping_per_s``.
        damping_memory_steps: steps over which the adaptive rule averages its Rayleigh quotient.
        device: Warp device (``"cpu"``, ``"cuda"``, ``"cuda:0"``); None: CUDA when available.
        check_every: read the NaN / out-of-grid flag back every this many steps; None: every step on
            the CPU (free), every 50 on CUDA (a read-back synchronises the GPU with the host).
        contact: how organs that touch interact. ``"sticky"`` (default): one grid velocity field for all, so
            touching organs move together (no sliding, no separation). ``"sliding"``: each organ has its own
            grid velocity field; where organs meet, motion toward each other along the contact normal is
            removed and tangential motion is free or Coulomb-limited by ``friction`` (multi-velocity-field
            MPM: :func:`warpmpm.solvers.explicit_kernels.grid_update_fields`); organs may separate. Costs a grid per organ.
        friction: Coulomb friction coefficient of ``"sliding"`` contact (0: frictionless).
        bonded: groups of organs that stay bonded under ``"sliding"`` contact (they share one velocity
            field). Default: the pancreas and the duodenum, whose head sits in the duodenal loop with shared
            vessels and ducts; without any bond nothing tethers the pancreas in this model (it has no
            retroperitoneum), and a frictionless pancreas pushed by a neighbour floats away as a free body
            (docs/decisions/2026-12-03-solver-defaults.md). ``()``: every organ slides.
        cell_at_least_gap: never make a derived cell smaller than ``min_layers_per_cell`` times the largest gap
            between neighbouring particles, nor an explicit ``cell_size_mm`` smaller than the gap itself (default).
            Only a simulation that drives every particle (the ground truth) may turn it off: its layers are held by
            their targets, not by each other.
        min_layers_per_cell: with ``cell_at_least_gap``, how many particle layers a derived cell spans at least along
            every axis. Default :data:`MIN_LAYERS_PER_CELL` (1.5; one layer a cell leaves a mode the grid does not
            see). The ground truth's finer grid keeps 1.0.
        method: how a frame's equilibrium is found. ``"explicit"`` (default): dynamic relaxation by explicit MLS-MPM
            steps under the PID drive, stopped by :class:`warpmpm.driving.ConvergenceConfig` (the paper's method).
            ``"quasistatic"``: Newton iterations with a matrix-free conjugate-gradient solve on the same grid
            (:mod:`warpmpm.solvers.quasistatic`): the settled equilibrium directly, in a fraction of the time the explicit
            solver needs to wait for it; sticky contact only. ``"auto"``: the quasi-static
            solve first, for at most ``QuasiStaticConfig.auto_newton_iterations``; a frame it has not settled by then
            goes on with explicit steps from there (the result's ``method`` says which finished it). The tracker's
            default, where a predicted frame starts in equilibrium; sticky contact only.
        quasistatic: settings of the ``"quasistatic"`` method.
        rigid_mode_acceleration: a coarse level for the explicit relaxation (:mod:`warpmpm.solvers.rigid_modes`): each organ's
            six rigid motions, whose coarse modes slower than the body's slowest deformation are accelerated to it
            (a two-level mass matrix; the equilibrium is unchanged, the step stays stable). Mass scaling makes the
            stiff organs (duodenum, stomach: up to 2,900x the pancreas's modulus) as heavy as they are stiff, and
            their rigid swings on the soft pancreas are what keeps a whole abdomen from settling.
            ``"auto"`` (default): on when a frame waits for the body to settle (``ConvergenceConfig.wait_settled``) and
            the contact is sticky; ``"on"``: also when a frame stops on the driven slice alone (sticky contact only);
            ``"off"``: never. The coarse space: 25 mm cubes of each organ (``rigid_mode_aggregate_mm``); it starts once
            the driven slice has arrived, and a guard switches it off where it grows unstable (``DriveResult.acceleration``).
            The default phantom settles in 1,700 steps instead of not within 8,000 (docs/decisions/2026-12-03-solver-defaults.md).
        rigid_mode_aggregate_mm: edge (mm) of the cubes each organ is cut into for the rigid-mode acceleration; None:
            whole organs. Default :data:`RIGID_MODE_AGGREGATE_MM` (smaller cubes: fewer steps, a longer set-up per frame
            and more work a step).
        rigid_mode_basis: the motions of each cube in that coarse space: ``"rigid"`` (6: translations and rotations)
            or ``"affine"`` (12: also stretches and shears, so the soft tissue between cubes can shear in the coarse
            space: fewer steps, more work a step). Default :data:`RIGID_MODE_BASIS` (docs/decisions/2026-12-03-solver-defaults.md).
        cpu_threads: on the CPU, threads an explicit step splits its particle and grid kernels over, and the
            quasi-static solver its particle kernels
            (:mod:`warpmpm.solvers.parallel`: Warp runs each CPU launch on one core, and launches over disjoint
            particle ranges from several threads run at once; each thread scatters into a grid copy of its
            own). None (default): the environment variable ``WARPMPM_CPU_THREADS`` when set, else every core
            this process may use, at most 2 (docs/decisions/2026-12-03-solver-defaults.md); 1: one launch per kernel, the single-core path. Ignored on CUDA and inside a graph capture. The answers agree with one thread
            to float32 rounding (the grid's sums are added in another order), not bit for bit.
    """

    particles_per_cell: float = 4.0
    cell_size_mm: float | None = None
    margin_mm: float = 10.0
    wall_cells: int = 3
    cfl: float = 0.5
    cfl_limit: float = 0.6
    dt_s: float | None = None
    mass_scaling: bool = True
    damping_per_s: float | None = None
    damping_factor: float = 4.0
    damping_rule: Literal["auto", "adaptive", "fixed"] = "auto"
    damping_bounds: tuple[float, float] = (1.0 / 16.0, 16.0)
    damping_memory_steps: float = 10.0
    device: str | None = None
    check_every: int | None = None
    cell_at_least_gap: bool = True
    min_layers_per_cell: float = MIN_LAYERS_PER_CELL
    contact: Literal["sticky", "sliding"] = "sticky"
    friction: float = 0.0
    bonded: tuple[tuple[str, ...], ...] = (("pancreas", "duodenum"),)
    method: Literal["explicit", "quasistatic", "auto"] = "explicit"
    quasistatic: QuasiStaticConfig = QuasiStaticConfig()
    rigid_mode_acceleration: Literal["auto", "on", "off"] = "auto"
    rigid_mode_aggregate_mm: float | None = RIGID_MODE_AGGREGATE_MM
    rigid_mode_basis: Literal["rigid", "affine"] = RIGID_MODE_BASIS
    cpu_threads: int | None = None

    def __post_init__(self):
        def finite(name, lo=0.0, strict=True, optional=False):
            v = getattr(self, name)
            if v is None and optional:
                return
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (v > lo if strict else v >= lo)
            if not ok:
                raise InputError(f"SolverConfig.{name} must be a finite number {'>' if strict else '>='} {lo:g}, got {v!r}")

        finite("particles_per_cell")
        finite("cell_size_mm", optional=True)
        finite("margin_mm", strict=False)
        finite("cfl_limit")
        finite("cfl")
        finite("dt_s", optional=True)
        finite("damping_per_s", strict=False, optional=True)
        finite("damping_factor", strict=False)
        finite("friction", strict=False)
        finite("min_layers_per_cell", lo=1.0, strict=False)
        finite("rigid_mode_aggregate_mm", optional=True)
        if self.damping_rule not in ("auto", "adaptive", "fixed"):
            raise InputError(f"SolverConfig.damping_rule must be 'auto', 'adaptive' or 'fixed', got {self.damping_rule!r}")
        lo_hi = self.damping_bounds
        if (not isinstance(lo_hi, tuple) or len(lo_hi) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in lo_hi)
                or not 0 < lo_hi[0] <= 1 <= lo_hi[1]):
            raise InputError(f"SolverConfig.damping_bounds must be (low, high) with 0 < low <= 1 <= high, got {lo_hi!r}")
        finite("damping_memory_steps", lo=1.0, strict=False)
        if self.method not in ("explicit", "quasistatic", "auto"):
            raise InputError(f"SolverConfig.method must be 'explicit', 'quasistatic' or 'auto', got {self.method!r}")
        if not isinstance(self.quasistatic, QuasiStaticConfig):
            raise InputError(f"SolverConfig.quasistatic must be a QuasiStaticConfig, got {type(self.quasistatic).__name__}")
        if self.method in ("quasistatic", "auto") and self.contact != "sticky":
            raise InputError(f"SolverConfig.method {self.method!r} handles sticky contact only; use contact='sticky' or the explicit method")
        if self.contact not in ("sticky", "sliding"):
            raise InputError(f"SolverConfig.contact must be 'sticky' or 'sliding', got {self.contact!r}")
        if self.rigid_mode_basis not in RIGID_MODE_BASES:
            raise InputError(f"SolverConfig.rigid_mode_basis must be one of {', '.join(RIGID_MODE_BASES)}, got {self.rigid_mode_basis!r}")
        if self.rigid_mode_acceleration not in ("auto", "on", "off"):
            raise InputError(f"SolverConfig.rigid_mode_acceleration must be 'auto', 'on' or 'off', got {self.rigid_mode_acceleration!r}")
        if self.rigid_mode_acceleration == "on" and self.contact != "sticky":
            raise InputError("SolverConfig.rigid_mode_acceleration 'on' handles sticky contact only (one grid field); "
                             "use contact='sticky' or rigid_mode_acceleration='auto' / 'off'")
        groups = self.bonded
        if not isinstance(groups, tuple) or not all(isinstance(g, tuple) and all(isinstance(o, str) for o in g) for g in groups):
            raise InputError(f"SolverConfig.bonded must be a tuple of tuples of organ names, got {groups!r}")
        named = [o for g in groups for o in g]
        if len(named) != len(set(named)):
            raise InputError(f"SolverConfig.bonded names an organ in two groups: {groups!r}")
        if self.cfl_limit > 1.0:
            raise InputError(f"SolverConfig.cfl_limit must be at most 1 (explicit MPM is unstable above), got {self.cfl_limit}")
        if self.cfl > self.cfl_limit:
            raise InputError(f"SolverConfig.cfl {self.cfl} is above the stable limit cfl_limit {self.cfl_limit}: the time step "
                             f"dt = cfl dx / c would make the simulation blow up; use cfl <= {self.cfl_limit}")
        if not isinstance(self.wall_cells, int) or self.wall_cells < 1:
            raise InputError(f"SolverConfig.wall_cells must be an integer >= 1, got {self.wall_cells!r}")
        if self.check_every is not None and (not isinstance(self.check_every, int) or self.check_every < 1):
            raise InputError(f"SolverConfig.check_every must be an integer >= 1, got {self.check_every!r}")
        if self.cpu_threads is not None and (not isinstance(self.cpu_threads, int) or isinstance(self.cpu_threads, bool)
                                             or not 1 <= self.cpu_threads <= 64):
            raise InputError(f"SolverConfig.cpu_threads must be an integer from 1 to 64 (or None: the machine's cores, at most 2), "
                             f"got {self.cpu_threads!r}")
