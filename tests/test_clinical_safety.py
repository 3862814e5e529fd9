"""Issue 51: the clinic's files, broken as a careless or unlucky clinic would, through every reader: one `error:` line
naming the file and the fix (or a `warning:` naming the organ and frame), never a traceback, never a silent wrong
result, nothing half-written. The corpus is ``scripts/hostile_inputs.py``'s, run in this process (no interpreter start
per case)."""

import csv
import importlib.util
import os
import types
import warnings

import numpy as np
import pydicom
import pytest

from warpmpm.cli import main
from warpmpm.errors import InputError, InputWarning

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def _hostile():
    spec = importlib.util.spec_from_file_location("hostile_inputs", os.path.join(ROOT, "scripts", "hostile_inputs.py"))
    h = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(h)
    return h


@pytest.fixture(scope="module")
def clinic(tmp_path_factory):
    d = str(tmp_path_factory.mktemp("hostile"))
    h = _hostile()
    h.make_clinic_files(d)
    return h, d


def test_every_broken_clinic_file_is_a_clear_refusal_or_a_named_warning(clinic):
    h, d = clinic
    outcomes, lines = {}, {}
    for name, argv, expected in h.clinic_cases(d):
        before = set(os.listdir(d))
        code, err = h.run_in_process(argv[1:])
        outcomes[name] = h.classify(types.SimpleNamespace(stderr=err, returncode=code), expected, before, d)
        lines[name] = err.strip().splitlines()[-1:] if expected == "error" else [x for x in err.splitlines() if "warning:" in x]
    assert len(outcomes) >= 35
    bad = {n: (o, lines[n]) for n, o in outcomes.items() if o not in ("clear error", "handled")}
    assert not bad, bad
    # each refusal names the file it refuses (or the option) and says what to do
    for name, (line,) in ((n, ln) for n, ln in lines.items() if outcomes[n] == "clear error" and ln):
        assert ("/" in line or "--" in line), (name, line)


def test_refusals_name_the_right_thing(clinic):
    h, d = clinic
    c = f"{d}/clinic"
    track = ["track", "--device", "cpu", "--image", f"{c}/series", "--rtstruct", f"{c}/RS.dcm", "--cine", f"{c}/cine"]
    expect = {
        ("--cine", f"{c}/cine_negative_spacing"): "unusable PixelSpacing",
        ("--cine", f"{c}/cine_one_untimed"): "frame_0001.dcm from file order",
        ("--cine", f"{c}/cine_no_spacing"): "has no PixelSpacing",
        ("--cine", f"{c}/cine_other_for"): "--assume-registered",
        ("--cine", f"{c}/cine_other_patient"): "of patient 'SOMEONE-ELSE'",
        ("--rtstruct", f"{c}/RS_dup_number.dcm"): "gives ROINumber",
        ("--rtstruct", f"{c}/RS_nan.dcm"): "non-finite",
        ("--rtstruct", f"{c}/RS_cut.dcm"): "cut short",
        ("--dose", f"{c}/RD_no_scaling.dcm"): "has no DoseGridScaling",
        ("--dose", f"{c}/RD_nan_scaling.dcm"): "DoseGridScaling 'nan' must be finite",
        ("--dose", f"{c}/RD_zero_spacing.dcm"): "PixelSpacing",
        ("--dose", f"{c}/RD_cgy.dcm"): "cGy labelled Gy",
        ("--dose", f"{c}/RD_negative.dcm"): "negative values",
        ("--dose", f"{c}/RD_other_for.dcm"): "frame of reference",
        ("--image", f"{c}/series_gap"): "1 slice missing",
        ("--image", f"{c}/series_spacing"): "another pixel spacing",
        ("--image", f"{c}/series_tilted"): "tilted 10.0 degrees",
    }
    for (opt, path), text in expect.items():
        argv = list(track)
        if opt in argv:
            argv[argv.index(opt) + 1] = path
        else:
            argv += [opt, path]
        code, err = h.run_in_process([*argv, "--out", f"{d}/never"])
        assert code == 2 and text in err.strip().splitlines()[-1] and os.path.basename(path) in err, (path, err)
        assert not os.path.exists(f"{d}/never")


def test_a_dose_grid_that_misses_the_organs_is_measured_per_organ_and_frame(clinic, tmp_path):
    """The issue: on a real CT most of the pancreas was carried outside the dose grid and counted as 0 Gy without a word.
    Now each organ's share outside the grid is in dose_coverage.csv (planning and every frame) and dose_metrics.csv, and
    a warning names the organ and the share. The grid here holds the lower third of the slices: the shares must be the
    organs' voxels above it, counted independently."""
    h, d = clinic
    c = f"{d}/clinic"
    out = tmp_path / "track"
    with pytest.warns(InputWarning, match=r"% of the pancreas"):
        assert main(["track", "--device", "cpu", "--image", f"{c}/series", "--rtstruct", f"{c}/RS.dcm", "--cine", f"{c}/cine",
                     "--dose", f"{c}/RD_small_grid.dcm", "--out", str(out)]) == 0
    from warpmpm.dicom_rt import case_from_rtstruct

    case = case_from_rtstruct(f"{c}/series", f"{c}/RS.dcm")
    n = int(pydicom.dcmread(f"{c}/RD_small_grid.dcm").NumberOfFrames)
    panc = case.labels == case.label_map["pancreas"]
    expected = 100.0 * panc[n:].sum() / panc.sum()  # slices at or beyond the grid's last plane's centre
    rows = list(csv.DictReader(open(out / "dose" / "dose_coverage.csv")))
    assert rows[0]["frame"] == "planning" and len(rows) == 4
    assert float(rows[0]["pancreas_outside_dose_grid_pct"]) == pytest.approx(expected, abs=0.5)
    metrics = list(csv.DictReader(open(out / "dose" / "dose_metrics.csv")))
    worst = max(float(r["pancreas_outside_dose_grid_pct"]) for r in rows)
    assert all(float(r["outside_dose_grid_max_pct"]) == pytest.approx(worst, abs=0.01) for r in metrics if r["organ"] == "pancreas")
    # the whole grid: nothing outside
    out2 = tmp_path / "track2"
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        assert main(["track", "--device", "cpu", "--image", f"{c}/series", "--rtstruct", f"{c}/RS.dcm", "--cine", f"{c}/cine",
                     "--dose", f"{c}/RD.dcm", "--out", str(out2)]) == 0
    rows = list(csv.DictReader(open(out2 / "dose" / "dose_coverage.csv")))
    assert max(float(v) for r in rows for k, v in r.items() if k != "frame") == 0.0


def test_a_series_without_uids_still_gives_valid_dicom(clinic, tmp_path):
    """The issue: empty Study/Series/Frame of Reference UIDs gave RS/REG/RD files with 183/82/1 dciodvfy errors."""
    import shutil
    import subprocess

    h, d = clinic
    c = f"{d}/clinic"
    out = tmp_path / "track"
    with pytest.warns(InputWarning, match="new UIDs were made"):
        assert main(["track", "--device", "cpu", "--image", f"{c}/series_empty_uids", "--rtstruct", f"{c}/RS.dcm", "--cine",
                     f"{c}/cine", "--dose", f"{c}/RD.dcm", "--dicom", "--out", str(out)]) == 0
    files = [out / "dicom" / "frame_0001" / "RS.dcm", out / "dicom" / "frame_0001" / "REG.dcm", out / "dicom" / "RD_accumulated.dcm"]
    for f in files:
        ds = pydicom.dcmread(f)
        for tag in ("StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID", "FrameOfReferenceUID"):
            assert str(ds.get(tag, "")).strip(), (f, tag)
    if shutil.which("dciodvfy") is None:
        pytest.skip("dciodvfy (dicom3tools) is not installed: the UIDs were checked, the full validation skipped")
    for f in files:
        report = subprocess.run(["dciodvfy", str(f)], capture_output=True, text=True).stderr
        assert not [ln for ln in report.splitlines() if ln.startswith("Error")], (f, report)


def test_valid_inputs_the_readers_once_refused(clinic, tmp_path):
    """AcquisitionTime 'HH' only, a beam-on CSV with a byte-order mark: accepted, and read as they mean."""
    from warpmpm.cine import read_cine

    h, d = clinic
    c = f"{d}/clinic"
    frames = read_cine(f"{c}/cine_hours")
    assert [round(f.time_s) for f in frames] == [0, 3600, 7200]
    from warpmpm.session import read_beam_on as _beam_on

    assert _beam_on(f"{c}/beam_bom.csv", 3) == [0.2, 0.2, 0.2]


def test_make_truth_builds_the_body_it_can_when_no_tissue_is_above_the_organs(tmp_path):
    """The issue: `make-truth` refused a scan cut just above the organs ("breathing needs a superior face of tissue").
    Now the body's own superior surface carries the diaphragm's motion, said in a warning and in truth.json, and the
    pancreas moves inferior with it."""
    import json
    from dataclasses import replace

    from warpmpm.images import write_case
    from warpmpm.phantom import make_phantom
    from warpmpm.truth_fem import TruthConfig, make_truth

    c = make_phantom(resolution=3.0)
    lab, img = c.labels.copy(), c.image.copy()
    top = np.nonzero(lab > 0)[0].max()
    lab[top + 1:] = 0
    img[top + 1:] = img.min()
    case = replace(c, labels=lab, image=img)
    with pytest.warns(InputWarning, match="body's own superior surface"):
        s = make_truth(case, "amos", TruthConfig(loads=("breathing",), frames=4, fps=2.0, cell_mm=9.0))
    assert "superior surface" in s.record["mesh"]["diaphragm_from"]
    f = s.field(2)
    panc = case.labels == case.label_map["pancreas"]
    assert f[panc][:, 2].mean() < -0.5  # inferior (world z is superior)
    write_case(case, tmp_path / "l.nii.gz", tmp_path / "i.nii.gz")
    with pytest.warns(InputWarning):
        assert main(["make-truth", "--image", str(tmp_path / "i.nii.gz"), "--labels", str(tmp_path / "l.nii.gz"), "--frames", "3",
                     "--cell-mm", "9", "--out", str(tmp_path / "truth")]) == 0
    assert "superior surface" in json.loads((tmp_path / "truth" / "truth.json").read_text())["mesh"]["diaphragm_from"]


# fuzz: random truncation, tag deletion and values through the DICOM and CSV readers ----------------------------------

FUZZ_TAGS = {"cine": ["PixelSpacing", "ImagePositionPatient", "ImageOrientationPatient", "AcquisitionTime", "Rows", "Columns",
                      "BitsAllocated", "PixelData", "SliceThickness", "FrameOfReferenceUID", "InstanceNumber"],
             "rs": ["StructureSetROISequence", "ROIContourSequence", "ReferencedFrameOfReferenceSequence", "SOPClassUID"],
             "rd": ["DoseGridScaling", "PixelSpacing", "ImagePositionPatient", "ImageOrientationPatient", "GridFrameOffsetVector",
                    "NumberOfFrames", "DoseUnits", "PixelData", "Rows", "Columns", "BitsAllocated"]}
FUZZ_VALUES = ["", "nan", "-1", "0", "1e308", "abc", "-0", "inf"]


def _crash(read, target) -> str | None:
    """What a reader does with a broken file that is neither a result nor an InputError (what the user would see as a
    traceback), or None."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            read(target)
    except InputError:
        return None
    except Exception as exc:  # noqa: BLE001
        return f"{type(exc).__name__}: {exc}"[:200]
    return None


def _readers(c):
    """Each reader of a clinic file, as the tracker calls it."""
    from warpmpm.cine import read_cine
    from warpmpm.dicom_rt import case_from_rtstruct
    from warpmpm.dose import read_dose

    return {"cine": lambda folder: read_cine(folder), "rs": lambda path: case_from_rtstruct(f"{c}/series", path),
            "rd": lambda path: read_dose(path)}


def _mutate(src, dst, rng, kind):
    data = open(src, "rb").read()
    how = rng.integers(3)
    if how == 0:  # truncation
        open(dst, "wb").write(data[: int(rng.integers(1, len(data)))])
        return f"cut at {len(open(dst, 'rb').read())} bytes"
    ds = pydicom.dcmread(src)
    tag = FUZZ_TAGS[kind][int(rng.integers(len(FUZZ_TAGS[kind])))]
    if how == 1:
        if tag in ds:
            delattr(ds, tag)
        ds.save_as(dst)
        return f"without {tag}"
    value = FUZZ_VALUES[int(rng.integers(len(FUZZ_VALUES)))]
    try:
        elem = ds[tag] if tag in ds else None
        if elem is not None and elem.VR in ("DS", "IS", "TM", "UI", "LO", "SH", "CS", "US", "UL", "FL", "FD", "SQ", "OB", "OW"):
            if elem.VR in ("US", "UL"):
                elem.value = int(rng.integers(0, 70000))
            elif elem.VR in ("SQ", "OB", "OW"):
                delattr(ds, tag)
            elif elem.VM > 1:
                elem.value = [value] * elem.VM
            else:
                elem.value = value
        ds.save_as(dst)
    except Exception:  # noqa: BLE001 - pydicom refused to write that value: the truncation stands in
        open(dst, "wb").write(data[: len(data) // 2])
        return "cut in half"
    return f"{tag} = {value!r}"


@pytest.mark.parametrize("kind", ["cine", "rs", "rd"])
def test_fuzzed_clinic_files_give_input_errors_or_a_result_never_anything_else(clinic, tmp_path, kind):
    """60 random mutations of each kind of file: every reader either reads it or raises InputError (which the command
    line turns into one `error:` line); any other exception is a traceback the user would see."""
    import shutil

    h, d = clinic
    c = f"{d}/clinic"
    read = _readers(c)[kind]
    rng = np.random.default_rng({"cine": 1, "rs": 2, "rd": 3}[kind])
    crashes = []
    for trial in range(60):
        if kind == "cine":
            folder = tmp_path / f"cine{trial}"
            shutil.copytree(f"{c}/cine", folder)
            victim = sorted(folder.iterdir())[int(rng.integers(3))]
            what = _mutate(str(victim), str(victim), rng, kind)
            target = str(folder)
        else:
            target = str(tmp_path / f"{kind}{trial}.dcm")
            what = _mutate(f"{c}/{'RS' if kind == 'rs' else 'RD'}.dcm", target, rng, kind)
        crash = _crash(read, target)
        if crash:
            crashes.append((what, crash))
    assert not crashes, crashes


@pytest.mark.parametrize("reader", ["beam-on", "plane-sweep", "sweep", "track"])
def test_fuzzed_csvs_give_input_errors_never_anything_else(tmp_path, reader):
    from warpmpm.session import read_beam_on as _beam_on
    from warpmpm.experiment.io import read_csv
    from warpmpm.experiment.train_planes import read_sweep_rows

    good = {"beam-on": "frame,beam_on_s\n0,0.2\n1,0.3\n2,0.1\n",
            "plane-sweep": "case,truth_seed,load,family,planes,copy_pancreas_mm\nphantom0,0,breathing,sagittal,sagittal:20,0.5\n",
            "sweep": "case,protocol,deformation,organs,orientation,slice,error_mm\nphantom0,paper,1,p,axial,8,3.2\n",
            "track": "frame,time_s,latency_s\n0,0.0,0.1\n1,0.3,0.1\n"}[reader]
    call = {"beam-on": lambda p: _beam_on(p, 3), "plane-sweep": lambda p: read_sweep_rows([p]),
            "sweep": lambda p: read_csv(p, "sweep CSV", ("case", "organs")),
            "track": lambda p: read_csv(p, "track table", ("frame", "latency_s"), torn="refuse")}[reader]
    rng = np.random.default_rng(7)
    data = good.encode()
    crashes = []
    for trial in range(80):
        b = bytearray(data)
        how = trial % 4
        if how == 0:
            b = b[: int(rng.integers(0, len(b)))]
        elif how == 1:
            for _ in range(3):
                b[int(rng.integers(len(b)))] = int(rng.integers(256))
        elif how == 2:
            b = bytearray(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8).tobytes())
        else:
            b = bytearray(b"\xef\xbb\xbf") + b.replace(b",", b";" if rng.random() < 0.5 else b",")
        p = tmp_path / f"f{trial}.csv"
        p.write_bytes(bytes(b))
        crash = _crash(call, str(p))
        if crash:
            crashes.append((bytes(b)[:60], crash))
    assert not crashes, crashes


def test_resuming_a_finished_plane_sweep_makes_no_truth_and_leaves_no_temp_folder(tmp_path, monkeypatch, capsys):
    """The issue: resuming on a finished CSV took 373 s to write nothing (each task remade its truth first), and every task
    left a plane-sweep-* folder in the temp folder. Ctrl-C said 'nothing was written' while finished rows stayed."""
    import tempfile

    import warpmpm.truth_fem as truth_fem

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    os.makedirs(tmp_path / "tmp")
    out = tmp_path / "planes.csv"
    args = ["sweep-planes", "--phantom-seeds", "0", "--phantom-resolution", "3", "--truth-seeds", "0", "--loads", "breathing",
            "--families", "sagittal", "--positions", "1", "--truth-cell-mm", "12", "--out", str(out)]
    assert main(args) == 0
    n = len(list(csv.DictReader(open(out))))
    assert n >= 2 and not os.listdir(tmp_path / "tmp")
    made = []
    real = truth_fem.make_truth
    monkeypatch.setattr(truth_fem, "make_truth", lambda *a, **k: made.append(1) or real(*a, **k))
    import warpmpm.experiment.plane_sweep as ps

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    assert main(args) == 0 and not made  # finished: skipped before any truth
    assert len(list(csv.DictReader(open(out)))) == n
    monkeypatch.setattr(ps, "run_tasks", interrupted)
    capsys.readouterr()
    assert main(args) == 130
    assert f"the {n} rows finished so far are kept in {out}" in capsys.readouterr().err


def test_fuzzed_vendor_cine_frames_give_input_errors_never_anything_else(tmp_path):
    """The real Elekta Unity `.bin` and DICOM frames of ../shared/data, cut at random and with random bytes overwritten
    (80 each): the frame reader reads them or refuses them with InputError."""
    from conftest import DATA

    from warpmpm.cine import read_frame

    folder = os.path.join(DATA, "unity_cine")
    if not os.path.isdir(folder):
        pytest.skip(f"the vendor cine frames are not in {folder} (../shared/data): nothing to fuzz")
    rng = np.random.default_rng(11)
    crashes = []
    for name in sorted(os.listdir(folder)):
        data = open(os.path.join(folder, name), "rb").read()
        for trial in range(80):
            b = bytearray(data)
            if trial % 2:
                b = b[: int(rng.integers(1, len(b)))]
            else:
                for _ in range(int(rng.integers(1, 8))):
                    b[int(rng.integers(len(b)))] = int(rng.integers(256))
            p = tmp_path / f"{trial}_{name}"
            p.write_bytes(bytes(b))
            crash = _crash(read_frame, str(p))
            if crash:
                crashes.append((name, trial, crash))
            p.unlink()
    assert not crashes, crashes


def test_a_gpu_is_named_by_its_number_and_nothing_else_is_taken_for_a_device(capsys):
    """Issue 53: `--device cuda:1` was refused by the command line; `--device gpu` must stay one clear line."""
    from warpmpm.cli import build_parser

    base = ["track", "--image", "i", "--labels", "l", "--cine", "c", "--out", "o"]
    assert build_parser().parse_args([*base, "--device", "cuda:1"]).device == "cuda:1"
    assert build_parser().parse_args([*base, "--device", "cpu"]).device == "cpu"
    with pytest.raises(SystemExit):
        build_parser().parse_args([*base, "--device", "gpu"])
    assert "use cpu, cuda or cuda:N" in capsys.readouterr().err


def test_every_json_written_is_strict_json_with_the_reason_for_each_null(tmp_path):
    """Issue 53, item 4: undefined figures were written as NaN, which strict readers refuse. Now null with the reason."""
    import json

    from warpmpm.errors import strict_json
    from warpmpm.experiment.io import write_json_atomic

    doc = {"error_mm": float("nan"), "p95": np.float32(np.inf), "ok": np.float64(1.5), "rows": [1.0, float("nan")],
           "nested": {"dice": np.nan, "n": np.int64(3)}, "arr": np.array([0.5, np.nan])}
    write_json_atomic(str(tmp_path / "a.json"), doc)
    text = (tmp_path / "a.json").read_text()
    back = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in a strict JSON file"))
    assert back["error_mm"] is None and "undefined" in back["error_mm_null_reason"]
    assert back["p95"] is None and back["p95_null_reason"] == "infinite" and back["ok"] == 1.5
    assert back["rows"] == [1.0, None] and back["arr"] == [0.5, None]
    assert back["nested"] == {"dice": None, "dice_null_reason": "not a number: undefined for this run", "n": 3}
    assert strict_json(float("nan")) is None
