"""Slice-driven estimation: the particles lying on one or more 2D slices are driven toward their targets while the
whole multi-organ model finds its equilibrium; the equilibrium positions are the frame's 3D estimate. A frame starts
from the previous frame's state (a cine stream is followed frame after frame).

:class:`SliceDrivenEstimator` owns the model, the driven particles and the frame solver (:mod:`warpmpm.solvers`); the
drive, its stopping rule and the result are re-exported here from :mod:`warpmpm.solvers.drive`,
:mod:`warpmpm.solvers.convergence` and :mod:`warpmpm.solvers.result`.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .model import ParticleModel
from .slices import DrivingSlice, driven_indices
from .solvers.config import SolverConfig
from .solvers.convergence import ConvergenceConfig, ConvergenceMonitor
from .solvers.drive import DriveConfig, Gains, pid_force
from .solvers.frame import choose_frame_solver
from .solvers.grid import MPMModel
from .solvers.quasistatic import QuasiStaticSolver
from .solvers.relaxation import ExplicitRelaxation
from .solvers.result import DriveResult

__all__ = ["ConvergenceConfig", "ConvergenceMonitor", "Gains", "DriveConfig", "pid_force", "DriveResult",
           "SliceDrivenEstimator"]


class SliceDrivenEstimator:
    """Owns the solver and the current state; estimates frame after frame.

    Example::

        est = SliceDrivenEstimator(model, [DrivingSlice("axial", 20)])
        idx, targets = affine_targets(model, est.positions_mm(), est.slices, [InPlaneAffine(A, t)])  # warpmpm.targets
        result = est.estimate(targets)          # frame 1
        result2 = est.estimate(next_targets)    # frame 2 starts from frame 1's state

    A frame is solved by the frame solver of ``SolverConfig.method`` (:func:`warpmpm.solvers.frame.choose_frame_solver`)
    on the state of the explicit relaxation (:class:`~warpmpm.solvers.relaxation.ExplicitRelaxation`, which also
    explains ``sync_every`` and ``use_graph``, the GPU path).
    """

    def __init__(self, model: ParticleModel, slices: list[DrivingSlice] | None = None, *,
                 driven: np.ndarray | None = None, solver_config: SolverConfig | None = None,
                 drive_config: DriveConfig | None = None, convergence: ConvergenceConfig | None = None,
                 extra_points_mm: np.ndarray | None = None, callback=None, sync_every: int | None = None,
                 use_graph: bool | None = None):
        if slices is None and driven is None:
            raise InputError("give driving slices or explicit driven particle indices")
        self.particles = model
        self.slices = list(slices) if slices else []
        self.driven = driven_indices(model, self.slices) if driven is None else np.asarray(driven, dtype=np.int64)
        if self.driven.size == 0:
            raise InputError("no particle to drive: the driving slices hold none of this model's particles"
                             + (f" (particle sampling step {model.sampling_step} leaves none on them)" if model.sampling_step > 1 else ""))
        if self.driven.min() < 0 or self.driven.max() >= model.n:
            raise InputError("driven particle indices outside the model")
        self.convergence = convergence or ConvergenceConfig()
        self.mpm = MPMModel(model, solver_config, extra_points_mm)
        self.relaxation = ExplicitRelaxation(self.mpm, model, self.driven, self.convergence, drive_config or DriveConfig(),
                                             None if callback is None else (lambda step, rel, rms: callback(self, step, rel, rms)),
                                             sync_every=sync_every, use_graph=use_graph)
        #: the Newton / conjugate-gradient solver of ``SolverConfig(method="quasistatic" | "auto")``; None: explicit steps
        self.quasistatic = (QuasiStaticSolver(self.mpm, self.mpm.config.quasistatic)
                            if self.mpm.config.method in ("quasistatic", "auto") else None)
        #: the frame solver of ``SolverConfig.method``
        self.frame_solver = choose_frame_solver(self.mpm.config.method, self.relaxation, self.quasistatic)

    @property
    def state(self):
        """The current state (the relaxation's; the quasi-static solver moves the same one)."""
        return self.relaxation.state

    @property
    def solver(self):
        """The explicit stepper (:class:`~warpmpm.solvers.explicit.MPMSolver`)."""
        return self.relaxation.solver

    @property
    def accelerator(self):
        """The rigid-mode accelerator of the settled mode; None: none."""
        return self.relaxation.accelerator

    @property
    def gains(self):
        """The PID drive's gains (physical units)."""
        return self.relaxation.gains

    @property
    def frames(self) -> int:
        return self.relaxation.frames

    def positions_mm(self) -> np.ndarray:
        return self.state.positions_mm()

    def driven_axes(self) -> np.ndarray:
        """(n_driven, 3, 3) the projector of each driven particle's drive (the identity: pinned; the plane's in-plane
        projector: in-plane driving), as the last :meth:`estimate` set it (a copy)."""
        return self.relaxation.driven_axes()

    def _inside_grid(self, points_mm: np.ndarray) -> bool:
        """Whether every point lies where a particle's stencil stays clear of the grid's wall layer."""
        lo = self.mpm.origin_mm + (self.mpm.config.grid.wall_cells + 1) * self.mpm.dx_mm
        hi = self.mpm.origin_mm + (np.asarray(self.mpm.grid_shape) - self.mpm.config.grid.wall_cells - 2) * self.mpm.dx_mm
        return not (np.any(points_mm < lo) or np.any(points_mm > hi))

    def move_to(self, positions_mm: np.ndarray) -> None:
        """Place every particle at ``positions_mm`` (N, 3), at rest, keeping its deformation gradient: a
        kinematic prediction the next :meth:`estimate` corrects (the tracker's predictor). The move itself
        stores no strain, so it must be a motion the tissue makes without deforming (per-organ translation,
        rotation), or the physics will not see it."""
        positions_mm = np.asarray(positions_mm, dtype=np.float64)
        if positions_mm.shape != (self.particles.n, 3) or not np.all(np.isfinite(positions_mm)):
            raise InputError(f"predicted positions must be finite with shape ({self.particles.n}, 3), got {positions_mm.shape}")
        if not self._inside_grid(positions_mm):
            raise InputError("predicted positions lie outside the simulation grid; build the estimator with a larger reach")
        self.state.x.assign(self.mpm.to_local_m(positions_mm))
        self.state.x_carry.zero_()
        self.state.v.zero_()
        self.state.C.zero_()

    def driven_positions_mm(self) -> np.ndarray:
        return self.positions_mm()[self.driven]

    def _checked_drive(self, targets_mm, axes):
        """The targets (n_driven, 3, world mm) and projectors (n_driven, 3, 3; None: every direction) as float64, or
        :class:`InputError` saying what is wrong with them."""
        targets_mm = np.asarray(targets_mm, dtype=np.float64)
        if targets_mm.shape != (len(self.driven), 3):
            raise InputError(f"targets must have shape ({len(self.driven)}, 3) for the driven particles, got {targets_mm.shape}")
        if not np.all(np.isfinite(targets_mm)):
            raise InputError("targets hold a non-finite value")
        if not self._inside_grid(targets_mm):
            raise InputError("targets lie outside the simulation grid; build the estimator with extra_points_mm covering them "
                             f"or a larger GridConfig.margin_mm (now {self.mpm.config.grid.margin_mm} mm)")
        nd = len(self.driven)
        if axes is None:
            axes = np.tile(np.eye(3), (nd, 1, 1))
        axes = np.asarray(axes, dtype=np.float64)
        if axes.shape != (nd, 3, 3) or not np.all(np.isfinite(axes)):
            raise InputError(f"driven axes must be finite projectors of shape ({nd}, 3, 3), got {axes.shape}")
        return targets_mm, axes

    def estimate(self, targets_mm: np.ndarray, convergence: ConvergenceConfig | None = None, carry_force: bool = True,
                 axes: np.ndarray | None = None) -> DriveResult:
        """Drive the driven particles to ``targets_mm`` (n_driven, 3) until convergence; one frame.

        ``axes`` (n_driven, 3, 3): per driven particle, the projector onto the directions that are driven
        (:func:`warpmpm.targets.plane_projector`: a slice drives its in-plane components and leaves the
        through-plane one to the physics); None drives all three components (the default).

        The PID integral restarts at zero every frame. With ``carry_force`` (default) the integral
        action that held the previous frame's equilibrium is kept as a constant feed-forward term,
        so a frame that differs little from the last starts almost in balance instead of springing
        back while the integral rebuilds (measured: fewer steps per frame in a stream).
        """
        targets_mm, axes = self._checked_drive(targets_mm, axes)
        self.relaxation.set_axes(axes)
        return self.frame_solver.solve(targets_mm, axes, convergence, carry_force)
