"""Trilinear hexahedral elements (scikit-fem's element matrices on one reference cell) and the elastic solve
(SuperLU below :data:`~warpmpm.truth_fem.config.DIRECT_MAX_DOFS` free unknowns, AMG-preconditioned CG above)."""

from __future__ import annotations


import numpy as np

from ..elastic_amg import elasticity_preconditioner, rigid_body_modes
from ..errors import SimulationError
from .config import DIRECT_MAX_DOFS

__all__ = ["CORNERS", "reference_matrices", "assemble", "ElasticSolver"]


#: Corner offsets (a, b, c) of a hexahedron in the order of :func:`reference_matrices` (corner = a + 2 b + 4 c).
CORNERS = np.array([[a, b, c] for c in (0, 1) for b in (0, 1) for a in (0, 1)])


def reference_matrices(h_mm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stiffness of one box-shaped trilinear hexahedron of edges ``h_mm`` (x, y, z), from scikit-fem.

    Returns ``(K_mu, K_lam, g)``: 24x24 matrices with ``K = mu K_mu + lam K_lam`` (``2 eps(u):eps(v)`` at 3x3x3
    Gauss points, ``div u div v`` at the centre: selective reduced integration), and ``g`` (24,) the load of a unit
    isotropic eigenstrain per unit bulk term, ``f = 3 K e* g`` with ``g = int div v`` at the centre. Unknowns are
    ordered ``3 * corner + component``, corners as :data:`CORNERS`; lengths in mm.
    """
    from skfem import Basis, BilinearForm, ElementHex1, ElementVector, LinearForm, MeshHex, asm
    from skfem.helpers import ddot, div, sym_grad

    hx, hy, hz = (float(v) for v in h_mm)
    mesh = MeshHex.init_tensor(np.array([0.0, hx]), np.array([0.0, hy]), np.array([0.0, hz]))
    e = ElementVector(ElementHex1())
    # scikit-fem's hexahedral rules never go below 2x2x2 points (intorder 0..3 all give 8): the one-point rule at the
    # reference cube's centre is given explicitly, else the volumetric term would be fully integrated and lock
    full = Basis(mesh, e, intorder=3)
    reduced = Basis(mesh, e, quadrature=(np.array([[0.5], [0.5], [0.5]]), np.array([1.0])))

    @BilinearForm
    def dev(u, v, w):
        return 2.0 * ddot(sym_grad(u), sym_grad(v))

    @BilinearForm
    def vol(u, v, w):
        return div(u) * div(v)

    @LinearForm
    def dil(v, w):
        return div(v)

    Km, Kl = asm(dev, full).toarray(), asm(vol, reduced).toarray()
    g = asm(dil, reduced)
    corner = np.rint(mesh.p.T / np.array([hx, hy, hz])).astype(int) @ np.array([1, 2, 4])  # skfem node -> our corner
    order = np.empty(24, dtype=int)
    for node in range(8):
        for comp in range(3):
            order[3 * corner[node] + comp] = full.nodal_dofs[comp, node]
    return Km[np.ix_(order, order)], Kl[np.ix_(order, order)], g[order]


def assemble(element_dofs: np.ndarray, mu: np.ndarray, lam: np.ndarray, K_mu: np.ndarray, K_lam: np.ndarray, n_dofs: int,
             chunk: int = 40_000):
    """The global stiffness (CSR) of elements with unknowns ``element_dofs`` (n_el, 24) and moduli ``mu``, ``lam``
    (Pa), summed chunk by chunk to bound memory."""
    from scipy.sparse import coo_matrix

    K = None
    for s in range(0, len(element_dofs), chunk):
        d = element_dofs[s:s + chunk]
        data = mu[s:s + chunk, None] * K_mu.ravel()[None] + lam[s:s + chunk, None] * K_lam.ravel()[None]
        rows = np.repeat(d, 24, axis=1).ravel()
        cols = np.tile(d, (1, 24)).ravel()
        part = coo_matrix((data.ravel(), (rows, cols)), shape=(n_dofs, n_dofs)).tocsr()
        K = part if K is None else K + part
    return K


class ElasticSolver:
    """``K u = f`` with some unknowns prescribed, factorised or preconditioned once, solved for many right-hand sides.

    ``fixed``: indices of prescribed unknowns. Above :data:`DIRECT_MAX_DOFS` free unknowns: CG with smoothed-
    aggregation AMG (near-null space: the rigid motions of ``points_mm``), else SuperLU.
    """

    def __init__(self, K, fixed: np.ndarray, points_mm: np.ndarray | None = None, rtol: float = 1e-8):
        n = K.shape[0]
        self.fixed = np.unique(np.asarray(fixed, dtype=np.int64))
        free = np.ones(n, dtype=bool)
        free[self.fixed] = False
        self.free = np.nonzero(free)[0]
        self.K = K
        self.Kff = K[self.free][:, self.free].tocsr()
        self.Kfd = K[self.free][:, self.fixed].tocsr()
        self.rtol = rtol
        self.method = "superlu" if len(self.free) <= DIRECT_MAX_DOFS else "amg-cg"
        if self.method == "superlu":
            from scipy.sparse.linalg import splu

            self._lu = splu(self.Kff.tocsc())
        else:
            B = None if points_mm is None else rigid_body_modes(points_mm)[self.free]
            self._M, self._ml = elasticity_preconditioner(self.Kff, B, max_coarse=2000)

    def solve(self, f: np.ndarray, prescribed: np.ndarray, x0: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """Solution ``u`` (all unknowns) with ``u[fixed] = prescribed`` and load ``f``, and ``{residual, iterations}``:
        ``residual = ||K_ff u_f - (f_f - K_fd u_d)|| / ||f_f - K_fd u_d||``."""
        u = np.zeros(self.K.shape[0])
        u[self.fixed] = prescribed
        rhs = f[self.free] - self.Kfd @ prescribed
        norm = float(np.linalg.norm(rhs))
        iters = 0
        if norm == 0.0:
            return u, {"residual": 0.0, "iterations": 0}
        if self.method == "superlu":
            uf = self._lu.solve(rhs)
        else:
            from scipy.sparse.linalg import cg

            count = [0]

            def cb(_):
                count[0] += 1

            uf, info = cg(self.Kff, rhs, x0=None if x0 is None else x0[self.free], rtol=self.rtol, atol=0.0, maxiter=2000,
                          M=self._M, callback=cb)
            iters = count[0]
            if info != 0:
                raise SimulationError(f"finite-element truth: conjugate gradients did not reach {self.rtol:g} in 2000 iterations")
        u[self.free] = uf
        res = float(np.linalg.norm(self.Kff @ uf - rhs)) / norm
        return u, {"residual": res, "iterations": iters}
