"""Issue 51, part 1: no command deletes or replaces what it did not write; one writer per output folder."""

import os
import subprocess
import sys

import pytest

from warpmpm.cli import main
from warpmpm.errors import InputError
from warpmpm.output_folder import RECORD, OutputFolder, record_name

TRACK_RECORD = record_name("track")  # track.json


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("cine") / "series")
    assert main(["make-cine", "--phantom-resolution", "3", "--frames", "2", "--plane", "sagittal", "--out", out]) == 0
    return out


def _track(series, out, *extra):
    return ["track", "--image", os.path.join(series, "planning", "image.nii.gz"), "--labels",
            os.path.join(series, "planning", "labels.nii.gz"), "--cine", os.path.join(series, "cine"), "--out", str(out),
            "--device", "cpu", *extra]


def _tree(folder):
    return sorted(os.path.relpath(os.path.join(d, f), folder) for d, _, fs in os.walk(folder) for f in fs)


def test_overwrite_never_deletes_an_input_folder(series, capsys):
    """The issue's data loss: `track --overwrite --out CINE` deleted the 8 frames, `--out PLANNING` the planning series."""
    for inp, opt in ((os.path.join(series, "cine"), "--cine"), (os.path.join(series, "planning"), "--image")):
        before = _tree(inp)
        assert main(_track(series, inp, "--overwrite")) == 2
        err = capsys.readouterr().err
        assert f"the input {opt}" in err and "name a new folder" in err, err
        assert _tree(inp) == before
    # nor a folder that holds an input
    before = _tree(series)
    assert main(_track(series, series, "--overwrite")) == 2 and "holds the input" in capsys.readouterr().err
    assert _tree(series) == before


def test_overwrite_replaces_only_an_earlier_track(series, tmp_path, capsys):
    mine = tmp_path / "results"
    mine.mkdir()
    (mine / "notes.txt").write_text("a user's own notes")
    assert main(_track(series, mine, "--overwrite")) == 2
    assert "did not write" in capsys.readouterr().err and (mine / "notes.txt").read_text() == "a user's own notes"
    # a warpmpm folder of another kind (a cine series) is not a track either
    assert main(_track(series, series, "--overwrite")) == 2
    out = tmp_path / "track"
    assert main(_track(series, out)) == 0
    assert (out / TRACK_RECORD).exists() and '"kind": "track"' in (out / TRACK_RECORD).read_text()
    (out / "stale.txt").write_text("left by the earlier track's user")
    assert main(_track(series, out)) == 2 and "--overwrite" in capsys.readouterr().err
    assert main(_track(series, out, "--overwrite")) == 0
    assert not (out / "stale.txt").exists() and (out / "track.csv").exists()  # replaced whole
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no lock or work folder left behind


def test_a_symlink_out_is_refused_and_its_target_kept(series, tmp_path, capsys):
    target = tmp_path / "real"
    assert main(_track(series, target)) == 0
    link = tmp_path / "link"
    link.symlink_to(target)
    before = _tree(target)
    assert main(_track(series, link, "--overwrite")) == 2 and "symbolic link" in capsys.readouterr().err
    assert _tree(target) == before and link.is_symlink()


def test_a_second_writer_is_refused_while_the_first_runs(series, tmp_path, capsys):
    """The issue: two tracks on one --out both exited 0, the later replacing the other's. The lock holds the first
    writer's process id; a second run is refused while it lives, and the lock of a dead one is taken over."""
    out = tmp_path / "track"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / ".track.lock").write_text(str(holder.pid))
        assert main(_track(series, out)) == 2
        err = capsys.readouterr().err
        assert f"being written by another warpmpm run (process {holder.pid}" in err and not out.exists()
        with pytest.raises(InputError, match="another warpmpm run"):
            OutputFolder(str(out), kind="track")
    finally:
        holder.kill()
        holder.wait()
    assert main(_track(series, out)) == 0 and (out / "track.csv").exists()  # the dead writer's lock taken over
    assert not (tmp_path / ".track.lock").exists()


def test_make_truth_and_make_cine_refuse_inputs_and_full_folders(series, tmp_path, capsys):
    planning = os.path.join(series, "planning")
    before = _tree(planning)
    assert main(["make-truth", "--image", os.path.join(planning, "image.nii.gz"), "--labels",
                 os.path.join(planning, "labels.nii.gz"), "--out", planning]) == 2
    assert "the input --image" in capsys.readouterr().err
    assert main(["make-cine", "--image", os.path.join(planning, "image.nii.gz"), "--labels",
                 os.path.join(planning, "labels.nii.gz"), "--out", planning]) == 2
    assert "the input --image" in capsys.readouterr().err
    assert _tree(planning) == before


def test_an_unwritable_out_is_one_error_line(series, capsys):
    """/proc refuses new files even to root (a read-only --out in a clinic's share)."""
    assert main(_track(series, "/proc/warpmpm-track")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error:") and "/proc" in err[-1] and "Traceback" not in "".join(err)


def test_an_interrupted_writer_leaves_the_old_result(tmp_path):
    """An exception while writing: the old folder is kept as it was, the working folder and the lock removed."""
    out = tmp_path / "truth"
    with OutputFolder(str(out), kind="truth") as work:
        open(os.path.join(work, "a.txt"), "w").write("first")
    with pytest.raises(RuntimeError):
        with OutputFolder(str(out), kind="truth", overwrite=True) as work:
            open(os.path.join(work, "a.txt"), "w").write("second")
            raise RuntimeError("killed mid-way")
    assert (out / "a.txt").read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["truth"]


def test_the_record_says_what_made_the_folder_from_what(series, tmp_path):
    """track.json (warpmpm-output.json for other kinds): kind, version, the arguments, the estimator and the full
    configuration, each input's sha256 (a folder's over its files), the machine, the run's time and latency, the outputs
    and its warnings, which still reach the user (and a recording catch_warnings). A user's own track.json is not
    taken for a record."""
    import hashlib
    import json
    import warnings

    from warpmpm.errors import InputWarning
    from warpmpm.output_folder import sha256_of

    out = tmp_path / "track"
    assert main(_track(series, out)) == 0
    rec = json.loads((out / TRACK_RECORD).read_text())
    assert rec["kind"] == "track" and rec["written_by"].startswith("warpmpm ") and rec["arguments"]["out"] == str(out)
    assert rec["estimator"] == "copy" and rec["config"]["estimator"] == "copy" and rec["config"]["registration"] == "gauss-newton"
    assert rec["config"]["solver"]["method"] == "auto" and rec["outputs"] == ["labels"] and rec["frames"] == 2
    assert 0 < rec["latency_s"]["median"] < 60 and rec["n_particles"] > rec["n_driven"] > 0
    labels = os.path.join(series, "planning", "labels.nii.gz")
    got = {i["option"]: i for i in rec["inputs"]}
    assert got["--labels"]["sha256"] == hashlib.sha256(open(labels, "rb").read()).hexdigest()
    assert got["--cine"]["sha256"] == sha256_of(os.path.join(series, "cine")) and len(got["--cine"]["sha256"]) == 64
    assert rec["machine"]["cpus"] >= 1 and rec["wall_s"] > 0
    folder = OutputFolder(str(tmp_path / "w"), kind="truth")
    with pytest.warns(InputWarning, match="a named warning"):
        with folder as work:
            with open(os.path.join(work, "a"), "w") as fh:
                fh.write("x")
            warnings.warn("a named warning", InputWarning)
    assert json.loads((tmp_path / "w" / RECORD).read_text())["warnings"] == ["a named warning"]
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "track.json").write_text('{"kind": "track"}')  # a user's file of that name, not warpmpm's record
    (mine / "track.csv").write_text("frame\n")
    assert main(_track(series, mine, "--overwrite")) == 2 and (mine / "track.json").exists()


def test_a_track_written_before_records_is_still_replaced_and_the_main_job_never_deletes_a_users_folder(series, tmp_path, capsys):
    """An older track (track.csv, particles.npz, labels/ and nothing else, no record) is this tool's: --overwrite replaces
    it. `python examples/run_case.py --out FOLDER` deleted whatever FOLDER was; now only an earlier main job."""
    import importlib.util

    old = tmp_path / "old_track"
    (old / "labels").mkdir(parents=True)
    (old / "track.csv").write_text("frame\n0\n")
    (old / "particles.npz").write_bytes(b"x")
    assert main(_track(series, old, "--overwrite")) == 0 and (old / TRACK_RECORD).exists()
    (old / TRACK_RECORD).unlink()
    (old / "notes.txt").write_text("mine")  # not a track's layout any more
    assert main(_track(series, old, "--overwrite")) == 2 and "did not write" in capsys.readouterr().err
    root = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
    spec = importlib.util.spec_from_file_location("run_case", os.path.join(root, "examples", "run_case.py"))
    job = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(job)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("a user's notes")
    with pytest.raises(SystemExit, match="not an earlier main job"):
        job.main(["--out", str(mine)])
    assert (mine / "notes.txt").read_text() == "a user's notes"


def test_make_truth_still_makes_its_missing_parent_folders(tmp_path):
    """Creating folders deletes nothing: make-truth made --out's missing parents before output folders were locked, and
    still does (track and make-cine refuse a missing parent, as they always did)."""
    out = tmp_path / "a" / "b" / "truth"
    assert main(["make-truth", "--phantom-resolution", "4", "--frames", "2", "--cell-mm", "12", "--out", str(out)]) == 0
    assert (out / "truth.json").exists() and (out / RECORD).exists()
