"""The solvers: one frame from a state and a drive to an equilibrium.

- :mod:`~warpmpm.solvers.config`: :class:`SolverConfig`, a composite of :class:`GridConfig`, :class:`ExplicitConfig`,
  :class:`QuasiStaticConfig` and :class:`AccelerationConfig`; units in the field names, a docstring on every field.
- :mod:`~warpmpm.solvers.grid`: the background grid and device policy, :class:`MPMModel` (built once) and :class:`State`.
- :mod:`~warpmpm.solvers.explicit` (kernels in :mod:`~warpmpm.solvers.explicit_kernels`): the explicit MLS-MPM stepper
  :class:`MPMSolver`, split over the CPU's cores by :mod:`~warpmpm.solvers.parallel`.
- :mod:`~warpmpm.solvers.quasistatic` (kernels in :mod:`~warpmpm.solvers.quasistatic_kernels`): the Newton /
  conjugate-gradient solve of the same equilibrium.
- :mod:`~warpmpm.solvers.rigid_modes` (kernels in :mod:`~warpmpm.solvers.rigid_modes_kernels`): the coarse level that
  accelerates the explicit relaxation.
- :mod:`~warpmpm.solvers.coarse_space` (kernels in :mod:`~warpmpm.solvers.coarse_space_kernels`): the one coarse space
  both of those use: groups' rigid or affine motions on the grid, restriction and prolongation.
- :mod:`~warpmpm.solvers.convergence`, :mod:`~warpmpm.solvers.drive`, :mod:`~warpmpm.solvers.relaxation`,
  :mod:`~warpmpm.solvers.frame`, :mod:`~warpmpm.solvers.result`: a frame: the stopping rule, the PID drive, the explicit
  relaxation loop, the :class:`~warpmpm.solvers.frame.FrameSolver` protocol and the choice among the frame solvers.
- :mod:`~warpmpm.solvers.completion` (kernels in :mod:`~warpmpm.solvers.completion_kernels`): the linear elastic
  equilibrium of the whole abdomen that completes what the planes see.
"""

from .config import (MIN_LAYERS_PER_CELL, RIGID_MODE_AGGREGATE_MM, RIGID_MODE_BASES, RIGID_MODE_BASIS, AccelerationConfig,
                     ExplicitConfig, GridConfig, QuasiStaticConfig, SolverConfig)
from .explicit import MPMSolver
from .grid import MPMModel, State, cpu_threads, default_device, grid_layout, memory_estimate_bytes
from .quasistatic import QuasiStaticResult, QuasiStaticSolver
from .rigid_modes import RigidModeAccelerator

__all__ = ["SolverConfig", "GridConfig", "ExplicitConfig", "QuasiStaticConfig", "AccelerationConfig", "MIN_LAYERS_PER_CELL", "RIGID_MODE_AGGREGATE_MM", "RIGID_MODE_BASIS",
           "RIGID_MODE_BASES", "MPMModel", "State", "MPMSolver", "QuasiStaticSolver", "QuasiStaticResult",
           "RigidModeAccelerator", "grid_layout", "memory_estimate_bytes", "cpu_threads", "default_device"]
