"""``python -m viewer RUN.rrd`` opens a recording in the Rerun viewer;
``python -m viewer --summary RUN.rrd`` prints its entities, timelines and counts without a display."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys


def summarize(path: str) -> dict:
    """Entities of a recording with their row counts, timelines, point counts and step range,
    read back through Rerun's own chunk reader."""
    from rerun.chunk import RrdReader

    if not os.path.exists(path):
        raise FileNotFoundError(f"recording not found: {path}")
    out: dict[str, dict] = {}
    for chunk in RrdReader(path).stream():
        ent = chunk.entity_path
        if ent.startswith("/__"):
            continue
        rb = chunk.to_record_batch()
        e = out.setdefault(ent, {"rows": 0, "timelines": set(), "points": [], "steps": [], "static": chunk.is_static})
        e["rows"] += chunk.num_rows
        e["timelines"].update(t for t in chunk.timeline_names if t != "log_time")
        for col in ("Points3D:positions", "Arrows3D:vectors"):
            if col in rb.schema.names:
                e["points"] += [len(x) if x is not None else 0 for x in rb.column(col).to_pylist()]
        if "step" in rb.schema.names:
            e["steps"] += [int(v) for v in rb.column("step").to_pylist() if v is not None]
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m viewer", description=__doc__)
    p.add_argument("rrd")
    p.add_argument("--summary", action="store_true", help="print entities, timelines and counts (no display needed)")
    a = p.parse_args(argv)
    if not os.path.exists(a.rrd):
        print(f"error: recording not found: {a.rrd}", file=sys.stderr)
        return 2
    if a.summary:
        for ent, e in sorted(summarize(a.rrd).items()):
            pts = f", points per row {min(e['points'])}..{max(e['points'])}" if e["points"] else ""
            steps = f", steps {min(e['steps'])}..{max(e['steps'])}" if e["steps"] else ""
            tl = ",".join(sorted(e["timelines"])) or "static"
            print(f"{ent}: {e['rows']} rows [{tl}]{pts}{steps}")
        return 0
    exe = shutil.which("rerun") or os.path.join(os.path.dirname(sys.executable), "rerun")
    return subprocess.call([exe, a.rrd])


if __name__ == "__main__":
    raise SystemExit(main())
