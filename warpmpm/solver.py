"""The MPM solver: a static :class:`MPMModel` built once from a particle model, a :class:`State`
that changes, and :class:`MPMSolver` that steps ``state_in -> state_out`` under an external force.

Layout follows the Newton physics engine: ``solver.step(state_in, state_out, control)`` where the
control is the per-particle external (driving) force in newtons.

Public values are physical: positions in mm (world coordinates), time steps in s, stresses in Pa,
densities in kg/m^3. Inside, kernels work in SI with positions relative to the grid origin.

Quasi-static relaxation
-----------------------
The estimate is an equilibrium, not a trajectory: with no body forces the converged positions do
not depend on the densities. ``mass_scaling`` (default on) therefore gives every material a
fictitious density ``rho = (lambda + 2 mu) / c_ref^2`` so that all organs share the wave speed
``c_ref`` of the stiffest organ: the time step stays the one the stiffest organ needs, and the soft
pancreas relaxes ~70x faster in steps than with its real density. Grid velocities are damped by a
factor ``exp(-damping_per_s * dt)`` every step (viscous damping toward rest, which does not change
the equilibrium); the default damping (``damping_factor`` 4 times ``2 pi c_s / L``) was chosen by
measurement to remove the slow swing of the least-damped mode without slowing convergence, at the
paper's stopping rule. A frame that waits for the whole body to settle damps adaptively instead
(``damping_rule``): the rate is made critical for the mode the body is moving in, measured every step
(:func:`warpmpm.kernels.stiffness_rayleigh`), which brings the body to rest 2.5-8x sooner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import warp as wp

from . import kernels, parallel
from .errors import InputError, SimulationError
from .model import ParticleModel

__all__ = ["QuasiStaticConfig", "MIN_LAYERS_PER_CELL", "RIGID_MODE_AGGREGATE_MM", "RIGID_MODE_BASIS",
           "RIGID_MODE_BASES", "SolverConfig", "RAYLEIGH_SLOTS", "BYTES_PER_PARTICLE", "BYTES_PER_NODE",
           "BYTES_PER_NODE_COPY", "grid_layout", "memory_estimate_bytes", "cpu_threads", "default_device", "MPMModel",
           "State", "MPMSolver"]


@dataclass(frozen=True)
class QuasiStaticConfig:
    """Settings of the quasi-static solve (:mod:`warpmpm.quasistatic`; ``SolverConfig(method="quasistatic")``)."""

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
#: (:mod:`warpmpm.rigid_modes`); measured against whole organs, 40 mm cubes and no acceleration in docs/decisions/2026-12-03-solver-defaults.md.
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
            particles' velocities, :func:`warpmpm.kernels.stiffness_rayleigh`), within ``damping_bounds``; the
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
            MPM: :func:`warpmpm.kernels.grid_update_fields`); organs may separate. Costs a grid per organ.
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
            (:mod:`warpmpm.quasistatic`): the settled equilibrium directly, in a fraction of the time the explicit
            solver needs to wait for it; sticky contact only. ``"auto"``: the quasi-static
            solve first, for at most ``QuasiStaticConfig.auto_newton_iterations``; a frame it has not settled by then
            goes on with explicit steps from there (the result's ``method`` says which finished it). The tracker's
            default, where a predicted frame starts in equilibrium; sticky contact only.
        quasistatic: settings of the ``"quasistatic"`` method.
        rigid_mode_acceleration: a coarse level for the explicit relaxation (:mod:`warpmpm.rigid_modes`): each organ's
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
            (:mod:`warpmpm.parallel`: Warp runs each CPU launch on one core, and launches over disjoint
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


#: Slots the adaptive damping's sums are spread over (by particle index): fewer atomics on one address on a GPU.
RAYLEIGH_SLOTS = 64

#: Bytes per particle of a step (two states of x, v, C, F; mass, volume, Lame; force) and per grid node (mass and
#: momentum, 16, in each thread's copy; velocity, 12).
BYTES_PER_PARTICLE = 220
BYTES_PER_NODE = 28
BYTES_PER_NODE_COPY = 16


def grid_layout(particles: ParticleModel, config: SolverConfig, extra_points_mm: np.ndarray | None = None):
    """``(dx_mm, origin_mm, grid_shape)`` of the background grid: the cell from the particle volume
    (never smaller than ``min_layers_per_cell`` times the largest gap between neighbouring particles), the box of
    the particles and ``extra_points_mm`` plus ``margin_mm`` and the wall layer."""
    cfg = config
    if particles.n == 0:
        raise InputError("the particle model is empty")
    gap = particles.max_gap_mm if cfg.cell_at_least_gap else 0.0
    if cfg.cell_size_mm:
        if cfg.cell_size_mm < gap * (1 - 1e-9):
            raise InputError(f"grid cell {cfg.cell_size_mm} mm is smaller than the {gap:.2f} mm gap between neighbouring "
                             "particles: the particle layers would not share grid nodes and would move apart; "
                             f"use cell_size_mm >= {gap:.2f}")
        dx = float(cfg.cell_size_mm)
    else:
        # the particle layers must share grid nodes (thick slices), and no axis may hold one layer a cell (null modes)
        dx = max(float((cfg.particles_per_cell * np.median(particles.volume_mm3)) ** (1 / 3)), cfg.min_layers_per_cell * gap)
    pts = particles.positions_mm
    if extra_points_mm is not None and len(extra_points_mm):
        extra = np.asarray(extra_points_mm, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(extra)):
            bad = int(np.nonzero(~np.all(np.isfinite(extra), axis=1))[0][0])
            raise InputError(f"extra_points_mm holds a non-finite value (point {bad}); the grid must cover finite positions")
        pts = np.vstack([pts, extra])
    lo = pts.min(axis=0) - cfg.margin_mm
    hi = pts.max(axis=0) + cfg.margin_mm
    pad = (cfg.wall_cells + 2) * dx
    # nodes at whole multiples of dx in world mm: the margin (and the extra points) set how far the grid
    # reaches, never where its nodes lie, so they cannot change the answer (a half-cell shift did by 4-12 %)
    origin = np.floor((lo - pad) / dx) * dx
    shape = tuple(int(v) for v in np.ceil((hi + pad - origin) / dx) + 1)
    return dx, origin, shape


def memory_estimate_bytes(n_particles: int, grid_shape, grid_copies: int = 1) -> int:
    """Memory of one simulation (particles and grid), from :data:`BYTES_PER_PARTICLE` and :data:`BYTES_PER_NODE`;
    ``grid_copies``: the threads of a split CPU step, each scattering into a copy of the grid's mass and momentum."""
    nodes = int(np.prod(grid_shape))
    return int(n_particles * BYTES_PER_PARTICLE + nodes * (BYTES_PER_NODE + (max(1, grid_copies) - 1) * BYTES_PER_NODE_COPY))


def cpu_threads(config: SolverConfig, device) -> int:
    """Threads an explicit step of ``config`` runs on ``device``: 1 on CUDA, else ``config.cpu_threads`` or
    :func:`warpmpm.parallel.default_threads` (:attr:`SolverConfig.cpu_threads`)."""
    if str(device).startswith("cuda"):
        return 1
    return config.cpu_threads if config.cpu_threads is not None else parallel.default_threads()


def default_device() -> str:
    wp.init()
    return "cuda" if wp.is_cuda_available() else "cpu"


class MPMModel:
    """Static simulation data: per-particle material, mass and volume; grid geometry; time step.

    Attributes:
        dx_mm: grid cell size (mm); grid_shape: nodes along x, y, z; origin_mm: world position
        of node (0, 0, 0); dt_s, dt_limit_s: time step and its stable limit (s);
        wave_speed_m_s: the (scaled) wave speed that sets the time step; damping_per_s.
    """

    def __init__(self, particles: ParticleModel, config: SolverConfig | None = None, extra_points_mm: np.ndarray | None = None):
        cfg = config or SolverConfig()
        self.config = cfg
        self.particles = particles
        self.device = cfg.device or default_device()
        vol_mm3 = particles.volume_mm3.astype(np.float64)
        self.dx_mm, self.origin_mm, self.grid_shape = grid_layout(particles, cfg, extra_points_mm)

        lam = particles.per_particle("lam_pa")
        mu = particles.per_particle("mu_pa")
        rho = particles.per_particle("density_kg_m3")
        modulus = lam + 2 * mu
        real_speed = np.sqrt(modulus / rho)
        self.real_wave_speed_m_s = float(real_speed.max())
        if cfg.mass_scaling:
            rho_eff = modulus / self.real_wave_speed_m_s**2
        else:
            rho_eff = rho
        self.density_kg_m3 = rho_eff
        self.wave_speed_m_s = float(np.sqrt(modulus / rho_eff).max())
        dx_m = self.dx_mm * 1e-3
        self.dt_limit_s = cfg.cfl_limit * dx_m / self.wave_speed_m_s
        if cfg.dt_s is not None:
            if not (cfg.dt_s > 0 and math.isfinite(cfg.dt_s)):
                raise InputError(f"time step must be a positive finite number, got {cfg.dt_s}")
            if cfg.dt_s > self.dt_limit_s:
                raise InputError(
                    f"time step {cfg.dt_s:.3e} s is above the stable limit {self.dt_limit_s:.3e} s "
                    f"(CFL {cfg.cfl_limit} x dx {self.dx_mm:.2f} mm / wave speed {self.wave_speed_m_s:.1f} m/s)"
                )
            self.dt_s = float(cfg.dt_s)
        else:
            self.dt_s = cfg.cfl * dx_m / self.wave_speed_m_s
        if cfg.damping_per_s is None:
            # Slowest shear mode of the scene: omega ~ pi c_s / L, with the smallest scaled shear speed.
            c_shear = np.sqrt(mu / rho_eff)
            size_m = float(np.max(particles.positions_mm.max(0) - particles.positions_mm.min(0))) * 1e-3
            if not (cfg.damping_factor >= 0 and math.isfinite(cfg.damping_factor)):
                raise InputError(f"damping_factor must be a finite number >= 0, got {cfg.damping_factor}")
            self.damping_per_s = float(cfg.damping_factor * 2.0 * math.pi * np.median(c_shear) / max(size_m, 10 * dx_m))
        else:
            if cfg.damping_per_s < 0:
                raise InputError(f"damping must be >= 0 1/s, got {cfg.damping_per_s}")
            self.damping_per_s = float(cfg.damping_per_s)

        mass = rho_eff * vol_mm3 * 1e-9
        self.mass_kg = mass
        d = self.device
        self.mass = wp.array(mass.astype(np.float32), dtype=float, device=d)
        self.vol0 = wp.array((vol_mm3 * 1e-9).astype(np.float32), dtype=float, device=d)
        self.mu = wp.array(mu.astype(np.float32), dtype=float, device=d)
        self.lam = wp.array(lam.astype(np.float32), dtype=float, device=d)
        #: grid velocity fields: one per organ with sliding contact, one shared with sticky contact
        field_of_organ = np.zeros(len(particles.organs), dtype=np.int32)
        if cfg.contact == "sliding":
            group_of = {o: gi for gi, g in enumerate(cfg.bonded) for o in g}
            keys = [("bond", group_of[o]) if o in group_of else ("organ", o) for o in particles.organs]
            ids = {k: i for i, k in enumerate(dict.fromkeys(keys))}
            field_of_organ = np.array([ids[k] for k in keys], dtype=np.int32)
        self.n_fields = int(field_of_organ.max()) + 1
        self.field = wp.array(field_of_organ[particles.organ_index], dtype=int, device=d)

    @property
    def n(self) -> int:
        return self.particles.n

    def to_local_m(self, world_mm: np.ndarray) -> np.ndarray:
        return ((np.asarray(world_mm, dtype=np.float64) - self.origin_mm) * 1e-3).astype(np.float32)

    def to_world_mm(self, local_m: np.ndarray) -> np.ndarray:
        return np.asarray(local_m, dtype=np.float64) * 1e3 + self.origin_mm

    def state(self, positions_mm: np.ndarray | None = None) -> "State":
        """A state at rest (F = I, v = 0) at the planning positions or at ``positions_mm``."""
        pos = self.particles.positions_mm if positions_mm is None else positions_mm
        return State(self, pos)

    def summary(self) -> dict:
        return {
            "n_particles": self.n,
            "dx_mm": self.dx_mm,
            "grid_shape": list(self.grid_shape),
            "dt_s": self.dt_s,
            "dt_limit_s": self.dt_limit_s,
            "wave_speed_m_s": self.wave_speed_m_s,
            "damping_per_s": self.damping_per_s,
            "mass_scaling": self.config.mass_scaling,
            "method": self.config.method,
            "device": str(self.device),
        }


class State:
    """Particle state: position ``x`` (grid-local m), velocity ``v`` (m/s), affine ``C`` (1/s),
    deformation gradient ``F``; ``x_carry`` (m) is the part of the motion below float32 resolution at
    ``x`` that the next step adds back (compensated summation, :func:`warpmpm.kernels.g2p`)."""

    def __init__(self, model: MPMModel, positions_mm: np.ndarray):
        d = model.device
        n = model.n
        positions_mm = np.asarray(positions_mm, dtype=np.float64)
        if positions_mm.shape != (n, 3):
            raise InputError(f"positions must have shape ({n}, 3), got {positions_mm.shape}")
        self.x = wp.array(model.to_local_m(positions_mm), dtype=wp.vec3, device=d)
        self.x_carry = wp.zeros(n, dtype=wp.vec3, device=d)
        self.v = wp.zeros(n, dtype=wp.vec3, device=d)
        self.C = wp.zeros(n, dtype=wp.mat33, device=d)
        self.F = wp.array(np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)), dtype=wp.mat33, device=d)
        self._model = model

    def positions_mm(self) -> np.ndarray:
        return self._model.to_world_mm(self.x.numpy())

    def copy_from(self, other: "State") -> None:
        for name in ("x", "x_carry", "v", "C", "F"):
            wp.copy(getattr(self, name), getattr(other, name))

    def numpy(self) -> dict[str, np.ndarray]:
        return {"positions_mm": self.positions_mm(), "v_m_s": self.v.numpy(), "C": self.C.numpy(), "F": self.F.numpy()}


class MPMSolver:
    """Explicit MLS-MPM time stepper over an :class:`MPMModel`.

    ``adaptive``: whether the velocity damping adapts (:attr:`SolverConfig.damping_rule`); None: only under
    ``"adaptive"`` (an ``"auto"`` rule is resolved by whoever knows the stopping rule, the estimator)."""

    def __init__(self, model: MPMModel, adaptive: bool | None = None):
        self.model = model
        d = model.device
        shape = model.grid_shape
        self.fields = model.n_fields > 1
        stacked = (shape[0] * model.n_fields, shape[1], shape[2])  # the organ fields stacked along x
        #: threads of a split CPU step (:mod:`warpmpm.parallel`); each scatters into its own copy of the grid's
        #: mass and momentum (the copies stacked along x after the organ fields), which the grid update adds
        self.threads = cpu_threads(model.config, d)
        self._ranges = parallel.split(model.n, self.threads)
        self.threads = len(self._ranges)
        self._node_ranges = parallel.split(shape[0], self.threads)
        #: the grid update visits only the blocks of nodes that hold mass (:func:`warpmpm.kernels.grid_update_blocks`;
        #: sticky contact on the CPU; one thread only: on two the dense update is faster, docs/decisions/2026-12-03-solver-defaults.md)
        self._sparse_capable = not self.fields and not str(d).startswith("cuda")
        self._sparse_update = self._sparse_capable and self.threads == 1
        blocks = tuple(-(-n // kernels.BLOCK) for n in shape) if self._sparse_capable else (1, 1, 1)
        self._stamps = wp.zeros(blocks, dtype=int, device=d)
        self._updated = wp.zeros(blocks, dtype=int, device=d)
        self._block_ranges = parallel.split(blocks[0], self.threads)
        self._views = parallel.ChunkViews(self._ranges)
        copies = (stacked[0] * self.threads, stacked[1], stacked[2])
        if self.fields:  # sliding contact: mass and momentum per organ field, and the mass gradient
            self.grid_m = wp.zeros(copies, dtype=float, device=d)
            self.grid_mv = wp.zeros(copies, dtype=wp.vec3, device=d)
        else:
            #: sticky contact: each node's momentum (x, y, z, kg m/s) and mass (w, kg) side by side, so P2G adds both with
            #: one address
            self.grid_mm = wp.zeros(copies, dtype=wp.vec4, device=d)
        #: the nodes' velocities (m/s) in x, y, z (w unused: 16-byte nodes, one aligned load each in G2P)
        self.grid_v = wp.zeros(stacked, dtype=wp.vec4, device=d)
        self.grid_g = wp.zeros(copies, dtype=wp.vec3, device=d) if self.fields else None
        #: the coarse level of the relaxation (:mod:`warpmpm.rigid_modes`), set by :meth:`set_accelerator`; None: none
        self.accelerator = None
        # the step's force impulse alone (scattered copies and their sum), only while an accelerator is set
        self._grid_f = self._force_sum = wp.zeros((1, 1, 1), dtype=wp.vec3, device=d)
        self.zero_force = wp.zeros(model.n, dtype=wp.vec3, device=d)
        # one status flag per thread (a CPU "atomic" is a plain read-modify-write: two threads must not share one)
        self._status_parts = [wp.array(np.array([0, 2**31 - 1, 2**31 - 1], dtype=np.int32), dtype=int, device=d)
                              for _ in range(self.threads)]
        self.status = self._status_parts[0]
        # velocity damping factor per step, on the device so the adaptive rule can change it inside a captured graph
        self.damping = wp.array([math.exp(-model.damping_per_s * model.dt_s)], dtype=float, device=d)
        self._damping_dt = model.dt_s  # the step length the fixed factor was computed for
        self.adaptive = model.config.damping_rule == "adaptive" if adaptive is None else bool(adaptive)
        if self.adaptive:
            self._accel_prev = wp.zeros(model.n, dtype=wp.vec3, device=d)
            self._rayleigh = wp.zeros((2, RAYLEIGH_SLOTS), dtype=float, device=d)
            self._rayleigh_memory = wp.zeros(2, dtype=float, device=d)
            #: 1 for the particles whose motion measures the stiffness, 0 for the driven ones (:meth:`set_driven`)
            self.rayleigh_weight = wp.ones(model.n, dtype=float, device=d)
        self.step_count = 0
        ce = model.config.check_every
        self.check_every = ce if ce is not None else (50 if str(d).startswith("cuda") else 1)
        dx_m = model.dx_mm * 1e-3
        self._dx = dx_m
        self._x_min = 1.0 * dx_m
        self._x_max = wp.vec3(*[(s - 2.0) * dx_m for s in shape])

    @property
    def sparse_update(self) -> bool:
        """Whether the grid update visits only the node blocks that hold mass (:func:`warpmpm.kernels.grid_update_blocks`):
        by default on a one-thread CPU step with sticky contact (the solver keeps the blocks' stamps whenever it runs on
        the CPU with sticky contact). It may be set to False (every node, the dense update: the same grid to the bit)
        and back; True is refused where there are no stamps (CUDA, sliding contact)."""
        return self._sparse_update

    @sparse_update.setter
    def sparse_update(self, value: bool) -> None:
        value = bool(value)
        if value and not self._sparse_capable:
            raise InputError("the sparse grid update runs on the CPU with sticky contact only: this solver was built for "
                             f"{'sliding contact' if self.fields else self.model.device}, without the node blocks' stamps")
        if value and not self._sparse_update:
            self._updated.fill_(1)  # the dense steps left no record of which blocks held mass: visit every block once
        self._sparse_update = value

    def set_accelerator(self, accelerator) -> None:
        """Use ``accelerator`` (a :class:`warpmpm.rigid_modes.RigidModeAccelerator`, or None for none) in every step
        from now on: P2G then also scatters the force impulse apart, and the accelerator adds its coarse velocity
        change after the grid update."""
        d = self.model.device
        self.accelerator = accelerator
        if accelerator is None:
            self._grid_f = self._force_sum = wp.zeros((1, 1, 1), dtype=wp.vec3, device=d)
        elif self._force_sum.shape != self.grid_v.shape:
            self._grid_f = wp.zeros(self.grid_mm.shape, dtype=wp.vec3, device=d)
            self._force_sum = wp.zeros(self.grid_v.shape, dtype=wp.vec3, device=d)

    def _accelerating(self) -> bool:
        return self.accelerator is not None and self.accelerator.active

    def set_driven(self, driven: np.ndarray) -> None:
        """Leave the driven particles out of the adaptive damping's stiffness estimate (their drive is a spring
        of its own, far stiffer than the tissue)."""
        if self.adaptive:
            w = np.ones(self.model.n, dtype=np.float32)
            w[np.asarray(driven, dtype=np.int64)] = 0.0
            self.rayleigh_weight.assign(w)

    def reset_damping(self) -> None:
        """Start the adaptive damping afresh (a new frame): the derived value, no memory of past motion."""
        self.damping.assign(np.array([math.exp(-self.model.damping_per_s * self.model.dt_s)], dtype=np.float32))
        self._damping_dt = self.model.dt_s
        if self.adaptive:
            self._rayleigh.zero_()
            self._rayleigh_memory.zero_()
            self._accel_prev.zero_()

    @property
    def damping_per_s(self) -> float:
        """The velocity damping rate (1/s) the next step applies (reads the device)."""
        return float(-math.log(float(self.damping.numpy()[0])) / self.model.dt_s)

    def step(self, state_in: State, state_out: State, control: wp.array | None = None, dt: float | None = None,
             check: bool = True) -> None:
        """Advance one step from ``state_in`` to ``state_out`` under the external force ``control`` (N).

        ``check=False`` skips the host read-back of the status flag (for graph capture, where no
        read-back may happen; call :meth:`check` after the graph has run)."""
        m = self.model
        dt = m.dt_s if dt is None else dt
        d = m.device
        force = self.zero_force if control is None else control
        if not self.adaptive and dt != self._damping_dt:  # a fixed rate: the factor follows the step's length
            self.damping.assign(np.array([math.exp(-m.damping_per_s * dt)], dtype=np.float32))
            self._damping_dt = dt
        damping = self.damping
        cfg = m.config
        parts = 1 if self.threads == 1 or wp.get_device(d).is_capturing else self.threads
        if parts == 1:
            self._p2g_part(0, state_in.x, state_in.v, state_in.C, state_in.F, force, [m.mass, m.vol0, m.mu, m.lam, m.field], dt)
            self._grid_update(0, 0, damping, 1)
        else:
            n = len(self._ranges)
            x_in, v_in, C_in, F_in, f_in = (self._views(a) for a in (state_in.x, state_in.v, state_in.C, state_in.F, force))
            carry_in = self._views(state_in.x_carry)
            outs = [self._views(a) for a in (state_out.x, state_out.x_carry, state_out.v, state_out.C, state_out.F)]
            pv = [self._views(a) for a in (m.mass, m.vol0, m.mu, m.lam, m.field)]
            parallel.run_together(
                lambda k=k: self._p2g_part(k, x_in[k], v_in[k], C_in[k], F_in[k], f_in[k], [a[k] for a in pv], dt) for k in range(n))
            parallel.run_together(lambda k=k: self._grid_update(k, n, damping, n) for k in range(n))
        if self._accelerating():
            self.accelerator.correct(self._force_sum, damping, self.grid_v)
        if parts == 1:
            self._g2p_part(0, state_in.x, state_in.x_carry, state_in.F, m.field,
                           [state_out.x, state_out.x_carry, state_out.v, state_out.C, state_out.F], dt)
        else:
            parallel.run_together(
                lambda k=k: self._g2p_part(k, x_in[k], carry_in[k], F_in[k], pv[4][k], [a[k] for a in outs], dt) for k in range(n))
        if self.adaptive:
            lo, hi = cfg.damping_bounds
            wp.launch(kernels.stiffness_rayleigh, m.n, [state_in.v, state_out.v, self._accel_prev, m.mass, self.rayleigh_weight,
                                                        self.damping, dt, self._rayleigh], device=d)
            wp.launch(kernels.adapt_damping, 1, [self._rayleigh, self._rayleigh_memory, 1.0 - 1.0 / cfg.damping_memory_steps, dt,
                                                 lo * m.damping_per_s, hi * m.damping_per_s, self.damping], device=d)
        self.step_count += 1
        if check and self.check_every and self.step_count % self.check_every == 0:
            self.check()

    def _p2g_part(self, k, x, v, C, F, force, per_particle, dt):
        """P2G of thread ``k``'s particles (the arrays cut to its range; whole for one thread) into grid copy ``k``."""
        m = self.model
        nx = m.grid_shape[0]
        mass, vol0, mu, lam, field = per_particle
        if self.fields:
            wp.launch(kernels.p2g_fields, x.shape[0], [x, v, C, F, force, mass, vol0, mu, lam, field, nx, self._dx, dt,
                                                       k * nx * m.n_fields, self.grid_m, self.grid_mv, self.grid_g], device=m.device)
        else:
            wp.launch(kernels.p2g, x.shape[0], [x, v, C, F, force, mass, vol0, mu, lam, self._dx, dt, k * nx,
                                                int(self._accelerating()), self._stamp(), self.grid_mm, self._grid_f,
                                                self._stamps],
                      device=m.device)

    def _stamp(self) -> int:
        """This step's number as P2G stamps it into the node blocks it scatters into (never 0, the blocks' start; 0
        when the update is dense: no stamps)."""
        return self.step_count % 1_000_000_000 + 1 if self.sparse_update else 0

    def _grid_update(self, k, n, damping, parts):
        """Grid update of thread ``k``'s slab along x (of ``n`` threads; 0 of 1 for all of it), adding ``parts`` copies
        of the scattered sums."""
        m = self.model
        cfg = m.config
        if self.sparse_update:
            lo, hi = self._block_ranges[k] if n > 1 else (0, self._stamps.shape[0])
            wp.launch(kernels.grid_update_blocks, (hi - lo, *self._stamps.shape[1:]),
                      [self.grid_mm, parts, lo, self._stamps, self._stamp(), self._updated, damping, cfg.wall_cells,
                       int(self._accelerating()), self._grid_f, self.grid_v, self._force_sum], device=m.device)
            return
        lo, hi = self._node_ranges[k] if n > 1 else (0, m.grid_shape[0])
        dim = (hi - lo, m.grid_shape[1], m.grid_shape[2])
        if self.fields:
            wp.launch(kernels.grid_update_fields, dim, [self.grid_m, self.grid_mv, self.grid_g, m.n_fields, m.grid_shape[0], parts, lo,
                                                        damping, cfg.wall_cells, cfg.friction, self.grid_v], device=m.device)
        else:
            wp.launch(kernels.grid_update, dim, [self.grid_mm, parts, lo, damping, cfg.wall_cells,
                                                 int(self._accelerating()), self._grid_f, self.grid_v, self._force_sum],
                      device=m.device)

    def _g2p_part(self, k, x, carry, F, field, outs, dt):
        """G2P of thread ``k``'s particles (arrays cut to its range), flagging into its own status array."""
        m = self.model
        nx = m.grid_shape[0] if self.fields else 0
        x_out, carry_out, v_out, C_out, F_out = outs
        wp.launch(kernels.g2p, x.shape[0], [self.grid_v, field, nx, x, carry, F, self._dx, dt, self._x_min, self._x_max,
                                            self.step_count, self._ranges[k][0], x_out, carry_out, v_out, C_out, F_out,
                                            self._status_parts[k]], device=m.device)

    def check(self) -> None:
        """Raise :class:`SimulationError` when a kernel flagged a non-finite value or a particle leaving the grid."""
        flags = np.stack([a.numpy() for a in self._status_parts]) if len(self._status_parts) > 1 else self.status.numpy()[None]
        code = int(flags[:, 0].max())
        if code == kernels.STATUS_OK:
            return
        bad = flags[flags[:, 0] > 0]
        particle, step = int(bad[:, 1].min()), int(bad[:, 2].min())
        organ = self.model.particles.organs[int(self.model.particles.organ_index[particle])]
        if code == kernels.STATUS_NONFINITE:
            raise SimulationError(
                f"non-finite value (NaN/Inf) at step {step}, particle {particle} ({organ}); the time step "
                f"{self.model.dt_s:.3e} s or the driving gains are too large for this scene"
            )
        raise SimulationError(
            f"particle {particle} ({organ}) tried to leave the simulation grid at step {step}; "
            f"increase SolverConfig.margin_mm (now {self.model.config.margin_mm} mm) or check the targets"
        )

    def reset_status(self) -> None:
        for a in self._status_parts:
            a.assign(np.array([0, 2**31 - 1, 2**31 - 1], dtype=np.int32))
