"""Issue 16: real planning scans and hostile input. Each test names the row of the issue it covers."""

import gzip
import json
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
import SimpleITK as sitk

from conftest import data_case
from warpmpm.cli import run_main
from warpmpm.driving import ConvergenceConfig, SliceDrivenEstimator
from warpmpm.errors import InputError, InputWarning, SimulationError
from warpmpm.experiment import CaseConfig, prepare_case, run_case
from warpmpm.images import PRESETS, Case, Geometry, load_case, write_case
from warpmpm.model import build_model
from warpmpm.phantom import make_phantom
from warpmpm.scenes import block_model
from warpmpm.slices import DrivingSlice, InPlaneAffine, parse_slices
from warpmpm.solvers import ExplicitConfig, GridConfig, MPMModel, SolverConfig
from warpmpm.targets import affine_targets

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
CPU = SolverConfig(device="cpu")
TINY = ["--phantom-resolution", "3", "--device", "cpu", "--quiet"]


def block_case(spacing, size_mm=(20, 20, 30)):
    """A pancreas block on a grid of ``spacing`` (a 4-voxel margin around it)."""
    size = [int(round(s / sp)) + 8 for s, sp in zip(size_mm, spacing)]
    lab = np.zeros(size[::-1], np.int32)
    hi = [4 + int(round(s / sp)) for s, sp in zip(size_mm, spacing)]
    lab[4:hi[2], 4:hi[1], 4:hi[0]] = PRESETS["amos"]["pancreas"]
    return Case(lab, Geometry(tuple(size), tuple(float(s) for s in spacing), (0.0, 0.0, 0.0)), dict(PRESETS["amos"]), name="block")


# 1. thick slices -----------------------------------------------------------------------------

def test_thick_slices_go_on_an_isotropic_lattice_of_the_same_volume():
    case = block_case((0.8, 0.8, 5.0))
    m = build_model(case, "p")
    assert m.lattice is not None and np.allclose(m.lattice.spacing_mm, (0.8 * 0.8 * 5.0) ** (1 / 3))
    assert m.volume_mm3.sum() == pytest.approx(20 * 20 * 30, rel=0.05)  # the organ's volume, not the staircase's
    # slice k of the scan holds the particles within its 5 mm
    k = 6
    z = m.positions_mm[m.slice_mask("axial", k), 2]
    assert np.all(np.abs(z - k * 5.0) <= 2.5 + 1e-9) and len(z) > 0
    assert build_model(case, "p", lattice="voxel").lattice is None
    assert build_model(make_phantom(resolution=3.0), "p").lattice is None  # 4 x 4 x 9 mm stays on its voxels


def test_a_rigid_slice_translation_carries_every_slice_of_a_thick_scan():
    """0.8 x 0.8 x 5 mm: the far slices must follow a 2 mm translation of slice 4. Before the fix they stayed put
    (0.00 mm; the grid cell was smaller than the 5 mm between slices)."""
    m = build_model(block_case((0.8, 0.8, 5.0)), "p")
    sl = [DrivingSlice("axial", 4)]
    idx, tg = affine_targets(m, m.positions_mm, sl, [InPlaneAffine(np.eye(2), [2.0, 0.0])])
    est = SliceDrivenEstimator(m, sl, solver_config=SolverConfig(device="cpu", explicit=ExplicitConfig(damping_factor=1.0)), extra_points_mm=tg,
                               convergence=ConvergenceConfig(max_steps=5000, wait_settled=True))
    res = est.estimate(tg)
    d = res.positions_mm - m.positions_mm
    assert res.settled
    for k in np.unique(m.voxel_ijk[:, 2]):
        assert d[m.voxel_ijk[:, 2] == k, 0].mean() > 1.8, k  # every slice, 90 % of the way


def test_the_grid_cell_never_falls_below_the_gap_between_particles():
    m = build_model(block_case((0.8, 0.8, 5.0)), "p", lattice="voxel")
    assert MPMModel(m, CPU).dx_mm >= 5.0
    with pytest.raises(InputError, match="smaller than the 5.00 mm gap"):
        MPMModel(m, SolverConfig(device="cpu", grid=GridConfig(cell_size_mm=2.0)))


def _thick_copy(folder, spacing):
    labels, image = data_case("totalseg_mr")
    out = []
    for path, interp in ((labels, sitk.sitkNearestNeighbor), (image, sitk.sitkLinear)):
        im = sitk.ReadImage(path)
        size = [int(round(sz * sp / ns)) for sz, sp, ns in zip(im.GetSize(), im.GetSpacing(), spacing)]
        r = sitk.Resample(im, size, sitk.Transform(), interp, im.GetOrigin(), spacing, im.GetDirection(), 0, im.GetPixelID())
        out.append(os.path.join(folder, os.path.basename(path)))
        sitk.WriteImage(r, out[-1])
    return out


def test_paper_protocol_on_a_thick_slice_copy_of_the_mr_sample(tmp_path):
    """1.5 x 1.5 x 6 mm copy of the 3 mm MR: the estimate cuts the error as on the original (measured: 0.15 of the
    initial error thick, 0.25 isotropic; the old voxel layout split apart and kept 0.42)."""
    labels, image = data_case("totalseg_mr")
    thick = _thick_copy(str(tmp_path), (1.5, 1.5, 6.0))
    ratios = {}
    for name, (lab, img) in (("iso", (labels, image)), ("thick", thick)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = run_case(CaseConfig(labels=lab, image=img, preset="totalseg_mr", deformation=2, device="cpu",
                                      baselines=("initial",)))
        ratios[name] = out.estimate.error_mm / out.results["initial"].error_mm
    assert ratios["thick"] < ratios["iso"] + 0.1 and ratios["thick"] < 0.35


# 2. corrupt files ----------------------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".nii.gz", ".nii"])
def test_truncated_files_are_refused(tmp_path, tiny_case, suffix):
    path = tmp_path / f"labels{suffix}"
    write_case(tiny_case, path)
    data = path.read_bytes()
    if suffix == ".nii.gz":  # a gzip stream cut in the middle, and a complete gzip of a cut NIfTI
        path.write_bytes(data[: len(data) // 2])
        with pytest.raises(InputError, match="truncated or corrupt"):
            load_case(path, preset="amos")
        raw = gzip.decompress(data)
        path.write_bytes(gzip.compress(raw[: len(raw) * 2 // 3]))
    else:
        path.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(InputError, match="truncated: its header announces"):
        load_case(path, preset="amos")


def test_nan_voxels_are_named_before_any_simulation(tmp_path, tiny_case, capsys):
    img = tiny_case.image.copy()
    img[3, 5, 7] = np.nan
    from dataclasses import replace

    write_case(replace(tiny_case, image=img), tmp_path / "l.nii.gz", tmp_path / "i.nii.gz")
    code = run_main(["--labels", str(tmp_path / "l.nii.gz"), "--image", str(tmp_path / "i.nii.gz"), "--device", "cpu",
                     "--json", str(tmp_path / "o.json")])
    err = capsys.readouterr().err
    assert code == 2 and "1 non-finite (NaN or Inf) voxels" in err and "(7, 5, 3)" in err and err.count("\n") == 1
    assert not (tmp_path / "o.json").exists()


# 3. a wrong preset ---------------------------------------------------------------------------

def test_an_organ_far_from_the_pancreas_is_warned(tmp_path, tiny_case):
    labels = tiny_case.labels.copy()
    d = tiny_case.label_map["duodenum"]
    labels[labels == d] = 0
    labels[-3:, -6:, -6:] = d  # a "duodenum" in a far corner: what a wrong preset gives (a lung lobe)
    from dataclasses import replace

    write_case(replace(tiny_case, labels=labels), tmp_path / "l.nii.gz")
    with pytest.warns(InputWarning, match=r"duodenum \(label 13\) lies \d+ mm from the pancreas"):
        load_case(tmp_path / "l.nii.gz", preset="amos")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the phantom's own labels raise no warning
        write_case(tiny_case, tmp_path / "ok.nii.gz")
        load_case(tmp_path / "ok.nii.gz", preset="amos")


def test_totalseg_ct_read_with_the_mr_preset_is_warned():
    labels, _ = data_case("totalseg_ct")
    with pytest.warns(InputWarning, match="duodenum.*is the label preset right"):
        load_case(labels, preset="totalseg_mr")


# 4. convergence that is not --------------------------------------------------------------------

def test_an_unreachable_rotation_stalls_and_is_not_called_converged(tiny_model):
    """A 90 degree rotation of the mid-pancreas slice of the phantom, its neighbours around it: the old rule called
    such a frame converged (stagnation), 12.7 mm off target with det F ~ 0."""
    m = tiny_model
    k = int(np.median(m.voxel_ijk[m.organ_slice("pancreas"), 2]))
    sl = [DrivingSlice("axial", k)]
    idx, tg = affine_targets(m, m.positions_mm, sl, [InPlaneAffine([[0.0, -1.0], [1.0, 0.0]])], m.geometry.center_mm())
    est = SliceDrivenEstimator(m, sl, solver_config=CPU, extra_points_mm=tg, convergence=ConvergenceConfig(max_steps=4000))
    with pytest.warns(RuntimeWarning, match="stalled|did not converge"):
        res = est.estimate(tg)
    assert not res.converged and res.reason in ("stalled", "max_steps") and res.final_rms_mm > 2.0


def test_stagnation_far_from_the_targets_is_stalled():
    from warpmpm.driving import ConvergenceMonitor

    cfg = ConvergenceConfig(th_s=5, th_d=3, stall_mm=1.0)
    for rms, reason in ((0.5, "stagnation"), (3.0, "stalled")):
        mon = ConvergenceMonitor(cfg)
        stops = [mon.update(0.1234, rms) for _ in range(6)]
        assert stops[-1] and mon.reason == reason and mon.converged == (reason == "stagnation")


def test_the_whole_body_is_watched_not_only_the_driven_slice():
    """The driven slice of a free block stops changing long before the far end has followed: reported not settled;
    waiting for it gets the far end there."""
    m = build_model(block_case((2.0, 2.0, 2.0), (20, 20, 20)), "p")
    sl = [DrivingSlice("axial", 4)]
    idx, tg = affine_targets(m, m.positions_mm, sl, [InPlaneAffine(np.eye(2), [2.0, 0.0])])
    far = m.voxel_ijk[:, 2] >= m.voxel_ijk[:, 2].max() - 2
    early = SliceDrivenEstimator(m, sl, solver_config=CPU, extra_points_mm=tg).estimate(tg)
    assert early.converged and not early.settled and (early.positions_mm - m.positions_mm)[far, 0].mean() < 1.5
    est = SliceDrivenEstimator(m, sl, solver_config=SolverConfig(device="cpu", explicit=ExplicitConfig(damping_factor=1.0)), extra_points_mm=tg,
                               convergence=ConvergenceConfig(max_steps=3000, wait_settled=True))
    late = est.estimate(tg)
    assert late.converged and late.settled and (late.positions_mm - m.positions_mm)[far, 0].mean() > 1.7


def test_a_non_finite_residual_is_a_simulation_error():
    from warpmpm.driving import ConvergenceMonitor

    with pytest.raises(SimulationError, match="non-finite residual"):
        ConvergenceMonitor().update(float("nan"))


# 5 and 6. crashes become clear errors, with the right wording -----------------------------------

@pytest.mark.parametrize("args,msg", [
    (["--phantom-seed", "-1"], "phantom seed must be an integer in 0.."),
    (["--protocol", "contact", "--deformation", "-1"], "contact scenario number"),
    (["--phantom-resolution", "nan"], "phantom resolution must be a finite number"),
    (["--particle-step", "1000"], "particle sampling step 1000 leaves no particle of the"),
    (["--rrd-every", "0"], "--rrd-every must be an integer >= 1"),
    (["--slices", "auto:zz"], "unknown --slices"),
    (["--solver", "quasistatic", "--contact", "sliding"], "handles sticky contact only"),
    (["--threads", "0"], "cpu_threads must be an integer from 1 to 64"),
])
def test_bad_values_are_one_line_errors(tmp_path, capsys, args, msg):
    code = run_main(TINY + ["--json", str(tmp_path / "o.json")] + args)
    err = capsys.readouterr().err
    assert code == 2 and msg in err and err.count("\n") == 1 and "Traceback" not in err
    assert not list(tmp_path.iterdir())


def test_a_bad_thread_count_in_the_environment_is_a_one_line_error(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("WARPMPM_CPU_THREADS", "two")
    code = run_main(TINY + ["--json", str(tmp_path / "o.json")])
    err = capsys.readouterr().err
    assert code == 2 and "WARPMPM_CPU_THREADS='two'" in err and err.count("\n") == 1
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("option", ["--json", "--rrd"])
def test_an_output_onto_a_directory_is_refused_before_the_run(tmp_path, capsys, monkeypatch, option):
    import warpmpm.experiment.run as run

    monkeypatch.setattr(run, "make_ground_truth", lambda *a, **k: pytest.fail("simulated before checking the output"))
    code = run_main(TINY + [option, str(tmp_path)])
    assert code == 2 and "is a directory" in capsys.readouterr().err


def test_solver_settings_are_checked_when_built():
    with pytest.raises(InputError, match="cfl must be a finite number > 0"):
        SolverConfig(explicit=ExplicitConfig(cfl=0))
    with pytest.raises(InputError, match="cfl must be a finite number > 0"):
        SolverConfig(explicit=ExplicitConfig(cfl=-0.1))
    with pytest.raises(InputError, match="above the stable limit.*time step"):  # the time step, not the margin
        SolverConfig(explicit=ExplicitConfig(cfl=3))
    with pytest.raises(InputError, match="margin_mm"):
        SolverConfig(grid=GridConfig(margin_mm=float("nan")))
    m = block_model((3, 3, 3), (2, 2, 2), "pancreas")
    bad = np.zeros((2, 3))
    bad[1, 2] = np.nan
    with pytest.raises(InputError, match="extra_points_mm holds a non-finite value \\(point 1\\)"):
        MPMModel(m, CPU, extra_points_mm=bad)


def test_itk_warnings_do_not_precede_the_error_line(tmp_path):
    path = tmp_path / "junk.nii"
    path.write_bytes(b"\x00" * 400)
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "examples", "seed_experiment.py"), "--labels", str(path)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and proc.stderr.startswith("error:") and proc.stderr.count("\n") == 1, proc.stderr


# 7. interrupts -----------------------------------------------------------------------------------

def test_ctrl_c_is_one_line_exit_130_and_no_output(tmp_path, capsys, monkeypatch):
    import warpmpm.experiment.run as run

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(run, "run_prepared", interrupted)
    code = run_main(TINY + ["--organs", "p", "--json", str(tmp_path / "o.json"), "--rrd", str(tmp_path / "o.rrd")])
    err = capsys.readouterr().err
    assert code == 130 and err.strip().splitlines()[-1].startswith("interrupted") and "Traceback" not in err
    assert not list(tmp_path.iterdir())  # neither the JSON nor a partial recording


# 8. sweeps ---------------------------------------------------------------------------------------

def test_a_second_sweep_on_the_same_csv_is_refused(tmp_path):
    from warpmpm.experiment.io import CsvAppender

    path = str(tmp_path / "s.csv")
    with CsvAppender(path, ["a"]):
        with pytest.raises(InputError, match="being written by another run"):
            with CsvAppender(path, ["a"]):
                pass
    with CsvAppender(path, ["a"]) as w:  # free again once the first has finished
        w.write([{"a": 1}])


def test_a_torn_last_line_is_dropped_and_reported(tmp_path, capsys):
    from warpmpm.experiment.io import CsvAppender, read_rows

    path = tmp_path / "s.csv"
    path.write_text("a,b\n1,2\n3,")  # a run killed in the middle of a row
    assert read_rows(str(path)) == [{"a": "1", "b": "2"}]
    with CsvAppender(str(path), ["a", "b"]) as w:
        w.write([{"a": 5, "b": 6}])
    assert "dropped a torn last line" in capsys.readouterr().err
    assert read_rows(str(path)) == [{"a": "1", "b": "2"}, {"a": "5", "b": "6"}]


def _fails_on_one(i):
    if i == 1:
        raise ValueError("boom")
    return [i]


def test_every_task_runner_goes_on_after_a_failure():
    from warpmpm.experiment.tasks import run_tasks

    for kw in ({"workers": 1}, {"workers": 2}):
        got = []
        failed = run_tasks(_fails_on_one, [(0,), (1,), (2,)], got.extend, **kw)
        assert sorted(got) == [0, 2] and len(failed) == 1 and "boom" in failed[0][1]


def test_sweep_cli_exits_non_zero_when_tasks_failed_and_the_summary_survives_failed_rows(tmp_path, monkeypatch, capsys):
    import warpmpm.cli as cli
    import warpmpm.experiment.sweep as sw
    from warpmpm.experiment.tables import summarize

    monkeypatch.setattr(sw, "sweep_task", lambda *a, **k: (_ for _ in ()).throw(SimulationError("NaN at step 3")))
    code = cli.main(["sweep", "--phantom-seeds", "0,1", "--deformations", "1", "--out", str(tmp_path / "s.csv")])
    assert code == 1 and "2 of 2 tasks failed" in capsys.readouterr().err
    rows = [{"case": "c", "deformation": "1", "organs": "p", "error_mm": "nan", "failure": "NaN"},
            {"case": "c", "deformation": "1", "organs": "p", "error_mm": "2.0", "dice": "0.5", "initial_error_mm": "5",
             "initial_dice": "0.3", "propagate_error_mm": "3", "failure": ""}]
    assert "| p, best slice | 2.00" in summarize(rows)


# 9. metrics that hide things ---------------------------------------------------------------------

def test_off_slice_error_and_a_mostly_driven_pancreas(tmp_path):
    with pytest.warns(InputWarning, match="of the pancreas particles lie on the driving slices"):
        out = run_case(CaseConfig(phantom_resolution=3.0, organs="p", slices="axial:7,axial:8,axial:9,axial:10,axial:6",
                                  device="cpu", baselines=("initial",), max_steps=300, exclude_driven=False))
    for name in ("initial", "estimate"):
        e = out.results[name].to_json()
        assert "error_offslice_mm" in e and np.isfinite(e["error_offslice_mm"])
    assert out.estimate.error_offslice_mm > out.estimate.error_mm  # the driven particles flatter the all-particle figure


def test_a_repeated_slice_counts_once():
    assert parse_slices("axial:9,axial:9, axial:9") == [DrivingSlice("axial", 9)]


def test_dice_is_not_clipped_when_the_truth_leaves_the_grid():
    from warpmpm.metrics import evaluate

    g = Geometry((10, 10, 10), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    pts = np.stack(np.meshgrid(np.arange(2, 6), np.arange(2, 6), np.arange(2, 6)), -1).reshape(-1, 3).astype(float)
    moved = pts + [20.0, 0, 0]  # wholly outside the planning grid, for both: the same shape
    assert evaluate(moved, moved, g)["dice"] == pytest.approx(1.0)


def test_a_volume_registration_that_fell_back_is_marked_in_the_table():
    from warpmpm.experiment.result import EstimateScores, RunResult, Scores
    from warpmpm.experiment.tables import format_table

    s = dict(error_mm=1.0, p95_mm=2.0, max_mm=3.0, dice=0.5, n=10)
    est = EstimateScores(**s, steps=10, wall_s=1.0, converged=True, reason="threshold", rms_residual_mm=0.1, rel_residual=0.01,
                         ms_per_step=1.0)
    out = RunResult(case="c", organs="p", slices=["axial:1"], protocol="paper", deformation=1, targets="affine", device="cpu",
                    n_particles={"pancreas": 10}, n_driven=2, excluded_driven=False, solver={}, gains={}, gt={},
                    results={"volume_registration": Scores(**s, info={"fallback_to_identity": True, "wall_s": 1.0}), "estimate": est})
    assert "volume_registration (FAILED: fell back to no motion)" in format_table(out)


def test_a_completion_that_did_not_converge_is_marked_in_the_table():
    from warpmpm.experiment.result import EstimateScores, RunResult, Scores
    from warpmpm.experiment.tables import format_table

    s = dict(error_mm=1.0, p95_mm=2.0, max_mm=3.0, dice=0.5, n=10)
    est = EstimateScores(**s, steps=10, wall_s=1.0, converged=True, reason="threshold", rms_residual_mm=0.1, rel_residual=0.01,
                         ms_per_step=1.0)

    def run(converged):
        c = Scores(**s, info={"converged": converged, "residual": 3e-3, "wall_s": 1.0})
        out = RunResult(case="c", organs="p", slices=["axial:1"], protocol="paper", deformation=1, targets="affine", device="cpu",
                        n_particles={"pancreas": 10}, n_driven=2, excluded_driven=False, solver={}, gains={}, gt={},
                        results={"completion": c, "estimate": est})
        return format_table(out)

    assert "completion (NOT converged: residual 3.0e-03)" in run(False)
    assert "NOT converged: residual" not in run(True)


# 10. ground truths that mislead ------------------------------------------------------------------

def test_a_volume_registration_that_fails_on_an_expansion_is_flagged():
    """CT sample, paper deformation 2 (scale 1.2): the masked registration ends 5.8 mm off (initial 11.5) while
    saying nothing; the unmasked check disagrees with it by 7.8 mm and flags it. Deformation 1 stays unflagged."""
    from warpmpm.experiment.baselines import volume_registration
    from warpmpm.experiment.truth import make_ground_truth

    labels, image = data_case("totalseg_ct")
    flags = {}
    for d in (1, 2):
        cfg = CaseConfig(labels=labels, image=image, preset="totalseg_ct", deformation=d, device="cpu")
        prep = prepare_case(cfg)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gt = make_ground_truth(prep, cfg)
        flags[d] = volume_registration(prep, gt, prep.full_model)[1]
    assert not flags[1]["uncertain"] and flags[2]["uncertain"] and flags[2]["disagreement_mm"] > 4.0


def test_contact_scenarios_differ_from_case_to_case():
    from warpmpm.experiment.truth import contact_seed

    cfg = CaseConfig(protocol="contact", deformation=3)
    a = prepare_case(CaseConfig(phantom_resolution=3.0, organs="p"))
    b = prepare_case(CaseConfig(phantom_resolution=3.0, organs="p"))
    b.case.name = "another_case"
    assert contact_seed(a, cfg) != contact_seed(b, cfg)


def test_a_ground_truth_that_leaves_the_scan_is_refused():
    from warpmpm.experiment.truth import check_inside_imaged_volume
    from warpmpm.groundtruth import GroundTruth

    prep = prepare_case(CaseConfig(phantom_resolution=3.0, organs="p"))
    m = prep.full_model
    geo = prep.input_geometry
    gone = m.positions_mm + [0.0, 0.0, geo.size[2] * geo.spacing_mm[2]]  # pushed a whole scan length along z
    with pytest.raises(InputError, match="out of the imaged volume"):
        check_inside_imaged_volume(prep, GroundTruth(m, gone, "contact"))
    check_inside_imaged_volume(prep, GroundTruth(m, m.positions_mm + 2.0, "contact"))  # a few mm is fine


# 11. big models give feedback ----------------------------------------------------------------------

def test_progress_names_the_model_size_grid_and_memory_first(tmp_path, capsys):
    code = run_main(["--phantom-resolution", "3", "--device", "cpu", "--organs", "p", "--no-volume-registration",
                     "--json", str(tmp_path / "o.json")])
    err = capsys.readouterr().err.splitlines()
    assert code == 0
    first = [ln for ln in err if not ln.startswith("warning:")][0]
    assert first.startswith("model: ") and "particles" in first and "grid" in first and "MB" in first
    assert any(ln.startswith("ground truth: ") and "steps" in ln for ln in err)
    assert json.loads((tmp_path / "o.json").read_text())["results"]["estimate"]["settled"] in (True, False)


def test_killing_a_sweep_ends_its_workers(tmp_path):
    """kill -9 of a --workers 2 sweep left its two workers simulating for nobody."""
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-m", "warpmpm.cli", "sweep", "--phantom-seeds", "0,1", "--phantom-resolution", "3",
                             "--deformations", "1,2", "--workers", "2", "--out", str(tmp_path / "s.csv")],
                            cwd=tmp_path, env=dict(os.environ, PYTHONPATH=ROOT), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def children(pid):
        try:
            with open(f"/proc/{pid}/task/{pid}/children") as f:
                return [int(c) for c in f.read().split()]
        except OSError:
            return []

    deadline = time.time() + 120
    kids = []
    while time.time() < deadline and len(kids) < 2:
        kids = [c for c in children(proc.pid) if "spawn_main" in open(f"/proc/{c}/cmdline").read().replace("\0", " ")]
        time.sleep(0.5)
    assert len(kids) >= 2, "the pool did not start"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 20
    while time.time() < deadline and any(os.path.exists(f"/proc/{k}") and open(f"/proc/{k}/stat").read().split()[2] != "Z" for k in kids):
        time.sleep(0.5)
    alive = [k for k in kids if os.path.exists(f"/proc/{k}") and open(f"/proc/{k}/stat").read().split()[2] != "Z"]
    for k in alive:
        os.kill(k, signal.SIGKILL)
    assert not alive, "workers outlived the sweep"


def test_a_closed_stdout_stops_without_a_traceback(tmp_path):
    """`warpmpm ... | head`: the reader goes away while a command prints; it ends with 141, no traceback."""
    import subprocess
    import sys

    script = tmp_path / "loud.py"
    script.write_text("import sys\n"
                      "from warpmpm import cli\n"
                      "def loud(a):\n"
                      "    for _ in range(100000):\n"
                      "        print('| row |')\n"
                      "    return 0\n"
                      "cli.COMMANDS['evaluate-track'] = loud  # a command whose table outlives its reader\n"
                      "sys.exit(cli.main(['evaluate-track', '--track', 'x', '--truth', 'y']))\n")
    p = subprocess.run(f"{sys.executable} {script} | head -1; exit ${{PIPESTATUS[0]}}", shell=True, executable="/bin/bash",
                       capture_output=True, text=True, timeout=120)
    assert p.stdout.strip() == "| row |"
    assert "Traceback" not in p.stderr and "BrokenPipe" not in p.stderr
    assert p.returncode == 141


@pytest.mark.parametrize("args", [["--pixel-mm", "0"], ["--plane", "oblique"], ["--frames", "0"], ["--fps", "nan"],
                                  ["--fps", "inf"], ["--thickness-mm", "nan"], ["--thickness-mm", "1e6"], ["--seed", "-1"],
                                  ["--frames", "100000000"], ["--image", "x.nii.gz"]])
def test_make_cine_refuses_bad_parameters_before_writing_anything(tmp_path, args):
    from warpmpm.cli import main

    out = tmp_path / "series"
    assert main(["make-cine", "--out", str(out), *args]) == 2
    assert not out.exists()  # not even the phantom's planning files


def test_make_cine_refuses_an_out_that_is_a_file_or_holds_a_series(tmp_path, capsys):
    from warpmpm.cli import main

    f = tmp_path / "file"
    f.write_text("x")
    assert main(["make-cine", "--out", str(f)]) == 2 and "is a file" in capsys.readouterr().err
    d = tmp_path / "old"
    d.mkdir()
    (d / "frame_0000.dcm").write_text("x")
    assert main(["make-cine", "--out", str(d)]) == 2 and "already holds files" in capsys.readouterr().err
    assert sorted(p.name for p in d.iterdir()) == ["frame_0000.dcm"]


def test_a_raw_numbers_run_name_that_is_not_a_key_is_refused_and_runs_are_kept(tmp_path):
    """Benchmarks keep their numbers in results/<script>.json, one entry per run: a run name with a folder in it is
    refused before the run (the option's type) and at the write, and nothing is written; a second run keeps the first."""
    from warpmpm.experiment import raw_numbers as raw

    script = str(tmp_path / "bench.py")
    for bad in ("../elsewhere", "a/b", "x.json", "", ".hidden"):
        with pytest.raises(ValueError, match="raw-numbers run name"):
            raw.save(script, {"n": 1}, run=bad)
    assert not (tmp_path / "results").exists()
    path = raw.save(script, {"n": 1}, run="fine_name-2.x", quiet=True)
    assert path == str(tmp_path / "results" / "bench.json")
    raw.save(script, {"n": 2}, quiet=True)
    assert raw.load(path, "fine_name-2.x") == {"n": 1} and raw.load(path) == {"n": 2}
    with pytest.raises(KeyError, match="holds no run 'other'; it holds default, fine_name-2.x"):
        raw.load(path, "other")
    assert sorted(os.listdir(tmp_path / "results")) == ["bench.json"]


def test_a_degenerate_registration_names_the_slice_the_user_gave(monkeypatch):
    """A registration that degenerates is a failure of the run (SimulationError, exit 3), not bad input, and names the
    input volume's slice index (the crop's differs)."""
    import warpmpm.targets as targets_module
    from warpmpm.errors import SimulationError
    from warpmpm.experiment.config import CaseConfig
    from warpmpm.experiment.run import run_case
    from warpmpm.phantom import make_phantom

    real = targets_module.register_slice_organs

    def broken(*args, **kw):
        whole, organs = real(*args, **kw)
        whole.ok, whole.stop = False, "a test's degenerate transform"
        return whole, organs

    monkeypatch.setattr(targets_module, "register_slice_organs", broken)
    case = make_phantom(resolution=3.0)
    i = int(np.median(np.nonzero(case.labels == case.label_map["pancreas"])[2]))  # the crop starts 3 voxels in along x
    cfg = CaseConfig(phantom_resolution=3.0, slices=f"sagittal:{i}", targets="registration", device="cpu", max_steps=20,
                     baselines=("initial",))
    with pytest.raises(SimulationError, match=rf"sagittal slice {i} gave a degenerate transform"):
        run_case(cfg)


def test_hostile_script_clinic_file_cases_are_clear_errors(tmp_path):
    """scripts/hostile_inputs.py's cases for the clinic's files (broken Unity .bin, structure sets without the pancreas or
    of another scan, bad --structure / --dose / --beam-on / --trackrad-centre): each one `error:` line, exit 2, nothing
    written, no traceback."""
    import importlib.util
    import subprocess
    import sys

    root = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
    spec = importlib.util.spec_from_file_location("hostile_inputs", os.path.join(root, "scripts", "hostile_inputs.py"))
    h = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(h)
    d = str(tmp_path)
    h.make_files(d)
    exe = os.path.join(os.path.dirname(sys.executable), "warpmpm")
    outcomes = {}
    for name, argv, expected in h.cases(d):
        if not name.startswith(("track:", "cine-info:", "make-cine:", "make-truth:")):
            continue
        before = set(os.listdir(d))
        proc = subprocess.run([exe] + argv[1:], capture_output=True, text=True, cwd=d, timeout=300)
        outcomes[name] = h.classify(proc, expected, before, d)
    assert len(outcomes) >= 20
    assert all(v == "clear error" for v in outcomes.values()), outcomes


def test_the_out_of_volume_check_on_a_label_map_flipped_against_its_image(tmp_path):
    """Labels on a grid whose y axis runs the other way (the same anatomy): a few mm of motion passes, a motion out of the
    scan is refused, naming the pancreas's and the scan's world boxes."""
    import SimpleITK as sitk

    from warpmpm.experiment.truth import check_inside_imaged_volume
    from warpmpm.groundtruth import GroundTruth
    from warpmpm.images import write_case
    from warpmpm.phantom import make_phantom

    c = make_phantom(resolution=3.0)
    write_case(c, str(tmp_path / "labels.nii.gz"), str(tmp_path / "image.nii.gz"))
    lab = sitk.ReadImage(str(tmp_path / "labels.nii.gz"))
    d = np.array(lab.GetDirection()).reshape(3, 3)
    d[:, 1] *= -1
    flipped = sitk.GetImageFromArray(np.ascontiguousarray(sitk.GetArrayFromImage(lab)[:, ::-1, :]))
    flipped.SetSpacing(lab.GetSpacing())
    flipped.SetOrigin(lab.TransformIndexToPhysicalPoint((0, lab.GetSize()[1] - 1, 0)))
    flipped.SetDirection(tuple(d.ravel()))
    (tmp_path / "flip").mkdir()
    sitk.WriteImage(flipped, str(tmp_path / "flip" / "labels.nii.gz"))
    with pytest.warns(InputWarning, match="another grid"):
        prep = prepare_case(CaseConfig(labels=str(tmp_path / "flip" / "labels.nii.gz"), image=str(tmp_path / "image.nii.gz"),
                                       preset="amos", organs="p"))
    m = prep.full_model
    check_inside_imaged_volume(prep, GroundTruth(m, m.positions_mm + [0.0, 3.0, -4.0], "contact"))
    gone = m.positions_mm + [0.0, 0.0, prep.input_geometry.size[2] * prep.input_geometry.spacing_mm[2]]
    with pytest.raises(InputError, match=r"pancreas spans \[.*\] mm .* the scan \["):
        check_inside_imaged_volume(prep, GroundTruth(m, gone, "contact"))


def test_a_long_stage_in_a_log_says_its_pace_and_the_most_it_can_take():
    """Not on a terminal, a long estimate still writes where it is: the time per step and the bound at its step cap."""
    from warpmpm.experiment.run import Progress

    lines = []
    p = Progress(lambda text, end="\n": lines.append(text), live=False)
    p.FIRST_LINE_S = 0.0
    p.step("estimate", 0, 1.0, 1000)
    p.step("estimate", 10, 0.5, 1000)
    assert len(lines) == 1 and "estimate: step 10" in lines[0] and "at most 990 steps more, up to" in lines[0]
    p.step("estimate", 11, 0.5, 1000)  # the next line waits EVERY_S
    assert len(lines) == 1
