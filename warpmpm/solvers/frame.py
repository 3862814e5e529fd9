"""One frame: from the current state and a drive (the driven particles' targets and the directions they are driven
along) to an equilibrium, and what the frame did.

:class:`FrameSolver` is what every frame solver does: :class:`~warpmpm.solvers.relaxation.ExplicitRelaxation` (explicit
MPM steps under the PID drive, stopped by the paper's rule or when the body has settled), :class:`QuasiStaticFrame`
(Newton / conjugate-gradient iterations to the settled equilibrium) and :class:`AutoFrame` (those iterations first, the
explicit steps from where they stopped when the frame has not settled); :func:`choose_frame_solver` picks one by
:attr:`SolverConfig.method <warpmpm.solvers.config.SolverConfig.method>`.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Protocol

import numpy as np

from .convergence import ConvergenceConfig
from .quasistatic import QuasiStaticSolver
from .relaxation import ExplicitRelaxation
from .result import DriveResult

__all__ = ["FrameSolver", "QuasiStaticFrame", "AutoFrame", "choose_frame_solver"]


class FrameSolver(Protocol):
    """Solves one frame: moves the state it shares with the estimator to the equilibrium under the drive."""

    def solve(self, targets_mm: np.ndarray, axes: np.ndarray, convergence: ConvergenceConfig | None = None,
              carry_force: bool = True) -> DriveResult:
        """Drive the driven particles toward ``targets_mm`` (n_driven, 3, world mm) along ``axes`` (n_driven, 3, 3
        projectors) until the frame's equilibrium; ``convergence`` overrides the stopping rule of an explicit frame,
        ``carry_force`` keeps the last frame's holding force as a feed-forward term."""
        ...


class QuasiStaticFrame:
    """A frame by the quasi-static solver (:mod:`warpmpm.solvers.quasistatic`): the settled equilibrium under the
    drive's spring; the ConvergenceConfig's rules do not apply (the solver stops when an iteration moves no particle by
    more than ``QuasiStaticConfig.settle_mm``). It works on the explicit relaxation's state (``relaxation``), whose
    PID memory it clears when it has settled."""

    def __init__(self, solver: QuasiStaticSolver, relaxation: ExplicitRelaxation):
        self.solver = solver
        self.relaxation = relaxation

    def solve(self, targets_mm: np.ndarray, axes: np.ndarray, convergence: ConvergenceConfig | None = None,
              carry_force: bool = True, trial: bool = False) -> DriveResult:
        """``trial`` (``method="auto"``): at most ``auto_newton_iterations``, stopping at a capped linear solve, and no
        warning when it has not settled (the explicit steps go on from there)."""
        rx = self.relaxation
        nd = len(rx.driven)
        t0 = time.perf_counter()
        self.solver.set_drive(rx.driven, targets_mm, axes)
        qc = self.solver.config
        res = self.solver.solve(rx.state, max_iterations=qc.auto_newton_iterations if trial else None, stop_at_cg_cap=trial,
                                max_cg_iterations=qc.auto_max_cg_iterations if trial else None)
        wall = time.perf_counter() - t0
        if res.settled:  # the PID's integral and feed-forward belong to an explicit frame's equilibrium; none holds this one
            rx.clear_drive_memory()
        reach = np.einsum("nij,nj->ni", axes, targets_mm - rx.particles.center_mm())
        scale = math.sqrt(max(float(np.sum(reach**2)), 1e-30) / nd)
        rms = np.asarray(res.rms_history_mm, dtype=np.float64)
        rel = rms / scale
        if rx.callback is not None:
            for k in range(len(rms)):
                rx.callback(k + 1, float(rel[k]), float(rms[k]))
        if trial and not res.settled:
            return DriveResult(rx.positions_mm(), res.newton_iterations, wall, rel, rms, False, "max_iterations", None, False,
                               res.max_move_mm, float("nan"), method="quasistatic", linear_iterations=res.cg_iterations)
        rx.frames += 1
        det = np.linalg.det(rx.state.F.numpy().astype(np.float64))
        result = DriveResult(rx.positions_mm(), res.newton_iterations, wall, rel, rms, res.settled,
                             "settled" if res.settled else "max_iterations", None, res.settled, res.max_move_mm, float(det.min()),
                             method="quasistatic", linear_iterations=res.cg_iterations)
        if not res.settled:
            warnings.warn(f"quasi-static estimate did not settle in {res.newton_iterations} Newton iterations (the last moved a "
                          f"particle {res.max_move_mm:.3f} mm; QuasiStaticConfig.settle_mm {self.solver.config.settle_mm} mm)",
                          RuntimeWarning, stacklevel=3)
        return result


class AutoFrame:
    """``SolverConfig(method="auto")``: the quasi-static iterations first, for at most
    ``QuasiStaticConfig.auto_newton_iterations``; a frame they have not settled goes on with explicit steps from where
    they stopped (the result's ``method`` then reads ``"quasistatic+explicit"``)."""

    def __init__(self, quasistatic: QuasiStaticFrame, relaxation: ExplicitRelaxation):
        self.quasistatic = quasistatic
        self.relaxation = relaxation

    def solve(self, targets_mm: np.ndarray, axes: np.ndarray, convergence: ConvergenceConfig | None = None,
              carry_force: bool = True) -> DriveResult:
        trial = self.quasistatic.solve(targets_mm, axes, trial=True)
        if trial.converged:
            return trial
        return self.relaxation.solve(targets_mm, axes, convergence, carry_force, trial=trial)


def choose_frame_solver(method: str, relaxation: ExplicitRelaxation, quasistatic: QuasiStaticSolver | None) -> FrameSolver:
    """The frame solver of ``SolverConfig.method``: ``"explicit"``, ``"quasistatic"`` or ``"auto"``."""
    if method == "explicit":
        return relaxation
    frame = QuasiStaticFrame(quasistatic, relaxation)
    return frame if method == "quasistatic" else AutoFrame(frame, relaxation)
