"""``python -m viewer RUN.rrd`` opens a recording in the Rerun viewer;
``python -m viewer --summary RUN.rrd`` prints its entities, timelines and counts without a display;
``python -m viewer --screenshot OUT.png RUN.rrd`` saves a picture of the viewer showing the recording
(on a headless machine it starts a virtual screen with ``Xvfb`` and software Vulkan, e.g. Debian's
``xvfb`` and ``mesa-vulkan-drivers``)."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys

from viewer.recording import rerun_executable


def summarize(path: str) -> dict:
    """Entities of a recording with their row counts, timelines, point counts and step range,
    read back through Rerun's own chunk reader."""
    from rerun.chunk import RrdReader

    if not os.path.exists(path):
        raise FileNotFoundError(f"recording not found: {path}")
    out: dict[str, dict] = {}
    try:
        chunks = list(RrdReader(path).stream())
    except Exception as exc:  # noqa: BLE001 - Rerun raises its own types for a junk file
        raise ValueError(f"{path} is not a readable Rerun recording ({type(exc).__name__}: {str(exc).strip()[:200]})") from None
    for chunk in chunks:
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
    if not out:
        raise ValueError(f"{path} holds no recorded data (empty, or not a Rerun recording)")
    return out


def _free_display() -> int:
    n = 90
    while os.path.exists(f"/tmp/.X11-unix/X{n}") or os.path.exists(f"/tmp/.X{n}-lock"):
        n += 1
    return n


def screenshot(path: str, out_png: str, size: tuple[int, int] = (1600, 900), timeout_s: float = 300) -> None:
    """Open ``path`` in the native Rerun viewer and save a screenshot to ``out_png``.

    Uses the current ``DISPLAY``; without one, starts ``Xvfb`` on a free display for the duration
    (the virtual screen is larger than the window so the pointer does not hover over it). Rerun's
    GL backend lacks a texture format on Mesa's software renderer, so Vulkan is asked for there.
    Raises RuntimeError with the viewer's message when no picture was written.
    """
    if not os.path.exists(path):
        raise FileNotFoundError(f"recording not found: {path}")
    exe = rerun_executable()
    env = dict(os.environ)
    xvfb = None
    if not env.get("DISPLAY"):
        if not shutil.which("Xvfb"):
            raise RuntimeError("no DISPLAY and no Xvfb to make one: install Xvfb (Debian: xvfb, mesa-vulkan-drivers) or run with a display")
        n = _free_display()
        xvfb = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", f"{4 * size[0]}x{4 * size[1]}x24"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        env["DISPLAY"] = f":{n}"
        env.setdefault("WGPU_BACKEND", "vulkan")
        env.setdefault("XDG_RUNTIME_DIR", "/tmp")
        import time

        time.sleep(1.0)
    tmp = out_png + ".part.png"
    try:
        proc = subprocess.run([exe, path, "--port", "auto", "--window-size", f"{size[0]}x{size[1]}", "--screenshot-to", tmp],
                              env=env, capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=timeout_s)
        if proc.returncode != 0 or not os.path.exists(tmp):
            lines = [ln for ln in (proc.stderr + proc.stdout).splitlines() if "rror" in ln]
            raise RuntimeError("the Rerun viewer wrote no screenshot: " + (lines[-1] if lines else f"exit code {proc.returncode}"))
        os.replace(tmp, out_png)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
        if xvfb is not None:
            xvfb.terminate()
            xvfb.wait()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m viewer", description=__doc__)
    p.add_argument("rrd")
    p.add_argument("--summary", action="store_true", help="print entities, timelines and counts (no display needed)")
    p.add_argument("--screenshot", metavar="PNG", help="save a picture of the viewer showing the recording (Xvfb when no display)")
    a = p.parse_args(argv)
    if not os.path.exists(a.rrd):
        print(f"error: recording not found: {a.rrd}", file=sys.stderr)
        return 2
    try:
        summary = summarize(a.rrd)  # also refuses a junk or empty file before a viewer opens it
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if a.summary:
        for ent, e in sorted(summary.items()):
            pts = f", points per row {min(e['points'])}..{max(e['points'])}" if e["points"] else ""
            steps = f", steps {min(e['steps'])}..{max(e['steps'])}" if e["steps"] else ""
            tl = ",".join(sorted(e["timelines"])) or "static"
            print(f"{ent}: {e['rows']} rows [{tl}]{pts}{steps}")
        return 0
    if a.screenshot:
        try:
            screenshot(a.rrd, a.screenshot)
        except RuntimeError as e:
            print(f"error: {e}", file=sys.stderr)
            return 1
        print(f"wrote {a.screenshot}")
        return 0
    exe = rerun_executable()
    return subprocess.call([exe, a.rrd])


if __name__ == "__main__":
    raise SystemExit(main())
