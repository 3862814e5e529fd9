"""One frame pipeline: ``warpmpm run --targets cine`` and ``warpmpm track`` give the same figures on the same frames,
and ``run``'s estimate is the default estimator's, each estimator also under its own name."""

import os

import numpy as np
import SimpleITK as sitk
import pytest

from warpmpm.cli import main
from warpmpm.experiment import CaseConfig
from warpmpm.experiment.case import prepare_case
from warpmpm.experiment.organs import organ_scores
from warpmpm.experiment.run import run_prepared
from warpmpm.experiment.target_kinds import cine_frames
from warpmpm.experiment.truth import gt_for_model, make_ground_truth
from warpmpm.images import write_case


@pytest.fixture(scope="module")
def cine_run():
    """The phantom under the seed's paper protocol (deformation 2), imaged on a sagittal and a coronal plane as cine
    frames and followed by the tracker's pipeline inside ``run``."""
    from dataclasses import replace

    cfg = CaseConfig(targets="cine", deformation=2, particle_step=2, device="cpu", phantom_resolution=2.0,
                     baselines=("initial", "propagate", "slice-driven"), max_steps=300)
    from warpmpm.slices import DrivingSlice

    prep = prepare_case(cfg)  # the planes through the pancreas's middle (on a column of particles), as input indices
    ijk = prep.full_model.voxel_ijk[prep.full_model.organ_slice("pancreas")]
    planes = [prep.to_input(DrivingSlice(o, int(np.median(ijk[:, a])))) for o, a in (("sagittal", 0), ("coronal", 1))]
    cfg = replace(cfg, slices=",".join(map(str, planes)))
    prep = prepare_case(cfg)
    gt = make_ground_truth(prep, cfg)
    return cfg, prep, gt, run_prepared(prep, gt, cfg)


def test_run_and_track_give_the_same_per_organ_figures_on_the_same_frames(cine_run, tmp_path):
    """The frames ``run --targets cine`` tracked, written as NIfTI files beside its planning case and given to
    ``warpmpm track``: the same particles, the same final estimate to 1e-3 mm, the same per-organ errors against the
    truth to 1e-3 mm (the NIfTI files keep the grid's geometry in float32: 1e-5 mm) (the copy is ``run``'s default estimate). Breaks when either path registers, renders or copies otherwise
    (e.g. ``run`` with the ITK backend of its own ``--registration`` differs by millimetres). The tracker's linear prior
    is the run's (``cine_linear_prior``, 0: a run's frame is one jump from planning)."""
    cfg, prep, gt, out = cine_run
    model = prep.model(cfg.organs)
    slices = prep.resolve_slices(model, cfg.slices)
    frames = cine_frames(prep, gt, slices, cfg.cine_thickness_mm)
    image, labels = str(tmp_path / "image.nii.gz"), str(tmp_path / "labels.nii.gz")
    write_case(prep.case, labels, image)
    os.makedirs(tmp_path / "cine")
    for k, f in enumerate(frames):
        sitk.WriteImage(f.image, str(tmp_path / "cine" / f"frame_{k:04d}.nii.gz"))
    assert main(["track", "--image", image, "--labels", labels, "--cine", str(tmp_path / "cine"), "--out",
                 str(tmp_path / "track"), "--particle-step", str(cfg.particle_step),
                 "--linear-prior", str(cfg.cine_linear_prior)]) == 0  # a run's one jump from planning: no prior
    p = np.load(tmp_path / "track" / "particles.npz")
    assert np.allclose(p["planning_mm"], model.positions_mm, atol=1e-4)  # the same model (NIfTI keeps float32 geometry)
    assert out.estimator == "copy" and out.results["estimate"] is out.results["copy"]
    assert np.allclose(p["estimate_mm"][-1], out.positions_mm, atol=1e-3)
    gt_pos = gt_for_model(gt, model)
    on_plane = np.zeros(model.n, dtype=bool)  # not compared: the split by plane is run's own
    tracked = organ_scores(model, p["estimate_mm"][-1], gt_pos, on_plane)
    for o in model.organs:
        assert tracked[o]["error_mm"] == pytest.approx(out.results["copy"].organs[o]["error_mm"], abs=1e-3)
    moved = np.linalg.norm(out.positions_mm - model.positions_mm, axis=1).max()
    assert moved > 1.0  # the frames moved the estimate: the comparison is not of two unmoved models


def test_runs_estimate_is_the_default_estimator_and_each_is_under_its_name(cine_run):
    """``results.estimate`` is the copy (the default: measured best), the seed's MPM is ``slice-driven`` with its own
    solve, and the JSON says which is the estimate."""
    cfg, prep, gt, out = cine_run
    j = out.to_json()
    assert j["estimator"] == "copy" and j["results"]["estimate"] == j["results"]["copy"]
    assert j["results"]["slice-driven"]["steps"] > 0 and j["results"]["copy"]["steps"] == 0
    assert j["results"]["slice-driven"]["error_mm"] != j["results"]["copy"]["error_mm"]
    assert j["solver"]["method"]  # the MPM's solver summary, as before


def test_the_copy_of_fitted_affines_combines_every_plane(cine_run):
    """``--targets affine`` on two planes: the copy (``results.estimate``) is every plane's fitted motion combined
    (``propagate_planes``), not the first plane's alone (``propagate``); on the seed's affine truth the combined copy
    is closer on the pancreas than either plane alone."""
    from dataclasses import replace

    cfg, prep, gt, _ = cine_run
    out = run_prepared(prep, gt, replace(cfg, targets="affine"))
    copy, planes = out.results["copy"], out.results["propagate_planes"]
    assert all(copy.organs[o]["error_mm"] == planes.organs[o]["error_mm"] for o in copy.organs)
    assert copy.error_mm < out.results["propagate"].error_mm


def test_the_materials_reach_the_mpm_and_leave_the_copy_alone(cine_run):
    """``materials="tissue"`` (elastography's soft duodenum and stomach instead of the paper's MPa): the seed's MPM ends
    elsewhere and says which table it used; the copy, which uses no materials, is unchanged to the digit."""
    from dataclasses import replace

    cfg, prep, gt, _ = cine_run
    paper = run_prepared(prep, gt, replace(cfg, targets="affine", baselines=("slice-driven",)))
    tissue = run_prepared(prep, gt, replace(cfg, targets="affine", baselines=("slice-driven",), materials="tissue"))
    assert paper.to_json()["results"]["slice-driven"]["materials"] == "paper"
    assert tissue.to_json()["results"]["slice-driven"]["materials"] == "tissue"
    a, b = paper.results["slice-driven"], tissue.results["slice-driven"]
    assert abs(a.error_mm - b.error_mm) > 1e-3 or any(abs(a.organs[o]["error_mm"] - b.organs[o]["error_mm"]) > 1e-3 for o in a.organs)
    assert paper.results["copy"].error_mm == tissue.results["copy"].error_mm


def test_the_copy_of_a_planes_motion_moves_each_organ_by_its_own_affine():
    """``copy_organ_motion``, the one copy the tracker and ``run`` share: an organ with its own affine moves by it, the
    others by the whole slice's, and the coordinate along the plane's normal never changes (analytic)."""
    from warpmpm.slices import InPlaneAffine, copy_organ_motion

    rng = np.random.default_rng(0)
    x = rng.normal(0, 30, (200, 3))
    organ_of = np.array(["pancreas", "duodenum"] * 100)
    e_u, e_v, c = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([5.0, -3.0, 2.0])  # a sagittal plane
    whole = InPlaneAffine(np.eye(2), [1.0, -2.0])
    own = InPlaneAffine([[np.cos(0.1), -np.sin(0.1)], [np.sin(0.1), np.cos(0.1)]], [0.5, 0.0])
    out = copy_organ_motion(x, organ_of, e_u, e_v, c, whole, {"duodenum": own})
    assert np.allclose(out[:, 0], x[:, 0])  # left-right: through the sagittal plane
    p = organ_of == "pancreas"
    assert np.allclose(out[p] - x[p], [0.0, 1.0, -2.0])
    uv = (x[~p] - c)[:, 1:]
    assert np.allclose((out[~p] - c)[:, 1:], uv @ own.A.T + own.t_mm)
