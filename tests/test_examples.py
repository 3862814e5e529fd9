"""The teaching examples run as tests, with tiny options, and what each one shows is checked."""

import importlib.util
import os

import numpy as np
import pytest

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def example(name):
    spec = importlib.util.spec_from_file_location(name, os.path.join(ROOT, "examples", f"{name}.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_build_model_one_particle_per_voxel(capsys):
    ex = example("example_build_model").main(["--phantom-resolution", "3"])
    m, case = ex.model, ex.case
    for organ in m.organs:
        assert m.counts()[organ] == int(case.organ_mask(organ).sum())
    np.testing.assert_allclose(m.volume_mm3, case.geometry.voxel_volume_mm3)
    np.testing.assert_allclose(m.mass_kg(), m.per_particle("density_kg_m3") * m.volume_mm3 * 1e-9)
    assert "axial slice" in capsys.readouterr().out


def test_mpm_step_momentum_equals_impulse_and_contact_carries_the_stiff_block():
    ex = example("example_mpm_step").main(["--steps", "600", "--voxels", "4"])
    p, j = ex.momentum(), ex.impulse()
    assert np.linalg.norm(p - j) < 1e-3 * np.linalg.norm(j)
    d = ex.displacement_mm()
    assert d[~ex.soft, 0].mean() > 1e-3  # pushed through the shared grid only
    assert np.all(np.isfinite(d))


def test_drive_slice_halves_the_off_slice_error():
    ex = example("example_drive_slice").main(["--resolution", "3", "--organs", "p"])
    before, after = ex.error_mm(ex.model.positions_mm), ex.error_mm(ex.result.positions_mm)
    assert ex.result.converged and after < 0.6 * before


def test_cine_stream_follows_the_slice_frame_after_frame():
    ex = example("example_cine_stream").main(["--frames", "4"])
    log = ex.log
    assert len(log) == 4 and all(f["converged"] for f in log)
    for f in log:  # the off-slice pancreas moves with the slice, same sign, most of the way
        assert 0.5 * abs(f["slice_shift_mm"]) < abs(f["pancreas_shift_mm"]) <= 1.05 * abs(f["slice_shift_mm"])
        assert np.sign(f["pancreas_shift_mm"]) == np.sign(f["slice_shift_mm"])
    assert log[-1]["steps"] < log[0]["steps"] * 1.2  # later frames start from the last equilibrium


def test_register_slice_recovers_a_known_motion():
    ex = example("example_register_slice").main(["--resolution", "2", "--angle-deg", "3", "--shift-mm", "2", "-1.5"])
    assert ex.result.ok and ex.error_mm() < 0.3


@pytest.mark.parametrize("name", ["example_build_model", "example_mpm_step", "example_drive_slice", "example_cine_stream",
                                  "example_register_slice", "run_case"])
def test_every_example_documents_itself(name):
    mod = example(name)
    assert mod.__doc__ and "python examples/" in mod.__doc__


def test_clinic_files_example_writes_what_a_planning_system_opens(tmp_path, capsys):
    """The DICOM planning data in, one `warpmpm track` command, contours / registrations / DVHs out."""
    import csv

    track = example("clinic_files").main(["--out", str(tmp_path), "--frames", "2", "--phantom-resolution", "3",
                                           "--device", "cpu"])
    for n in range(2):
        for name in ("RS.dcm", "REG.dcm"):
            assert os.path.getsize(os.path.join(track, "dicom", f"frame_{n:04d}", name)) > 1000
    assert os.path.exists(os.path.join(track, "dicom", "RD_accumulated.dcm"))
    rows = {(r["organ"], r["metric"]) for r in csv.DictReader(open(os.path.join(track, "dose", "dose_metrics.csv")))}
    assert {("pancreas", "D95_Gy"), ("pancreas", "D98_Gy"), ("duodenum", "D0.5cc_Gy"), ("stomach", "D1cc_Gy")} <= rows
    out = capsys.readouterr().out
    assert "pancreas     D95_Gy" in out


def test_main_job_tracks_a_finite_element_truth_and_scores_every_organ(tmp_path, capsys):
    """examples/run_case.py: truth, cine, track, evaluation; the table on stdout, one line a stage on stderr, the
    outputs written; on the truth's breathing the track beats no motion on the pancreas."""
    ev = example("run_case").main(["--out", str(tmp_path / "job"), "--frames", "6", "--device", "cpu"])
    out, err = capsys.readouterr()
    assert "| estimate |" in out and "| initial |" in out and "latency per frame" in out
    assert [ln.split(":")[0] for ln in err.strip().splitlines()][-4:] == [
        "truth (finite elements", "cine (sagittal / coronal DICOM frames imaged from the truth)", "track (the truth never read)",
        "evaluation (every organ against the truth)"]
    assert not any(w in err.lower() for w in ("error", "fail", "warning"))
    for f in ("track/track.csv", "track/labels/frame_0005.nii.gz", "track/displacement/frame_0005.nii.gz", "track.rrd",
              "eval.json", "eval.png"):
        assert os.path.exists(tmp_path / "job" / f), f
    e = ev["results"]
    assert e["estimate"]["organs"]["pancreas"]["error_mm"] < e["initial"]["organs"]["pancreas"]["error_mm"]
