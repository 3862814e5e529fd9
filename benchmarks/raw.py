"""Raw numbers of a benchmark run, kept beside the tables in ``benchmarks/README.md``.

``save(name, data)`` writes ``benchmarks/results/<name>.json``: the numbers the script printed, with
the machine, the date, the command line and the package versions, so a table can be re-read (or
re-plotted) without re-running it. Written through a temporary file: never half a file.
"""

import argparse
import datetime
import json
import os
import platform
import re
import sys

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


def machine() -> dict:
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
    """A raw-numbers name that cannot name a file of ``benchmarks/results/`` (argparse prints its message)."""


def check_name(name: str) -> str:
    """``name`` when it can name a file of ``benchmarks/results/`` (letters, digits, ``_``, ``-``, ``.``; no folder, no
    ``.json``), else :class:`RawNameError` (a ValueError) saying so (an ``argparse`` type for ``--raw`` options)."""
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.-]+", name) or name.startswith(".") or name.endswith(".json"):
        raise RawNameError(f"raw-numbers name {name!r}: use letters, digits, '_', '-' and '.', without a folder or '.json' "
                         f"(it becomes benchmarks/results/<name>.json)")
    return name


def save(name: str, data, quiet: bool = False) -> str:
    """Write ``data`` (JSON-able; numpy values are converted) with the run's context; returns the path."""
    check_name(name)
    os.makedirs(RESULTS, exist_ok=True)
    path = os.path.join(RESULTS, f"{name}.json")
    doc = {"benchmark": name, "date": datetime.datetime.now().isoformat(timespec="seconds"), "argv": sys.argv,
           "machine": machine(), "data": data}
    tmp = path + ".part"

    def default(o):
        if hasattr(o, "tolist"):
            return o.tolist()
        if hasattr(o, "item"):
            return o.item()
        return str(o)

    with open(tmp, "w") as f:
        json.dump(doc, f, indent=1, default=default)
    os.replace(tmp, path)
    if not quiet:
        print(f"raw numbers: {os.path.relpath(path)}")
    return path
