"""Issue 8: Rerun recordings, read back through Rerun's own reader."""

import subprocess
import sys

import numpy as np

import pytest

from warpmpm.errors import SimulationError
from warpmpm.experiment import CaseConfig, run_case
from viewer.__main__ import summarize
from viewer.recording import RerunRecorder


def test_recording_holds_every_entity(tmp_path, tiny_model):
    path = tmp_path / "run.rrd"
    out = run_case(CaseConfig(phantom_resolution=3.0, device="cpu", baselines=("initial",), max_steps=300,
                              estimator="slice-driven"), RerunRecorder(str(path)))
    s = summarize(str(path))
    counts = out.n_particles
    for organ, n in counts.items():
        for prefix in ("planning", "gt", "estimate"):
            e = s[f"/{prefix}/{organ}"]
            assert set(e["points"]) == {n}, (prefix, organ)
    assert set(s["/error/pancreas"]["points"]) == {counts["pancreas"]}
    steps = out.estimate.steps
    assert max(s["/estimate/pancreas"]["steps"]) == steps
    assert s["/metrics/rel_residual"]["rows"] == steps
    assert s["/metrics/rms_residual_mm"]["rows"] == steps
    assert s["/metrics/pancreas_error_mm"]["rows"] >= steps // 20
    assert {"step", "frame"} <= s["/estimate/pancreas"]["timelines"]
    slice_ents = [k for k in s if k.startswith("/slices/")]
    assert any(k.endswith("/plane") for k in slice_ents) and any(k.endswith("/image") for k in slice_ents)
    assert set(s[[k for k in slice_ents if k.endswith("/targets")][0]]["points"]) == {out.n_driven}
    assert "/run/params" in s


def test_logging_off_writes_nothing_and_imports_no_rerun(tmp_path):
    code = ("import sys; from warpmpm.experiment import CaseConfig, run_case; "
            "run_case(CaseConfig(phantom_resolution=3.0, organs='p', device='cpu', baselines=('initial',), max_steps=200)); "
            "print('rerun' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=600,
                          env={**__import__("os").environ, "PYTHONPATH": str(__import__("pathlib").Path(__file__).parents[1])})
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "False"
    assert not list(tmp_path.glob("*.rrd"))


def test_summary_cli(tmp_path):
    import rerun as rr

    path = tmp_path / "x.rrd"
    rec = rr.RecordingStream("t")
    rec.save(str(path))
    rec.log("a", rr.Points3D(np.zeros((5, 3))), static=True)
    rec.flush()
    rec.disconnect()
    proc = subprocess.run([sys.executable, "-m", "viewer", "--summary", str(path)], capture_output=True, text=True, timeout=120,
                          cwd=str(__import__("pathlib").Path(__file__).parents[1]))
    assert proc.returncode == 0 and "/a: 1 rows [static], points per row 5..5" in proc.stdout


def test_recording_opens_whole_in_the_viewer(tmp_path):
    """The recording is compacted (one chunk per entity and timeline run) and carries the default layout;
    with a display or Xvfb the native viewer renders it to a picture."""
    import os
    import shutil

    from rerun.chunk import RrdReader

    path = tmp_path / "run.rrd"
    run_case(CaseConfig(phantom_resolution=3.0, device="cpu", baselines=("initial",), max_steps=200), RerunRecorder(str(path)))
    chunks = [c.entity_path for c in RrdReader(str(path)).stream()]
    assert chunks.count("/estimate/pancreas") == 1, "recording was not compacted"
    if not (os.environ.get("DISPLAY") or shutil.which("Xvfb")):
        import pytest

        pytest.skip("no display and no Xvfb: the screenshot part needs one (Debian: xvfb, mesa-vulkan-drivers)")
    from viewer.__main__ import screenshot

    png = tmp_path / "shot.png"
    screenshot(str(path), str(png), size=(800, 500))
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000


def test_a_failed_run_leaves_no_recording(tmp_path, monkeypatch):
    """A run that fails (or is interrupted) mid-way must not leave a partial .rrd a viewer would read as whole."""
    import warpmpm.experiment.run as run

    def boom(*a, **k):
        raise SimulationError("non-finite value (NaN/Inf) at step 7")

    monkeypatch.setattr(run, "run_prepared", boom)
    path = tmp_path / "run.rrd"
    with pytest.raises(SimulationError):
        run_case(CaseConfig(phantom_resolution=3.0, organs="p", device="cpu", baselines=("initial",), max_steps=50), RerunRecorder(str(path)))
    assert not list(tmp_path.iterdir())


def test_junk_recording_is_a_clear_error(tmp_path):
    for name, data in (("junk.rrd", b"not a recording at all"), ("empty.rrd", b"")):
        path = tmp_path / name
        path.write_bytes(data)
        proc = subprocess.run([sys.executable, "-m", "viewer", "--summary", str(path)], capture_output=True, text=True,
                              timeout=120, cwd=str(__import__("pathlib").Path(__file__).parents[1]))
        assert proc.returncode == 2 and proc.stderr.startswith("error:") and "Traceback" not in proc.stderr, proc.stderr
