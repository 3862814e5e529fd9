"""Writing results so that nothing half-written is ever left: atomic JSON, and a CSV appender for sweeps
that is safe to resume and refuses a second writer."""

from __future__ import annotations

import csv
import json
import os
import sys
import tempfile

import numpy as np

from ..errors import InputError

__all__ = ["check_output_path", "write_json_atomic", "read_rows", "CsvAppender"]


def check_output_path(path: str, option: str) -> str:
    """The absolute path of an output file to write later; :class:`InputError` now (before any work)
    when its folder is missing or the path is a directory."""
    path = os.path.abspath(path)
    d = os.path.dirname(path)
    if not os.path.isdir(d):
        raise InputError(f"output folder {d} for {option} does not exist")
    if os.path.isdir(path):
        raise InputError(f"{option} {path} is a directory; give a file name")
    return path


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if hasattr(o, "to_json"):
        return o.to_json()
    return str(o)


def write_json_atomic(path: str, data) -> None:
    """Write JSON (a dict or anything with ``to_json()``) through a temporary file and a rename."""
    path = check_output_path(path, "the JSON output")
    if hasattr(data, "to_json"):
        data = data.to_json()
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2, default=_json_default)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def read_rows(path: str) -> list[dict]:
    """The complete rows of a CSV written by :class:`CsvAppender` (a torn last line, from a killed run, is left out)."""
    if not os.path.exists(path):
        return []
    with open(path, newline="") as f:
        text = f.read()
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    rows = list(csv.DictReader(text.splitlines()))
    return rows


class CsvAppender:
    """Append rows to a CSV as tasks finish (flushed per task), in the file's own column order when it exists.

    Holds an exclusive lock on ``path + '.lock'`` while open: a second sweep on the same file is refused
    (it would write every row twice). A torn last line left by a killed run is cut off on opening,
    and reported on stderr.
    """

    def __init__(self, path: str, fields: list[str]):
        self.path, self.fields = path, fields
        self._lock = None

    def __enter__(self):
        import fcntl

        self._lock = open(self.path + ".lock", "w")
        try:
            fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._lock.close()
            self._lock = None
            raise InputError(f"{self.path} is being written by another run (lock {self.path}.lock); wait for it or use another --out") from None
        new_file = not os.path.exists(self.path) or os.path.getsize(self.path) == 0
        if not new_file:
            with open(self.path, "rb+") as f:
                data = f.read()
                if not data.endswith(b"\n"):
                    cut = data.rfind(b"\n") + 1
                    f.truncate(cut)
                    print(f"{self.path}: dropped a torn last line ({len(data) - cut} bytes) left by an interrupted run",
                          file=sys.stderr)
            with open(self.path, newline="") as f:  # a CSV from an older version keeps its header
                self.fields = next(csv.reader(f), None) or self.fields
        self.f = open(self.path, "a", newline="")
        self.w = csv.DictWriter(self.f, fieldnames=self.fields, extrasaction="ignore")
        if new_file:
            self.w.writeheader()
        return self

    def write(self, rows: list[dict]) -> None:
        for row in rows:
            self.w.writerow(row)
        self.f.flush()

    def __exit__(self, *exc):
        self.f.close()
        if self._lock is not None:
            self._lock.close()
            try:
                os.remove(self.path + ".lock")
            except OSError:
                pass
