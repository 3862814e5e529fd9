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

from .errors import InputError
from .model import ParticleModel


def fem_displacement_mm(model: ParticleModel, driven: np.ndarray, targets_mm: np.ndarray) -> np.ndarray:
    """Equilibrium displacement (N, 3, mm) of every particle of a lattice model (one particle per voxel of
    its grid, e.g. :func:`warpmpm.scenes.block_model`) with the ``driven`` particles moved to ``targets_mm``.

    Raises :class:`InputError` when the particles do not fill a box of the lattice (the mesh would have holes).
    """
    from skfem import Basis, BilinearForm, ElementHex1, ElementVector, MeshHex, asm, condense, solve
    from skfem.helpers import ddot, div, sym_grad

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
    axes = [np.arange(n) * s for n, s in zip(shape, sp)]
    mesh = MeshHex.init_tensor(*axes)
    node_ijk = np.rint(mesh.p.T / sp).astype(int)
    node_particle = index[tuple(node_ijk.T)]
    element = ElementVector(ElementHex1())
    full = Basis(mesh, element, intorder=3)
    reduced = Basis(mesh, element, intorder=1)
    lam_p, mu_p = model.per_particle("lam_pa"), model.per_particle("mu_pa")
    corners = node_particle[mesh.t]  # (8, n_elements)
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
    u_grid = u_world @ R  # components along the image axes
    particle_node = np.empty(model.n, dtype=np.int64)
    particle_node[node_particle] = np.arange(mesh.p.shape[1])
    dofs = full.nodal_dofs[:, particle_node[driven]]  # (3, n_driven)
    x = np.zeros(K.shape[0])
    x[dofs] = u_grid.T
    u = solve(*condense(K, np.zeros(K.shape[0]), x=x, D=dofs.ravel()))
    u_nodes = u[full.nodal_dofs].T  # (n_nodes, 3) along the grid axes
    out = np.empty((model.n, 3))
    out[node_particle] = u_nodes @ R.T
    return out
