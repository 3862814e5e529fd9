"""Issue 17 (in part): the independent finite-element reference, and the MPM checked against it."""

import math

import numpy as np
import pytest

from warpmpm.driving import ConvergenceConfig, DriveConfig, SliceDrivenEstimator
from warpmpm.errors import InputError
from warpmpm.fem import fem_displacement_mm
from warpmpm.scenes import block_model
from warpmpm.slices import DrivingSlice, InPlaneAffine
from warpmpm.solvers import ExplicitConfig, SolverConfig
from warpmpm.targets import affine_targets


def test_fem_moves_a_free_block_rigidly_with_a_translated_slice():
    m = block_model((6, 5, 7), (2.0, 2.0, 2.0), "pancreas")
    idx = np.nonzero(m.voxel_ijk[:, 2] == 3)[0]
    u = fem_displacement_mm(m, idx, m.positions_mm[idx] + [1.0, -2.0, 0.5])
    np.testing.assert_allclose(u, np.tile([1.0, -2.0, 0.5], (m.n, 1)), atol=1e-8)


@pytest.mark.parametrize("refine", [1, 2])
def test_fem_turns_a_free_block_rigidly_with_an_infinitesimally_rotated_slice(refine):
    """u = theta (-y, x, 0) on one slice is a zero-energy motion of linear elasticity, so the whole block takes it
    exactly, on the particles' mesh and on a finer one (whose nodes between the driven particles must take the
    interpolated motion: left free, or driven to zero, they would bend the slice)."""
    m = block_model((6, 5, 7), (2.0, 2.0, 2.0), "pancreas")
    c = m.positions_mm.mean(0)
    theta = 0.01
    idx = np.nonzero(m.voxel_ijk[:, 2] == 3)[0]
    rot = lambda p: theta * np.stack([-(p[:, 1] - c[1]), p[:, 0] - c[0], np.zeros(len(p))], axis=1)  # noqa: E731
    u = fem_displacement_mm(m, idx, m.positions_mm[idx] + rot(m.positions_mm[idx]), refine=refine)
    np.testing.assert_allclose(u, rot(m.positions_mm), atol=1e-7)


def test_fem_refuses_a_bad_refinement():
    m = block_model((3, 3, 3), (2.0, 2.0, 2.0), "pancreas")
    with pytest.raises(InputError, match="refinement"):
        fem_displacement_mm(m, np.arange(9), m.positions_mm[:9], refine=0)


def test_fem_far_layers_follow_and_the_answer_is_mirror_symmetric():
    """Scaling the middle slice of a nearly incompressible block (nu = 0.49): the far layers still move in plane,
    and the answer is symmetric about the slice (in-plane equal, through-plane opposite)."""
    m = block_model((8, 8, 9), (2.0, 2.0, 2.0), "pancreas")
    idx = np.nonzero(m.voxel_ijk[:, 2] == 4)[0]
    c = m.positions_mm.mean(0)
    tg, = [affine_targets(m, m.positions_mm, [DrivingSlice("axial", 4)], [InPlaneAffine(np.eye(2) * 1.05)], c)[1]]
    u = fem_displacement_mm(m, idx, tg)
    top, bottom = m.voxel_ijk[:, 2] == 8, m.voxel_ijk[:, 2] == 0
    assert np.linalg.norm(u[top][:, :2], axis=1).mean() > 0.02  # measured 0.025 mm (the slice moves up to 0.35)
    np.testing.assert_allclose(u[top][:, :2], u[bottom][:, :2], atol=1e-8)
    np.testing.assert_allclose(u[top][:, 2], -u[bottom][:, 2], atol=1e-8)


def test_fem_refuses_a_scene_with_holes(tiny_model):
    with pytest.raises(InputError, match="fill a box"):
        fem_displacement_mm(tiny_model, np.arange(3), tiny_model.positions_mm[:3])


A3 = math.radians(3.0)


def _block_scene(size, k, load):
    """A pancreas block of 2 mm particles whose axial slice ``k`` is moved by ``load``: the model, the slice, its
    targets and the relative L2 error of given positions' non-driven displacement against the FEM's."""
    m = block_model(size, (2.0, 2.0, 2.0), "pancreas")
    sl = [DrivingSlice("axial", k)]
    idx, tg = affine_targets(m, m.positions_mm, sl, [load], m.positions_mm.mean(0))
    u_fem = fem_displacement_mm(m, idx, tg)
    free = np.ones(m.n, bool)
    free[idx] = False

    def rel_error(positions_mm):
        u = positions_mm - m.positions_mm
        return float(np.linalg.norm(u[free] - u_fem[free]) / np.linalg.norm(u_fem[free]))

    return m, sl, tg, rel_error


def test_mpm_matches_fem_for_a_rotated_slice_once_the_body_has_settled():
    """3 degree in-plane rotation of the middle slice of a 20 mm pancreas block. Measured: 3.2 % relative L2
    difference of the non-driven displacement once settled (468 steps, adaptive damping; 3.1 % at a fixed
    damping 1); 28 % at the paper's stopping rule, which returns before the far layers have followed.
    Tolerance: twice the settled figure."""
    m, sl, tg, rel_error = _block_scene((10, 10, 10), 5, InPlaneAffine([[math.cos(A3), -math.sin(A3)], [math.sin(A3), math.cos(A3)]]))
    est = SliceDrivenEstimator(m, sl, solver_config=SolverConfig(device="cpu"), extra_points_mm=tg,
                               convergence=ConvergenceConfig(wait_settled=True, max_steps=6000))
    res = est.estimate(tg)
    assert res.settled and rel_error(res.positions_mm) < 0.065


def test_adaptive_damping_settles_a_rotated_block_in_a_fraction_of_the_steps():
    """The adaptive (critical) damping against the fixed over-damped factor 4 on the rotated 20 mm block, same
    steps. Measured after 300 steps: 3.8 % off the FEM with the adaptive rule, 16.4 % with the fixed one (it
    reaches 3.8 % only at step 650). Broken adaptation (the factor stuck at its first value) is the fixed run."""
    m, sl, tg, rel_error = _block_scene((10, 10, 10), 5, InPlaneAffine([[math.cos(A3), -math.sin(A3)], [math.sin(A3), math.cos(A3)]]))
    rel = {}
    for rule in ("adaptive", "fixed"):
        est = SliceDrivenEstimator(m, sl, solver_config=SolverConfig(device="cpu", explicit=ExplicitConfig(damping_rule=rule)), extra_points_mm=tg,
                                   convergence=ConvergenceConfig(th_v=1e-12, th_d=12, max_steps=300))
        with pytest.warns(RuntimeWarning, match="did not converge"):
            res = est.estimate(tg)
        rel[rule] = rel_error(res.positions_mm)
    assert rel["adaptive"] < 0.06 and rel["fixed"] > 0.12, rel


def test_settled_mode_does_not_drift_on_a_scaled_slice():
    """A 32 mm block whose middle slice is scaled 1.05, run on past settling (2,000 steps) in the settled mode
    (adaptive damping, PD drive). Measured: 22.5 % off the FEM at step 500 and at step 2,000; with the PID drive it
    replaced, 42.4 % growing to 45.3 % (the integral pushes the driven layer onto targets the grid reaches only by
    stretching its neighbours, and the body creeps for as long as it runs). Against the fully integrated (locking)
    FEM used before 2026-12-03 the same runs read 11.7 % and 16.1-16.7 %: a volume change of the nearly
    incompressible pancreas (lambda / mu = 49) is where the locking reference was too stiff."""
    m, sl, tg, rel_error = _block_scene((16, 16, 17), 8, InPlaneAffine(np.eye(2) * 1.05))
    err = {}
    for name, ki in (("pd", None), ("pid", 0.02)):
        rec = {}

        def cb(est, step, rel, rms):
            if step in (500, 2000):
                rec[step] = rel_error(est.positions_mm())

        settle = ConvergenceConfig(wait_settled=True, th_v=1e-12, th_d=12, max_steps=2000)  # runs on to 2,000 steps
        est = SliceDrivenEstimator(m, sl, solver_config=SolverConfig(device="cpu"), drive_config=DriveConfig(ki_ratio=ki),
                                   extra_points_mm=tg, convergence=settle, callback=cb)
        with pytest.warns(RuntimeWarning, match="did not converge"):
            est.estimate(tg)
        err[name] = rec
    assert err["pd"][2000] < 0.24 and abs(err["pd"][2000] - err["pd"][500]) < 0.003, err
    assert err["pid"][2000] > err["pid"][500] + 0.004, err  # what the PD drive removed
