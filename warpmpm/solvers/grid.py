"""The background grid and the device policy of the MPM solvers: the grid's layout from the particles and the config,
the memory a scene needs, the threads a step splits over, the default device; the static :class:`MPMModel` built once
from a particle model and the :class:`State` that changes.

Public values are physical: positions in mm (world coordinates), time steps in s, densities in kg/m^3. Inside, kernels
work in SI with positions relative to the grid origin."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..errors import InputError
from ..model import ParticleModel
from . import parallel
from .config import SolverConfig

__all__ = ["BYTES_PER_PARTICLE", "BYTES_PER_NODE", "BYTES_PER_NODE_COPY", "grid_layout", "memory_estimate_bytes",
           "cpu_threads", "default_device", "MPMModel", "State"]


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
    gap = particles.max_gap_mm if cfg.grid.cell_at_least_gap else 0.0
    if cfg.grid.cell_size_mm:
        if cfg.grid.cell_size_mm < gap * (1 - 1e-9):
            raise InputError(f"grid cell {cfg.grid.cell_size_mm} mm is smaller than the {gap:.2f} mm gap between neighbouring "
                             "particles: the particle layers would not share grid nodes and would move apart; "
                             f"use cell_size_mm >= {gap:.2f}")
        dx = float(cfg.grid.cell_size_mm)
    else:
        # the particle layers must share grid nodes (thick slices), and no axis may hold one layer a cell (null modes)
        dx = max(float((cfg.grid.particles_per_cell * np.median(particles.volume_mm3)) ** (1 / 3)), cfg.grid.min_layers_per_cell * gap)
    pts = particles.positions_mm
    if extra_points_mm is not None and len(extra_points_mm):
        extra = np.asarray(extra_points_mm, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(extra)):
            bad = int(np.nonzero(~np.all(np.isfinite(extra), axis=1))[0][0])
            raise InputError(f"extra_points_mm holds a non-finite value (point {bad}); the grid must cover finite positions")
        pts = np.vstack([pts, extra])
    lo = pts.min(axis=0) - cfg.grid.margin_mm
    hi = pts.max(axis=0) + cfg.grid.margin_mm
    pad = (cfg.grid.wall_cells + 2) * dx
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
    :func:`warpmpm.solvers.parallel.default_threads` (:attr:`SolverConfig.cpu_threads`)."""
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
        if cfg.explicit.mass_scaling:
            rho_eff = modulus / self.real_wave_speed_m_s**2
        else:
            rho_eff = rho
        self.density_kg_m3 = rho_eff
        self.wave_speed_m_s = float(np.sqrt(modulus / rho_eff).max())
        dx_m = self.dx_mm * 1e-3
        self.dt_limit_s = cfg.explicit.cfl_limit * dx_m / self.wave_speed_m_s
        if cfg.explicit.dt_s is not None:
            if not (cfg.explicit.dt_s > 0 and math.isfinite(cfg.explicit.dt_s)):
                raise InputError(f"time step must be a positive finite number, got {cfg.explicit.dt_s}")
            if cfg.explicit.dt_s > self.dt_limit_s:
                raise InputError(
                    f"time step {cfg.explicit.dt_s:.3e} s is above the stable limit {self.dt_limit_s:.3e} s "
                    f"(CFL {cfg.explicit.cfl_limit} x dx {self.dx_mm:.2f} mm / wave speed {self.wave_speed_m_s:.1f} m/s)"
                )
            self.dt_s = float(cfg.explicit.dt_s)
        else:
            self.dt_s = cfg.explicit.cfl * dx_m / self.wave_speed_m_s
        if cfg.explicit.damping_per_s is None:
            # Slowest shear mode of the scene: omega ~ pi c_s / L, with the smallest scaled shear speed.
            c_shear = np.sqrt(mu / rho_eff)
            size_m = float(np.max(particles.positions_mm.max(0) - particles.positions_mm.min(0))) * 1e-3
            if not (cfg.explicit.damping_factor >= 0 and math.isfinite(cfg.explicit.damping_factor)):
                raise InputError(f"damping_factor must be a finite number >= 0, got {cfg.explicit.damping_factor}")
            self.damping_per_s = float(cfg.explicit.damping_factor * 2.0 * math.pi * np.median(c_shear) / max(size_m, 10 * dx_m))
        else:
            if cfg.explicit.damping_per_s < 0:
                raise InputError(f"damping must be >= 0 1/s, got {cfg.explicit.damping_per_s}")
            self.damping_per_s = float(cfg.explicit.damping_per_s)

        mass = rho_eff * vol_mm3 * 1e-9
        self.mass_kg = mass
        d = self.device
        self.mass = wp.array(mass.astype(np.float32), dtype=float, device=d)
        self.vol0 = wp.array((vol_mm3 * 1e-9).astype(np.float32), dtype=float, device=d)
        self.mu = wp.array(mu.astype(np.float32), dtype=float, device=d)
        self.lam = wp.array(lam.astype(np.float32), dtype=float, device=d)
        #: grid velocity fields: one per organ with sliding contact, one shared with sticky contact
        field_of_organ = np.zeros(len(particles.organs), dtype=np.int32)
        if cfg.explicit.contact == "sliding":
            group_of = {o: gi for gi, g in enumerate(cfg.explicit.bonded) for o in g}
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
            "mass_scaling": self.config.explicit.mass_scaling,
            "method": self.config.method,
            "device": str(self.device),
        }


class State:
    """Particle state: position ``x`` (grid-local m), velocity ``v`` (m/s), affine ``C`` (1/s),
    deformation gradient ``F``; ``x_carry`` (m) is the part of the motion below float32 resolution at
    ``x`` that the next step adds back (compensated summation, :func:`warpmpm.solvers.explicit_kernels.g2p`)."""

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
