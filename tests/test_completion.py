"""The completion solve (warpmpm.solvers.completion): its stiffness against the analytic strain energy, a seen
translation carried through the tissue to an organ no plane crosses, the held back, honest convergence."""

import numpy as np
import pytest

from warpmpm.errors import InputError
from warpmpm.experiment.case import prepare_case
from warpmpm.experiment.config import CaseConfig
from warpmpm.slices import driven_indices
from warpmpm.solvers.completion import CompletionConfig, CompletionModel, complete


@pytest.fixture(scope="module")
def phantom():
    prep = prepare_case(CaseConfig(phantom_resolution=3.0, device="cpu"))
    return prep, prep.model("psdl")


def test_stiffness_gives_the_strain_energy_of_a_homogeneous_deformation(phantom):
    """Quadratic B-splines reproduce a linear field exactly, so u_a = G x_a at the nodes has the strain eps = sym(G)
    at every point: 1/2 u^T K u must be sum_p V (lam/2 tr(eps)^2 + mu eps:eps), and zero for a rotation."""
    prep, model = phantom
    cm = CompletionModel(prep.case, "amos", model, CompletionConfig(cell_mm=8.0))
    K = cm._to_csr(cm.stiffness_stencil)
    x = cm.node_positions_mm()
    rng = np.random.default_rng(3)
    G = 1e-2 * rng.normal(size=(3, 3))
    eps = 0.5 * (G + G.T)
    u = (x @ G.T).ravel()
    energy = 0.5 * u @ (K @ u)
    expected = float(np.sum(cm.point_volume_mm3 * (0.5 * cm.point_lam_pa * np.trace(eps) ** 2 + cm.point_mu_pa * np.sum(eps * eps))))
    assert energy == pytest.approx(expected, rel=1e-4)
    W = 1e-2 * np.array([[0.0, -1.0, 0.4], [1.0, 0.0, -0.7], [-0.4, 0.7, 0.0]])  # an infinitesimal rotation: no strain
    r = (x @ W.T).ravel()
    assert 0.5 * r @ (K @ r) < 1e-8 * expected


def test_a_seen_translation_moves_the_organ_no_plane_crosses(phantom):
    """Nothing is held in the phantom (no bone labelled, the wall free): a translation seen on one sagittal plane must
    move every organ with it through the tissue, the unseen ones included, and leave the direction no plane measures
    (left-right) still. Without the tissue between them the unseen organ would not move."""
    prep, model = phantom
    s = prep.resolve_slices(model, f"sagittal:{int(np.median(model.voxel_ijk[model.organ_slice('pancreas'), 0]))}")
    idx = driven_indices(model, s)
    seen = {o for k, o in enumerate(model.organs) if np.count_nonzero(model.organ_index[idx] == k) >= 10}
    unseen = [o for o in model.organs if o not in seen]
    assert "pancreas" in seen and unseen, (seen, unseen)
    t = np.array([0.0, -2.0, -6.0])  # anterior and inferior: in the sagittal plane
    x = model.positions_mm
    P = np.diag([0.0, 1.0, 1.0])
    cm = CompletionModel(prep.case, "amos", model, CompletionConfig(observed_first=False, rtol=1e-8))
    r = complete(cm, idx, x[idx] + t, np.tile(P, (len(idx), 1, 1)), x + t)
    assert r.converged
    d = r.positions_mm - x
    for o in model.organs:
        mean = d[model.organ_slice(o)].mean(0)
        assert np.allclose(mean, t, atol=0.05 * np.linalg.norm(t)), (o, mean)
    assert np.abs(d[:, 0]).max() < 1e-3


def test_the_held_back_does_not_move(phantom):
    """With the posterior wall held, the wall's points stay within a tenth of the seen motion while the seen organs
    keep theirs."""
    prep, model = phantom
    s = prep.resolve_slices(model, f"sagittal:{int(np.median(model.voxel_ijk[model.organ_slice('pancreas'), 0]))}")
    idx = driven_indices(model, s)
    x = model.positions_mm
    t = np.array([0.0, 0.0, -8.0])
    cm = CompletionModel(prep.case, "amos", model, CompletionConfig(hold_posterior_wall=True))
    assert cm.n_anchors > 0
    r = complete(cm, idx, x[idx] + t, None, x + t)
    u, _ = cm.solve(t[None] * np.ones((len(idx), 1)), (t[None] * np.ones((len(cm._plan["idx"]) - len(idx), 1))))
    wall = cm.anchor_points_mm
    import warp as wp

    xc = wp.array(((wall - cm.origin_mm) / cm.dx).astype(np.float32), dtype=wp.vec3)
    moved = np.linalg.norm(cm.particle_displacements(u, xc), axis=1)
    assert np.median(moved) < 0.1 * np.linalg.norm(t)
    assert np.allclose(r.positions_mm[idx] - x[idx], t, atol=1e-6)  # observed first: the seen particles keep their motion


def test_a_solve_stopped_short_is_not_converged(phantom):
    prep, model = phantom
    s = prep.resolve_slices(model, f"sagittal:{int(np.median(model.voxel_ijk[model.organ_slice('pancreas'), 0]))}")
    idx = driven_indices(model, s)
    x = model.positions_mm
    cm = CompletionModel(prep.case, "amos", model, CompletionConfig(max_iterations=1))
    r = complete(cm, idx, x[idx] + np.array([0.0, 0.0, -5.0]), None, x + np.array([0.0, 0.0, -5.0]))
    assert not r.converged and r.residual > cm.config.rtol


@pytest.mark.parametrize("bad", [{"cell_mm": 0.0}, {"off_plane_stiffness": -1.0}, {"materials": "steel"}, {"point_mm": float("nan")}])
def test_bad_config_is_refused(bad):
    with pytest.raises(InputError):
        CompletionConfig(**bad)


def test_tissue_seen_on_a_plane_carries_an_organ_no_plane_crosses(phantom):
    """With no organ observed at all, a translation of the tissue on one plane (tissue_motion) must move every organ,
    off the plane, with it through the tissue (nothing is held in the phantom: the equilibrium is the translation);
    with tissue_stiffness 0 nothing moves."""
    prep, model = phantom
    x = model.positions_mm
    t = np.array([0.0, 0.0, -5.0])
    z0 = float(np.median(x[:, 2]))

    def tissue_motion(pts):
        on = np.nonzero(np.abs(pts[:, 2] - z0) < 3.0)[0]
        return on, np.tile(t, (len(on), 1)), np.tile(np.eye(3), (len(on), 1, 1))

    none = np.zeros(0, np.int64)
    moved = {}
    for k in (0.0, 100.0):
        cm = CompletionModel(prep.case, "amos", model, CompletionConfig(tissue_stiffness=k, rtol=1e-8))
        r = complete(cm, none, np.zeros((0, 3)), None, x.copy(), tissue_motion=tissue_motion)
        moved[k] = {o: (r.positions_mm - x)[model.organ_slice(o)].mean(0) for o in model.organs}
    for o in model.organs:
        assert np.allclose(moved[0.0][o], 0.0, atol=1e-6)
        assert np.allclose(moved[100.0][o], t, atol=0.02 * np.linalg.norm(t)), (o, moved[100.0][o])


def test_the_reduced_completion_equals_the_full_solve_on_an_affine_observation(phantom):
    """The precomputed responses (ReducedCompletion) are the full solve's on any observation that is an affine motion of
    each seen organ: a small rotation plus translation seen on a sagittal plane."""
    from warpmpm.solvers.completion import ReducedCompletion

    prep, model = phantom
    s = prep.resolve_slices(model, f"sagittal:{int(np.median(model.voxel_ijk[model.organ_slice('pancreas'), 0]))}")
    idx = driven_indices(model, s)
    x = model.positions_mm
    c = x.mean(0)
    W = np.array([[0.0, -0.02, 0.01], [0.02, 0.0, -0.015], [-0.01, 0.015, 0.0]])
    moved = x + (x - c) @ W.T + np.array([0.5, -2.0, -6.0])
    P = np.tile(np.diag([0.0, 1.0, 1.0]), (len(idx), 1, 1))
    cfg = CompletionConfig(rtol=1e-10, response_rtol=1e-10, max_iterations=1000)
    full = complete(CompletionModel(prep.case, "amos", model, cfg), idx, moved[idx], P, moved)
    reduced = ReducedCompletion(CompletionModel(prep.case, "amos", model, cfg), idx, P)
    r = reduced.complete(moved[idx], moved)
    assert np.abs(r.positions_mm - full.positions_mm).max() < 1e-3
    assert np.abs(r.positions_mm - x).max() > 1.0  # it moved


@pytest.mark.parametrize("through_plane", ["copy", "equilibrium"])
def test_a_seen_organ_takes_the_copys_through_plane_motion_by_default(phantom, through_plane):
    """One sagittal plane sees the pancreas squeezed 5 % in plane (anterior-posterior and superior-inferior). Nothing
    measures left-right: by default (``through_plane="copy"``) every particle of a seen organ takes the copy's motion
    there (none); the equilibrium would bulge the nearly incompressible organ left-right instead (measured worse than
    the copy on the finite-element truths)."""
    prep, model = phantom
    s = prep.resolve_slices(model, f"sagittal:{int(np.median(model.voxel_ijk[model.organ_slice('pancreas'), 0]))}")
    idx = driven_indices(model, s)
    x = model.positions_mm
    pan = model.organ_slice("pancreas")
    c = x[pan].mean(0)
    squeeze = np.diag([1.0, 0.95, 0.95])
    moved = c + (x - c) @ squeeze.T
    P = np.tile(np.diag([0.0, 1.0, 1.0]), (len(idx), 1, 1))
    cm = CompletionModel(prep.case, "amos", model, CompletionConfig(through_plane=through_plane))
    r = complete(cm, idx, moved[idx], P, moved)
    seen = np.zeros(model.n, bool)
    seen[pan] = True
    lr = np.abs(r.positions_mm[seen, 0] - x[seen, 0])
    assert np.allclose(r.positions_mm[idx, 1:], moved[idx, 1:], atol=1e-6)  # the observation, either way
    if through_plane == "copy":
        assert lr.max() < 1e-6
    else:
        assert lr.max() > 0.05
