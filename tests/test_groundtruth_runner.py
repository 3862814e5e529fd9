"""Issue 5: ground truth, metrics, baselines and the run_case entry point."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import SimpleITK as sitk

from warpmpm.groundtruth import PAPER_DEFORMATIONS, contact_ground_truth, paper_affine, paper_ground_truth, perturb_materials
from warpmpm.images import crop_to_organs
from warpmpm.metrics import dice, evaluate, particle_errors_mm
from warpmpm.model import build_model
from warpmpm.experiment.baselines import register_volumes_affine
from warpmpm.cli import run_main as main
from warpmpm.slices import in_plane_axes
from warpmpm.solvers import SolverConfig

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def test_paper_affine_table():
    # closed form of R(r) G(g) S(s) when r = g (deformations 1 and 8): [[s cos 2r / cos r, 0], [2 s sin r, s / cos r]]
    np.testing.assert_allclose(paper_affine(1), [[0.79853769, 0.0], [-0.05583919, 0.80048764]], atol=1e-8)
    np.testing.assert_allclose(paper_affine(8), [[1.19780653, 0.0], [0.08375879, 1.20073145]], atol=1e-8)
    # det A = s^2 (1 - tan^2 g) for every type; r and g read as degrees
    for d, (r, g, s) in PAPER_DEFORMATIONS.items():
        assert np.linalg.det(paper_affine(d)) == pytest.approx(s * s * (1 - np.tan(np.deg2rad(g)) ** 2), rel=1e-12)
    assert len(PAPER_DEFORMATIONS) == 8
    # the literal reading r / 2 pi radians: 2 / 2 pi = 0.318 rad, a far larger angle
    lit = paper_affine(1, literal=True)
    assert np.linalg.det(lit) == pytest.approx(0.64 * (1 - np.tan(-1 / np.pi) ** 2), rel=1e-12)


def test_paper_gt_moves_slice_by_its_affine(tiny_model):
    m = tiny_model
    gt = paper_ground_truth(m, 4, perturb=True, seed=0, solver_config=SolverConfig(device="cpu"))
    assert gt.converged
    c = m.geometry.center_mm()
    e_u, e_v = in_plane_axes(m, "axial")
    k = int(np.median(m.voxel_ijk[:, 2]))
    on = m.slice_mask("axial", k)
    d = m.positions_mm[on] - c
    uv = np.stack([d @ e_u, d @ e_v], 1) @ paper_affine(4).T
    expected = c + uv[:, :1] * e_u + uv[:, 1:] * e_v + (d @ np.cross(e_u, e_v))[:, None] * np.cross(e_u, e_v)
    err = np.linalg.norm(gt.positions_mm[on] - expected, axis=1)
    assert err.mean() < 1.0  # within the GT simulation's residual
    assert gt.params["perturbed"] and "materials" in gt.params


def test_perturbation_is_seeded_and_bounded(tiny_model):
    a = perturb_materials(tiny_model.materials, 5)
    b = perturb_materials(tiny_model.materials, 5)
    assert a == b
    for o, m in a.items():
        assert 0.7 <= m.mu_pa / tiny_model.materials[o].mu_pa <= 1.3


def test_contact_gt_moves_pancreas_through_contact(tiny_model):
    gt = contact_ground_truth(tiny_model, seed=2, neighbour="duodenum", push_mm=10.0, solver_config=SolverConfig(device="cpu"))
    pan = tiny_model.organ_slice("pancreas")
    disp = np.linalg.norm(gt.positions_mm - tiny_model.positions_mm, axis=1)
    assert disp[pan].mean() > 0.3          # pushed, though never driven
    assert gt.params["neighbour"] == "duodenum" and gt.params["push_mm"] == 10.0
    # motion differs along the body axis: the slice-wise mean displacement varies
    ks = np.unique(tiny_model.voxel_ijk[pan, 2])
    per_slice = [disp[pan & (tiny_model.voxel_ijk[:, 2] == k)].mean() for k in ks]
    assert np.ptp(per_slice) > 0.3


def test_metrics_exact_on_hand_made_cases(tiny_case):
    a = np.zeros((4, 3))
    b = np.array([[3.0, 4.0, 0.0], [0, 0, 1.0], [0, 0, 0], [0, 0, 0]])
    np.testing.assert_allclose(particle_errors_mm(a, b), [5, 1, 0, 0])
    m1 = np.zeros((4, 4), bool)
    m1[:2] = True
    m2 = np.zeros((4, 4), bool)
    m2[1:3] = True
    assert dice(m1, m2) == pytest.approx(0.5)
    model = build_model(tiny_case, "p")
    shifted = model.positions_mm + np.array([tiny_case.geometry.spacing_mm[0], 0, 0])
    r = evaluate(shifted, model.positions_mm, tiny_case.geometry)
    assert r["error_mm"] == pytest.approx(tiny_case.geometry.spacing_mm[0])
    assert r["p95_mm"] == pytest.approx(tiny_case.geometry.spacing_mm[0])
    excl = np.zeros(model.n, bool)
    excl[: model.n // 2] = True
    assert evaluate(shifted, model.positions_mm, tiny_case.geometry, excl)["n"] == model.n - model.n // 2


def test_volume_registration_recovers_known_affine():
    from warpmpm.phantom import make_phantom

    case, _ = crop_to_organs(make_phantom(seed=1, resolution=2.0), ("pancreas", "stomach", "duodenum", "left_kidney"), 15)
    g = case.geometry
    M = np.array([[1.03, 0.02, 0.0], [-0.02, 0.97, 0.01], [0.0, 0.01, 1.02]])
    b = np.array([3.0, -2.0, 1.5])
    c = g.center_mm()
    tx = sitk.AffineTransform(3)
    Mi = np.linalg.inv(M)
    tx.SetCenter(c.tolist())
    tx.SetMatrix(Mi.ravel().tolist())
    tx.SetTranslation((-Mi @ b).tolist())
    img = case.intensity_image()
    target = sitk.GetArrayFromImage(sitk.Resample(img, img, tx, sitk.sitkLinear, 0.0))
    reg = register_volumes_affine(case.image, target, g, mask=case.labels > 0)
    model = build_model(case, "psdl")
    truth = (model.positions_mm - c) @ M.T + c + b
    assert np.linalg.norm(reg.apply(model.positions_mm) - truth, axis=1).mean() < 0.5


def test_run_case_end_to_end_cli(tmp_path, capsys):
    out = tmp_path / "r.json"
    code = main(["--phantom-resolution", "3", "--particle-step", "1", "--device", "cpu", "--json", str(out)])
    assert code == 0
    text = capsys.readouterr().out
    assert "| estimate (copy) |" in text and "| slice-driven |" in text and "| volume_registration" in text  # the row may carry an "uncertain" mark
    data = json.loads(out.read_text())
    for key in ("organs", "slices", "protocol", "deformation", "device", "n_particles", "results"):
        assert key in data
    for name in ("initial", "propagate", "volume_registration", "estimate"):
        assert {"error_mm", "p95_mm", "dice"} <= set(data["results"][name])
    est = data["results"]["estimate"]
    assert {"steps", "wall_s", "converged"} <= set(est)
    assert est["error_mm"] < data["results"]["initial"]["error_mm"]
    assert data["organs"] == "psdl" and data["device"] == "cpu"


@pytest.mark.parametrize("args,msg", [
    (["--labels", "/nonexistent/l.nii.gz"], "file not found"),
    (["--organs", "sx"], "unknown organ letter"),
    (["--slices", "axial:9999"], "axial slice 9999"),
    (["--slices", "diagonal:3"], "unknown slice orientation"),
    (["--deformation", "9"], "deformation must be 1..8"),
    (["--gt-wait-settled"], "contact protocol only"),
])
def test_run_case_bad_input_exit_2_no_json(tmp_path, capsys, args, msg):
    out = tmp_path / "r.json"
    code = main(["--phantom-resolution", "3", "--device", "cpu", "--json", str(out)] + args)
    assert code == 2
    err = capsys.readouterr().err
    assert msg in err and err.count("\n") == 1
    assert not out.exists() and not list(tmp_path.iterdir())


def test_seed_experiment_script_runs_as_a_program(tmp_path):
    """The seed's experiment script itself (as a user runs it), on a tiny phantom, without volume registration."""
    out = tmp_path / "r.json"
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "examples", "seed_experiment.py"), "--phantom-resolution", "3",
                           "--organs", "p", "--device", "cpu", "--no-volume-registration", "--json", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(out.read_text())["organs"] == "p"


def test_gt_label_map_at_rest_is_the_planning_map_for_sampled_models(tiny_case):
    from warpmpm.groundtruth import GroundTruth

    for step in (1, 2):
        model = build_model(tiny_case, "psdl", sampling_step=step)
        gt = GroundTruth(model, model.positions_mm.copy(), "paper")
        lab = gt.label_map(tiny_case.label_map)
        planning = np.where(np.isin(tiny_case.labels, list(tiny_case.label_map.values())), tiny_case.labels, 0)
        assert dice(lab > 0, planning > 0) > (0.999 if step == 1 else 0.9)


def test_empty_slice_refused_before_any_simulation(tmp_path, capsys, monkeypatch):
    import warpmpm.experiment.run as runner

    def no_gt(*a, **k):
        raise AssertionError("the ground truth was simulated before the slice was checked")

    monkeypatch.setattr(runner, "make_ground_truth", no_gt)
    code = main(["--phantom-resolution", "3", "--device", "cpu", "--slices", "axial:0", "--json", str(tmp_path / "r.json")])
    assert code == 2 and "holds no particle" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def _maybe_diverge(i):
    from warpmpm.errors import SimulationError

    if i == 1:
        raise SimulationError("non-finite value (NaN/Inf) at step 3")
    return [i]


def test_a_failed_task_does_not_lose_the_others(capsys):
    from warpmpm.experiment.tasks import run_tasks

    got = []
    failed = run_tasks(_maybe_diverge, [(0,), (1,), (2,)], got.extend)
    assert got == [0, 2] and len(failed) == 1 and failed[0][0] == (1,) and "NaN" in failed[0][1]
    assert "failed" in capsys.readouterr().err


def test_failed_simulations_leave_their_condition_out():
    from warpmpm.selection import TrainingTable

    rows = []
    for k in range(3):
        for d in (1, 2):
            err = "nan" if (k == 1 and d == 2) else str(1.0 + k)
            rows.append({"case": "c", "orientation": "axial", "slice": str(k), "organs": "p", "deformation": str(d),
                         "error_mm": err, "count_pancreas": "5", "count_stomach": "0", "count_duodenum": "0", "count_left_kidney": "0"})
    table = TrainingTable.from_sweep(rows)
    assert [k[2] for k in table.keys] == [0, 2]  # slice 1 diverged once: left out, the case kept


def test_paper_gt_that_diverged_at_the_estimators_cfl_now_converges():
    """Regression: this GT (every particle driven) gave NaN at step 1730 when it ran at CFL 0.5."""
    import numpy as np

    from warpmpm.experiment import CaseConfig, make_ground_truth, prepare_case

    cfg = CaseConfig(phantom_resolution=3.0, phantom_seed=8, deformation=8, device="cpu")
    gt = make_ground_truth(prepare_case(cfg), cfg)
    assert np.all(np.isfinite(gt.positions_mm)) and gt.converged
    sol = gt.params["solver"]
    assert sol["dt_s"] <= sol["dt_limit_s"] * 0.3 / 0.6 * (1 + 1e-9)  # CFL 0.3 (the limit is CFL 0.6)
    assert gt.params["gt_rms_residual_mm"] < 1.5
