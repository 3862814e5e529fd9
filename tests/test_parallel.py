"""Issue 19: one explicit step split over two CPU threads (warpmpm.solvers.parallel) computes the same physics as one."""

import numpy as np
import pytest

from warpmpm.errors import InputError
from warpmpm.scenes import block_model, merge_models
from warpmpm.errors import SimulationError
from warpmpm.solvers import ExplicitConfig, MPMModel, MPMSolver, SolverConfig


def _scene():
    """A soft block thrown at a stiff one (~3000x) across a 6 mm gap: free flight, contact, rotation and the polar
    decomposition all work. The blocks differ in size, so the threads' particle ranges cut through a block."""
    soft = block_model((6, 6, 6), (2, 2, 2), "pancreas")
    stiff = block_model((6, 6, 4), (2, 2, 2), "duodenum", origin_mm=(18.0, 0, 0))
    return merge_models(soft, stiff)


def _run(pm, threads, steps, **cfg):
    m = MPMModel(pm, SolverConfig(device="cpu", cpu_threads=threads, explicit=ExplicitConfig(damping_per_s=0.0, **cfg)))
    s = MPMSolver(m)
    assert s.threads == threads
    a, b = m.state(), m.state()
    rng = np.random.default_rng(3)
    v = rng.normal(0.0, 0.05, (pm.n, 3)).astype(np.float32)
    v[: pm.n // 2, 0] += 3.0  # the soft block (first half of the particles) is thrown at the stiff one
    a.v.assign(v)
    p0 = (m.mass_kg[:, None] * v).sum(0)
    for _ in range(steps):
        s.step(a, b)
        a, b = b, a
    return a, (m.mass_kg[:, None] * a.v.numpy()).sum(0) - p0, np.abs(m.mass_kg[:, None] * v).sum()


@pytest.mark.parametrize("contact,threads", [("sticky", 2), ("sticky", 3), ("sliding", 2)])
def test_split_steps_give_one_threads_motion(contact, threads):
    pm = _scene()
    one, dp1, scale = _run(pm, 1, 300, contact=contact, bonded=())
    two, dp2, _ = _run(pm, threads, 300, contact=contact, bonded=())
    moved = np.linalg.norm(one.positions_mm() - pm.positions_mm, axis=1)
    assert moved.mean() > 0.5  # the scene does move (mm)
    assert np.abs(one.F.numpy() - np.eye(3)).max() > 0.02  # and deforms
    # the grid sums are added in another order: float32 rounding, not bit for bit
    assert np.abs(two.positions_mm() - one.positions_mm()).max() < 1e-3
    assert np.abs(two.F.numpy() - one.F.numpy()).max() < 1e-4
    # momentum is conserved by the split step as by the whole one (no particle's scatter lost or doubled)
    assert np.linalg.norm(dp2) < 1e-4 * scale and np.linalg.norm(dp1) < 1e-4 * scale


def test_a_bad_particle_of_the_second_thread_is_named():
    pm = block_model((4, 4, 4), (2, 2, 2), "pancreas")
    m = MPMModel(pm, SolverConfig(device="cpu", cpu_threads=2))
    s = MPMSolver(m)
    a, b = m.state(), m.state()
    carry = np.zeros((pm.n, 3), dtype=np.float32)
    carry[pm.n - 3] = np.nan  # a position update of one particle of the second thread's range goes bad, and no other
    a.x_carry.assign(carry)
    with pytest.raises(SimulationError, match=rf"non-finite.*step 0, particle {pm.n - 3} "):
        s.step(a, b)


@pytest.mark.parametrize("threads", [1, 2])
def test_the_sparse_grid_update_is_the_dense_one_node_for_node(threads):
    """The CPU grid update visits only the node blocks that hold mass (kernels.grid_update_blocks): with the soft
    block flying 20 mm up past the stiff one (blocks of 12.7 mm fill and empty, the ones it leaves with mass in
    their last layer of nodes) and spinning, every position, F and grid
    velocity is the dense update's to the bit."""
    pm = _scene()
    out = {}
    for sparse in (True, False, "toggled"):
        m = MPMModel(pm, SolverConfig(device="cpu", cpu_threads=threads, explicit=ExplicitConfig(damping_per_s=0.0, bonded=())))
        s = MPMSolver(m)
        assert s.sparse_update == (threads == 1)  # the default on a one-thread CPU step
        s.sparse_update = sparse is True
        a, b = m.state(), m.state()
        v = np.zeros((pm.n, 3), dtype=np.float32)
        soft = slice(0, pm.n // 2)
        r = pm.positions_mm[soft] - pm.positions_mm[soft].mean(0)
        v[soft] = np.array([0.0, 12.0, 0.0]) + np.cross([0.0, 0.0, 400.0], r * 1e-3)  # m/s: 20 mm up, 0.6 rad about z
        a.v.assign(v)
        seen = set()
        for step in range(300):
            if sparse == "toggled":  # dense from step 0, sparse from 100 (after dense steps left no block record), dense again
                s.sparse_update = 100 <= step < 200
            s.step(a, b)
            a, b = b, a
            if sparse is True and step % 10 == 0:
                seen.add(tuple(np.flatnonzero(s._updated.numpy())))
        out[sparse] = (a.x.numpy(), a.F.numpy(), s.grid_v.numpy(), seen)
    assert len(out[True][3]) > 2  # the set of blocks holding mass changed during the run
    x_dense, F_dense, v_dense, _ = out[False]
    assert (a.positions_mm()[soft, 1] - pm.positions_mm[soft, 1]).mean() > 15.0  # the soft block did fly (mm)
    for variant in (True, "toggled"):
        x_sparse, F_sparse, v_sparse, _ = out[variant]
        assert np.array_equal(x_sparse, x_dense) and np.array_equal(F_sparse, F_dense)
        assert np.array_equal(v_sparse, v_dense)


def test_the_sparse_update_is_refused_where_there_are_no_block_stamps():
    """Sliding contact keeps a grid per organ and the dense update: asking it for the sparse one is a clear error,
    not an index out of range."""
    m = MPMModel(_scene(), SolverConfig(device="cpu", explicit=ExplicitConfig(contact="sliding", bonded=())))
    s = MPMSolver(m)
    assert not s.sparse_update
    s.sparse_update = False
    with pytest.raises(InputError, match="sticky contact only"):
        s.sparse_update = True


def test_switching_back_to_the_sparse_update_clears_what_the_dense_steps_left():
    """Dense steps keep no record of the blocks that held mass: the first sparse step after them visits every block,
    so where the particles were (moved away 15 mm, more than a block, between the two steps) the grid velocity is
    zero as the dense update leaves it, not what the last dense step left there."""
    pm = _scene()
    grids = {}
    for switch in (False, True):
        m = MPMModel(pm, SolverConfig(device="cpu", cpu_threads=1, explicit=ExplicitConfig(damping_per_s=0.0, bonded=())))
        s = MPMSolver(m)
        s.sparse_update = False
        a, b = m.state(), m.state()
        a.v.assign(np.tile(np.array([0.0, 1.0, 0.0], dtype=np.float32), (pm.n, 1)))
        for _ in range(5):
            s.step(a, b)
            a, b = b, a
        a.x.assign(a.x.numpy() + np.array([0.0, 0.015, 0.0], dtype=np.float32))  # m: every particle 15 mm further
        s.sparse_update = switch
        s.step(a, b)
        grids[switch] = s.grid_v.numpy()
    assert np.abs(grids[False]).max() > 0.5  # the grid moves (m/s)
    assert np.array_equal(grids[True], grids[False])


@pytest.mark.parametrize("threads", [2, 3])
def test_a_split_quasistatic_solve_gives_one_threads_equilibrium(threads):
    """The quasi-static solver's conjugate-gradient products (``apply_stiffness``: each thread scatters into its own
    copy of the product, ``finish_matvec`` adds them) and particle moves split over threads: a 3 degree rotated slice
    of a 16 x 16 x 12 mm pancreas block (384 particles, 4 Newton and 410-430 CG iterations) settles where one thread's
    solve does (measured: within 7.5e-6 mm of a 0.52 mm motion; the copies add in another order). And a particle that
    would leave the grid is named by its index in the whole model, from any thread."""
    import math

    from warpmpm.driving import SliceDrivenEstimator
    from warpmpm.slices import DrivingSlice, InPlaneAffine
    from warpmpm.targets import affine_targets

    pm = block_model((8, 8, 6), (2.0, 2.0, 2.0), "pancreas")
    sl = [DrivingSlice("axial", 3)]
    a = math.radians(3.0)
    idx, tg = affine_targets(pm, pm.positions_mm, sl, [InPlaneAffine([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])],
                             pm.positions_mm.mean(0))
    res = {}
    for t in (1, threads):
        est = SliceDrivenEstimator(pm, sl, solver_config=SolverConfig(device="cpu", method="quasistatic", cpu_threads=t), extra_points_mm=tg)
        assert est.quasistatic.threads == t
        res[t] = est.estimate(tg)
        assert res[t].settled and res[t].linear_iterations > 20
    moved = np.linalg.norm(res[1].positions_mm - pm.positions_mm, axis=1)
    assert moved.max() > 0.3
    assert np.abs(res[threads].positions_mm - res[1].positions_mm).max() < 1e-3

    qs = est.quasistatic
    state = est.state
    x = state.x.numpy()
    last = pm.n - 5  # in the last thread's range: named by its index in the whole model, not in the thread's range
    x[last, 2] = qs._x_max[2] - 0.1 * qs._dx  # at the grid's edge; a move of half a cell along z takes it past
    state.x.assign(x)
    qs.du.assign(np.tile(np.array([0.0, 0.0, 0.5 * qs._dx], np.float32), (qs.n_nodes, 1)))
    qs._move(state, 1.0, 1)
    with pytest.raises(SimulationError, match=rf"particle {last} \(pancreas\) would leave the simulation grid"):
        qs._check()
    qs._check()  # the flags were cleared
