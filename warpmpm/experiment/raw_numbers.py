"""Raw numbers of a benchmark or study, kept beside the script that measured them.

A script ``benchmarks/<name>.py`` keeps its numbers in ``benchmarks/results/<name>.json``: one file per script, one
entry per named run in it (``{"benchmark": name, "runs": {run: {"date", "argv", "machine", "data"}}}``), so a table
can be re-read or re-plotted without re-running it, and a run of one mode never overwrites another mode's numbers.
Every write goes through a temporary file: never half a file.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import sys

from ..errors import strict_json

__all__ = ["machine", "check_name", "results_path", "save", "load"]


def machine() -> dict:
    """The machine a run was measured on: host, processor, cores, Python and Warp versions."""
    info = {"node": platform.node(), "processor": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "python": platform.python_version()}
    try:
        with open("/proc/cpuinfo") as f:
            names = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
        if names:
            info["cpu"] = names[0]
    except OSError:
        pass
    try:
        import warp as wp

        info["warp"] = wp.__version__
    except ImportError:
        pass
    return info


class RawNameError(ValueError, argparse.ArgumentTypeError):
    """A run name that cannot be a key of a results file (argparse prints its message)."""


def check_name(name: str) -> str:
    """``name`` when it can name a run (letters, digits, ``_``, ``-``, ``.``; no folder, no ``.json``), else
    :class:`RawNameError` (a ValueError) saying so; usable as an ``argparse`` type."""
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.-]+", name) or name.startswith(".") or name.endswith(".json"):
        raise RawNameError(f"raw-numbers run name {name!r}: use letters, digits, '_', '-' and '.', without a folder or '.json'")
    return name


def results_path(script: str) -> str:
    """``<folder of script>/results/<script's stem>.json`` (``script`` is the script's ``__file__``)."""
    folder, base = os.path.split(os.path.abspath(script))
    return os.path.join(folder, "results", os.path.splitext(base)[0] + ".json")


def _default(o):
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    return str(o)


def save(script: str, data, run: str = "default", quiet: bool = False) -> str:
    """Write ``data`` (JSON-able; numpy values are converted) as run ``run`` of ``results_path(script)`` with the
    date, the command line and the machine, keeping the file's other runs; returns the path."""
    check_name(run)
    path = results_path(script)
    doc = {"benchmark": os.path.splitext(os.path.basename(path))[0], "runs": {}}
    if os.path.exists(path):
        with open(path) as f:
            doc = json.load(f)
    doc["runs"][run] = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "argv": sys.argv,
                        "machine": machine(), "data": data}
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = path + ".part"
    with open(tmp, "w") as f:
        json.dump(strict_json(json.loads(json.dumps(doc, default=_default))), f, indent=1, allow_nan=False)
    os.replace(tmp, path)
    if not quiet:
        print(f"raw numbers: {os.path.relpath(path)} (run {run!r})")
    return path


def load(path: str, run: str = "default"):
    """The ``data`` of run ``run`` of a results file; ``KeyError`` naming the runs it holds when it has no such run."""
    with open(path) as f:
        runs = json.load(f)["runs"]
    if run not in runs:
        raise KeyError(f"{path} holds no run {run!r}; it holds {', '.join(sorted(runs))}")
    return runs[run]["data"]
