"""The cine tracker on finite-element truths: the completion against the slice-driven estimate and the copy, same run.

    python benchmarks/track_fem.py                                   # phantom, MR, CT; sagittal+coronal and sagittal
    python benchmarks/track_fem.py --cases phantom --planes sagittal,coronal --frames 8
    python benchmarks/track_fem.py --report                          # re-print the table of results/track_fem.json

For each case: a finite-element truth (``warpmpm make-truth``, breathing + a duodenal push, seed 0, 16 frames; not
made by anything the tracker uses), a cine series imaged from it (``warpmpm make-cine``: DICOM frames, interleaved
when two planes), tracked from the planning scan alone with each estimator (``--estimator completion`` and
``slice-driven``), each scored against the truth (``warpmpm evaluate-track``): every organ's mean error over the
frames (mm) of the estimate, of ``propagate`` (the frame's per-organ motion copied to every particle; organs on no
plane take the whole slice's motion) and of ``initial`` (no motion); the completion's one-off set-up (s) and the
median and p95 latency of a frame after the first (registration included). Series and tracks are kept under
``--work``. The samples are read from ``../shared/data`` (or ``$WARPMPM_SAMPLE_DATA``); an absent one is skipped with
a message. Raw numbers: ``benchmarks/results/track_fem.json``.
"""

import argparse
import os
import time


from warpmpm.experiment import raw_numbers as raw
from warpmpm.experiment.fem_cases import load_on_disk

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
ORGANS = ("pancreas", "stomach", "duodenum", "left_kidney")


def table(rows: list[dict]) -> str:
    head = ("| case | planes | estimator | " + " | ".join(f"{o.replace('_', ' ')}: estimate / copy" for o in ORGANS)
            + " | set-up s | frame median / p95 s |")
    out = [head, "|---|---|---|" + "---|" * len(ORGANS) + "---|---|"]
    for r in rows:
        ev = r["eval"]["results"]
        cells = []
        for o in ORGANS:
            e, c = ev["estimate"]["organs"].get(o), ev["propagate"]["organs"].get(o)
            cells.append(f"{e['error_mm']:.2f} / {c['error_mm']:.2f}" if e else "")
        lat = r["eval"]["latency_s"]
        out.append(f"| {r['case']} | {r['planes']} | {r['estimator']} | " + " | ".join(cells)
                   + f" | {r['setup_s']:.1f} | {lat['median']:.3f} / {lat['p95']:.3f} |")
    return "\n".join(out)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default="phantom,mr,ct")
    p.add_argument("--planes", default="sagittal+coronal,sagittal", help="plane sets, comma-separated; '+' joins planes")
    p.add_argument("--estimators", default="completion,slice-driven",
                   help="estimators to compare, comma-separated; copy:RULE is the copy with TrackerConfig.unseen=RULE "
                   "(whole-slice, nearest, global, none)")
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--work", default=os.path.join(ROOT, "runs", "track_fem"), help="truths, series and tracks go here (kept)")
    p.add_argument("--raw", type=raw.check_name, default="default", help="the run's name in results/track_fem.json")
    p.add_argument("--report", action="store_true", help="print the table of run --raw and stop")
    a = p.parse_args(argv)
    if a.report:
        print(table(raw.load(raw.results_path(__file__), a.raw)))
        return
    from warpmpm.cine import read_cine
    from warpmpm.experiment.cine_series import evaluate_track
    from warpmpm.cli import main as warpmpm
    from warpmpm.tracker import Tracker, TrackerConfig

    rows = []
    for name in a.cases.split(","):
        base = os.path.join(a.work, name)
        loaded = load_on_disk(name, base)
        if loaded is None:
            continue
        case, preset, img, lab = loaded
        plan = ["--image", img, "--labels", lab, "--preset", preset]
        truth = os.path.join(base, "truth")
        if not os.path.isdir(truth):
            assert warpmpm(["make-truth", *plan, "--load", "breathing,push", "--frames", str(a.frames), "--out", truth]) == 0
        for planes in a.planes.split(","):
            series = os.path.join(base, f"cine_{planes}")
            if not os.path.isdir(series):
                assert warpmpm(["make-cine", *plan, "--truth", truth, "--plane", planes.replace("+", ","), "--out", series]) == 0
            frames = read_cine(os.path.join(series, "cine"))
            for est in a.estimators.split(","):
                t0 = time.perf_counter()
                name_, _, rule = est.partition(":")  # copy:RULE is the copy with that rule for the organs a frame misses
                cfg = TrackerConfig(estimator=name_, preset=preset, **({"unseen": rule} if rule else {}))
                tracker = Tracker(case, frames, cfg)
                setup = time.perf_counter() - t0
                out = os.path.join(base, f"track_{planes}_{est.replace(':', '_')}")
                if os.path.isdir(out):
                    import shutil

                    shutil.rmtree(out)  # this benchmark's own track folder under --work
                tracker.run(out)
                ev = evaluate_track(out, truth)
                rows.append({"case": name, "planes": planes, "estimator": est, "setup_s": setup,
                             "completion_setup_s": tracker.estimator.setup_s, "frames": len(frames),
                             "truth_made_by": "warpmpm.truth_fem (finite elements), breathing + push, seed 0", "eval": ev})
                raw.save(__file__, rows, run=a.raw, quiet=True)
                print(table(rows[-1:]).splitlines()[-1], flush=True)
    print(table(rows))
    raw.save(__file__, rows, run=a.raw)


if __name__ == "__main__":
    main()
