"""The one coarse space (:mod:`warpmpm.solvers.coarse_space`) against independent references: the stencil it reads from
the kernels against the quadratic B-spline written out here, its restriction and prolongation against the dense modes,
and the rigid modes' meaning (a rigid motion of a group is exactly one of its modes)."""

import numpy as np
import pytest
import warp as wp

from warpmpm.solvers import MPMModel, SolverConfig
from warpmpm.solvers.coarse_space import CoarseSpace, aggregate_groups, stencils
from warpmpm.solvers.coarse_space_kernels import prolong_nodes, restrict_nodes


@pytest.fixture
def space_model(tiny_case):
    from warpmpm.model import build_model

    return MPMModel(build_model(tiny_case, "psdl"), SolverConfig(device="cpu"))


def bspline_stencil(x_m: np.ndarray, dx: float, grid_shape):
    """The quadratic B-spline of MLS-MPM (Hu et al. 2018), written out independently: base node ``floor(x/dx - 0.5)``,
    weights ``0.5 (1.5 - f)^2, 0.75 - (f - 1)^2, 0.5 (f - 0.5)^2`` per axis."""
    base = np.floor(x_m / dx - 0.5).astype(np.int64)
    f = x_m / dx - base
    w1 = np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=1)
    off = np.array([(a, b, c) for a in range(3) for b in range(3) for c in range(3)])
    w = w1[:, off[:, 0], 0] * w1[:, off[:, 1], 1] * w1[:, off[:, 2], 2]
    ijk = base[:, None, :] + off[None]
    flat = (ijk[..., 0] * grid_shape[1] + ijk[..., 1]) * grid_shape[2] + ijk[..., 2]
    return flat, w, (off[None] - f[:, None, :]) * dx


def test_the_stencil_is_the_quadratic_bspline(space_model):
    m = space_model
    state = m.state()
    x = state.x.numpy().astype(np.float64)
    flat, w, r = stencils(state.x, m.dx_mm * 1e-3, m.grid_shape, m.device)
    f_ref, w_ref, r_ref = bspline_stencil(x, m.dx_mm * 1e-3, m.grid_shape)
    np.testing.assert_array_equal(flat, f_ref)
    np.testing.assert_allclose(w, w_ref, atol=2e-6)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-5)  # partition of unity
    np.testing.assert_allclose(r, r_ref, atol=1e-6 * m.dx_mm * 1e-3)


@pytest.mark.parametrize("modes,size", [("rigid", None), ("rigid", 25.0), ("affine", 25.0)])
def test_restriction_and_prolongation_are_the_dense_modes(space_model, modes, size):
    """``Z^T v`` and ``Z y`` by the kernels equal the products with the dense ``Z`` of the same table."""
    m = space_model
    space = CoarseSpace(m, aggregate_groups(m.particles, size), modes)
    state = m.state()
    table = space.table(state.x)
    Z = space.dense_modes(table)
    dev = space.device_table(table)
    nodes = table["nodes"]
    nn = int(np.prod(m.grid_shape))
    rng = np.random.default_rng(3)
    v = np.zeros((nn, 3), np.float32)
    v[nodes] = rng.normal(size=(nodes.size, 3))
    t = wp.zeros(space.size, dtype=wp.float64, device="cpu")
    args = [dev["nodes"], dev["node_group"], dev["node_share"], dev["centre"], dev["inv_len"]]
    geom = [m.grid_shape[1], m.grid_shape[2], m.dx_mm * 1e-3, int(space.affine)]
    wp.launch(restrict_nodes, nodes.size, args + [wp.array(v, dtype=wp.vec3, device="cpu")] + geom + [t], device="cpu")
    ref = np.einsum("akc,ac->k", Z, v[nodes].astype(np.float64))
    np.testing.assert_allclose(t.numpy(), ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())
    y = rng.normal(size=space.size)
    z = wp.zeros(nn, dtype=wp.vec3, device="cpu")
    wp.launch(prolong_nodes, nodes.size, args + [wp.array(y, dtype=wp.float64, device="cpu")] + geom + [z], device="cpu")
    ref = np.einsum("akc,k->ac", Z, y)
    np.testing.assert_allclose(z.numpy()[nodes], ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())


def test_a_rigid_motion_of_a_group_is_one_of_its_modes(space_model):
    """A rotation of one organ about its centre, sampled on the nodes it alone touches, is its rotation mode: the group's
    motion, not an approximation of it."""
    m = space_model
    space = CoarseSpace(m, m.particles.organ_index, "rigid")
    table = space.table(m.state().x)
    Z = space.dense_modes(table)
    g = 0
    only = np.all((table["node_group"] == g) | (table["node_share"] == 0), axis=1) & (table["node_share"][:, 0] > 0.999)
    y = (table["Xn"][only] - table["centre"][g]) / table["radius"][g]
    omega = np.array([0.2, -0.5, 0.7])
    motion = np.cross(omega, y)  # about the group's centre, in units of its radius
    coef = np.zeros(space.size)
    coef[6 * g + 3:6 * g + 6] = omega
    np.testing.assert_allclose(np.einsum("akc,k->ac", Z[only], coef), motion, atol=1e-12)
