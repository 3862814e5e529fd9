"""An independent finite-element reference for the MPM equilibrium (scikit-fem).

The ground truth of every protocol is simulated by the same MPM, so an error of the physics is invisible
to it. This module solves the same problem another way: small-strain linear elasticity on trilinear
hexahedra whose nodes are the particles of a lattice model (each element joins eight neighbouring
particles), the same Lame parameters, the driven particles a Dirichlet condition at their targets and
everything else traction-free. Locking-free: the volumetric term ``lambda div u div v`` is integrated at
one point per element (selective reduced integration), the deviatoric ``2 mu eps(u):eps(v)`` at 2x2x2.

Interface elements (corners in two organs) take the mean of the corner particles' Lame parameters.
"""

from __future__ import annotations

import numpy as np

from .elastic_amg import elasticity_preconditioner, rigid_body_modes
from .errors import InputError
from .model import ParticleModel

__all__ = ["DIRECT_MAX_DOFS", "fem_displacement_mm"]


#: Free degrees of freedom above which :func:`fem_displacement_mm` solves iteratively (conjugate gradients with an
#: algebraic-multigrid preconditioner, ``pyamg``) instead of by a sparse direct factorisation: at 2x refinement of
#: the 40 mm benchmark block (187k unknowns) SuperLU had not finished after 6 minutes.
DIRECT_MAX_DOFS = 60_000


def fem_displacement_mm(model: ParticleModel, driven: np.ndarray, targets_mm: np.ndarray, refine: int = 1) -> np.ndarray:
    """Equilibrium displacement (N, 3, mm) of every particle of a lattice model (one particle per voxel of
    its grid, e.g. :func:`warpmpm.scenes.block_model`) with the ``driven`` particles moved to ``targets_mm``.

    ``refine``: each hexahedron between particles is cut into ``refine^3`` (nodes every ``spacing / refine``); an
    element keeps the material of the particle element it lies in, and a new node is driven where every particle
    node around it is (its target interpolated trilinearly from theirs: the exact motion for an affine slice
    motion). The answer is still read at the particles. Comparing ``refine=1`` with 2 tells how far the reference
    itself is from the continuum (measured in ``benchmarks/fem_reference.py --fem-convergence``). Systems above
    :data:`DIRECT_MAX_DOFS` unknowns are solved by multigrid-preconditioned conjugate gradients (``pyamg``).

    Raises :class:`InputError` when the particles do not fill a box of the lattice (the mesh would have holes),
    or for a refinement that is not a positive integer.
    """
    from skfem import Basis, BilinearForm, ElementHex1, ElementVector, MeshHex, asm, condense, solve
    from skfem.helpers import ddot, div, sym_grad

    if not isinstance(refine, (int, np.integer)) or isinstance(refine, bool) or refine < 1:
        raise InputError(f"FEM refinement must be a positive integer, got {refine!r}")
    r = int(refine)
    g = model.particle_grid
    ijk = np.rint(g.world_to_index(model.positions_mm)).astype(int)
    lo, hi = ijk.min(0), ijk.max(0)
    shape = hi - lo + 1
    if np.prod(shape) != model.n or np.any(shape < 2):
        raise InputError("the FEM reference needs a model whose particles fill a box of its lattice (a block scene)")
    index = np.full(tuple(shape), -1, dtype=np.int64)
    index[tuple((ijk - lo).T)] = np.arange(model.n)
    # mesh nodes in lattice units, mapped back to world mm below (the block's axes are the grid's)
    sp = np.asarray(g.spacing_mm)
    fine = (shape - 1) * r + 1
    mesh = MeshHex.init_tensor(*[np.arange(n) * s / r for n, s in zip(fine, sp)])
    node_f = np.rint(mesh.p.T / (sp / r)).astype(int)  # fine lattice index of every mesh node
    element = ElementVector(ElementHex1())
    full = Basis(mesh, element, intorder=3)
    # scikit-fem's hexahedral rules never have fewer than 2x2x2 points (intorder 0..3 all give 8): the one-point rule
    # at the reference cube's centre is given explicitly (before 2026-12-03 ``intorder=1`` integrated it fully)
    reduced = Basis(mesh, element, quadrature=(np.array([[0.5], [0.5], [0.5]]), np.array([1.0])))
    lam_p, mu_p = model.per_particle("lam_pa"), model.per_particle("mu_pa")
    # each element takes the mean Lame parameters of the eight particles of the particle element it lies in
    centre_f = node_f[mesh.t].mean(0)  # (n_elements, 3), fine lattice units
    cell = np.minimum(np.floor(centre_f / r).astype(int), shape - 2)
    offsets = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    corners = index[tuple((cell[None, :, :] + offsets[:, None, :]).transpose(2, 0, 1))]  # (8, n_elements)
    lam_e, mu_e = lam_p[corners].mean(0), mu_p[corners].mean(0)

    @BilinearForm
    def deviatoric(u, v, w):
        return 2.0 * w.mu * ddot(sym_grad(u), sym_grad(v))

    @BilinearForm
    def volumetric(u, v, w):
        return w.lam * div(u) * div(v)

    K = (asm(deviatoric, full, mu=np.repeat(mu_e[:, None], full.X.shape[-1], axis=1))
         + asm(volumetric, reduced, lam=np.repeat(lam_e[:, None], reduced.X.shape[-1], axis=1)))
    # world displacement of the driven particles, expressed along the grid's axes
    R = g.direction_matrix
    u_world = np.asarray(targets_mm, dtype=np.float64) - model.positions_mm[driven]
    u_particle = np.zeros((model.n, 3))
    u_particle[driven] = u_world @ R  # components along the image axes
    is_driven = np.zeros(model.n, dtype=bool)
    is_driven[driven] = True
    # a mesh node is driven where every particle node its trilinear interpolation uses is
    q = node_f / r
    base = np.minimum(np.floor(q).astype(int), shape - 1)
    frac = q - base
    node_driven = np.ones(len(node_f), dtype=bool)
    node_u = np.zeros((len(node_f), 3))
    for off in offsets:
        w = np.prod(np.where(off == 1, frac, 1.0 - frac), axis=1)
        use = w > 1e-12
        corner = np.minimum(base + off, shape - 1)
        p_idx = index[tuple(corner.T)]
        node_driven &= ~use | is_driven[p_idx]
        node_u += (w * use)[:, None] * u_particle[p_idx]
    dofs = full.nodal_dofs[:, node_driven]  # (3, n_driven_nodes)
    x = np.zeros(K.shape[0])
    x[dofs] = node_u[node_driven].T
    Kc, bc, xc, I = condense(K, np.zeros(K.shape[0]), x=x, D=dofs.ravel())
    if len(I) > DIRECT_MAX_DOFS:
        x[I] = _amg_cg(Kc, bc, mesh.p[:, :].T, full.nodal_dofs, I)
        u = x
    else:
        u = solve(Kc, bc, xc, I)
    u_nodes = u[full.nodal_dofs].T  # (n_nodes, 3) along the grid axes
    at_particle = np.full(tuple(fine), -1, dtype=np.int64)
    at_particle[tuple(node_f.T)] = np.arange(len(node_f))
    out = np.empty((model.n, 3))
    out[index[tuple((ijk - lo).T)]] = u_nodes[at_particle[tuple(((ijk - lo) * r).T)]] @ R.T
    return out


def _amg_cg(K, b, points, nodal_dofs, free, rtol: float = 1e-10) -> np.ndarray:
    """Solve the condensed system ``K x = b`` (unknowns ``free`` of the full system) by conjugate gradients
    preconditioned with smoothed-aggregation multigrid whose near-null space is the six rigid motions."""
    try:
        import pyamg  # noqa: F401
    except ImportError as exc:
        raise InputError("a FEM reference this large needs pyamg (pip install pyamg); "
                         f"or use a smaller block / refinement (at most {DIRECT_MAX_DOFS} unknowns solve directly)") from exc
    from scipy.sparse.linalg import cg

    n_nodes = points.shape[0]
    comp = np.empty(3 * n_nodes, dtype=np.int64)
    node = np.empty(3 * n_nodes, dtype=np.int64)
    for k in range(3):
        comp[nodal_dofs[k]] = k
        node[nodal_dofs[k]] = np.arange(n_nodes)
    B = rigid_body_modes(points)[3 * node + comp][free]  # the system's unknowns in scikit-fem's order
    M, _ = elasticity_preconditioner(K.tocsr(), B, max_coarse=2000)
    x, info = cg(K, b, rtol=rtol, atol=0.0, maxiter=5000, M=M)
    if info != 0:
        from .errors import SimulationError

        raise SimulationError(f"FEM reference: conjugate gradients did not converge in 5000 iterations (code {info})")
    return x
