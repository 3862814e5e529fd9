"""Smoothed-aggregation algebraic multigrid for linear elasticity (``pyamg``), shared by every elastic solve of the
package: the finite-element reference (:mod:`warpmpm.fem`), the finite-element truths (:mod:`warpmpm.truth_fem`) and
the completion solve (:mod:`warpmpm.solvers.completion`). Linear algebra only: no Warp, no MPM.

The near-null space of an elastic body is its six rigid motions; giving them to the aggregation (``B``) is what makes
the coarse levels carry the soft modes of stiff inclusions in soft tissue.
"""

from __future__ import annotations

import numpy as np

__all__ = ["rigid_body_modes", "elasticity_preconditioner"]


def rigid_body_modes(points_mm: np.ndarray) -> np.ndarray:
    """(3 n, 6) the three translations and three small rotations (about x, y, z, around the points' centroid) of the
    points, unknowns interleaved (``3 i + component``): rotation about x is ``(0, -z, y)``, about y ``(z, 0, -x)``,
    about z ``(-y, x, 0)``."""
    c = np.asarray(points_mm, np.float64) - np.mean(points_mm, 0)
    n = len(c)
    B = np.zeros((3 * n, 6))
    for k in range(3):
        B[k::3, k] = 1.0
    for j, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
        B[a::3, 3 + j] = -c[:, b]
        B[b::3, 3 + j] = c[:, a]
    return B


def elasticity_preconditioner(A, B: np.ndarray | None, max_coarse: int = 2000):
    """One V-cycle of smoothed-aggregation AMG on ``A`` with near-null space ``B``, as a preconditioner for scipy's
    ``cg`` (strength: every connection, theta 0; coarsest level by SuperLU: the default dense pseudo-inverse of a
    coarse level of thousands of unknowns takes minutes). Returns ``(preconditioner, hierarchy)``."""
    import pyamg

    ml = pyamg.smoothed_aggregation_solver(A, B=B, strength=("symmetric", {"theta": 0.0}), max_coarse=max_coarse,
                                          coarse_solver="splu")
    return ml.aspreconditioner(cycle="V"), ml
