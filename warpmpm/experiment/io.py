"""Writing results so that nothing half-written is ever left: atomic JSON, and a CSV appender for sweeps
that is safe to resume and refuses a second writer."""

from __future__ import annotations

import csv
import json
import os
import sys
import tempfile


from ..errors import InputError

__all__ = ["check_output_path", "write_json_atomic", "read_rows", "CsvAppender"]


def check_output_path(path: str, option: str, inputs=()) -> str:
    """The absolute path of an output file to write later; :class:`InputError` now (before any work) when its folder is
    missing or cannot be written, the path is a directory, a symbolic link or not a regular file, or it is one of the
    run's ``inputs`` ((option, path) pairs: an output never replaces an input)."""
    from ..output_folder import check_not_an_input

    path = os.path.abspath(path)
    d = os.path.dirname(path)
    if not os.path.isdir(d):
        raise InputError(f"output folder {d} for {option} does not exist")
    if os.path.isdir(path):
        raise InputError(f"{option} {path} is a directory; give a file name")
    if os.path.islink(path) or (os.path.exists(path) and not os.path.isfile(path)):
        raise InputError(f"{option} {path} is a link or a special file; name a new file")
    check_not_an_input(path, option, inputs)
    try:  # a folder that refuses new files (read-only, or a system folder) is found now, not after the run
        fd, probe = tempfile.mkstemp(dir=d, prefix=".warpmpm-probe-")
        os.close(fd)
        os.remove(probe)
    except OSError as exc:
        raise InputError(f"the folder {d} for {option} cannot be written ({exc.strerror}); name a folder you can write "
                         "to") from None
    return path


def write_json_atomic(path: str, data) -> None:
    """Write JSON (a dict or anything with ``to_json()``) through a temporary file and a rename."""
    from ..errors import strict_json

    path = check_output_path(path, "the JSON output")
    if hasattr(data, "to_json"):
        data = data.to_json()
    data = strict_json(data)  # NaN and Infinity as null with the reason beside them: strict readers accept it
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2, allow_nan=False)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def read_csv(path: str, what: str, required: tuple[str, ...] = (), fix: str = "", torn: str = "drop") -> list[dict]:
    """The rows of a CSV the tool wrote or a user made, refused with one line naming the file and ``fix`` when it is not a
    regular file, not UTF-8 text (a byte-order mark is accepted), holds NUL bytes, or lacks a ``required`` column.
    A last line without its newline (a run killed while writing it) is dropped with ``torn="drop"`` (a warning says so)
    or refused with ``torn="refuse"``. Values and column names are stripped of surrounding spaces."""
    import warnings

    from ..errors import InputWarning

    hint = f"; {fix}" if fix else ""
    if not os.path.exists(path):
        raise InputError(f"{what} {path} not found{hint}")
    if not os.path.isfile(path):
        raise InputError(f"{what} {path} is not a regular file{hint}")
    import gzip

    opener = gzip.open if path.endswith(".gz") else open
    try:
        with opener(path, "rt", newline="", encoding="utf-8-sig") as f:
            text = f.read()
    except (UnicodeDecodeError, EOFError, gzip.BadGzipFile):
        raise InputError(f"{what} {path} is not a CSV text file (not UTF-8, or a broken gzip){hint}") from None
    if "\x00" in text:
        raise InputError(f"{what} {path} is not a CSV text file (it holds NUL bytes){hint}")
    if text and not text.endswith("\n"):
        cut = text.rfind("\n") + 1
        if torn == "refuse":
            raise InputError(f"{what} {path} ends in the middle of a line (cut short: a run killed while writing it?){hint}")
        if cut and text[cut:].strip():
            warnings.warn(f"{path}: its last line is cut short (a run killed while writing it?) and is left out",
                          InputWarning, stacklevel=2)
        text = text[:cut]
    try:
        reader = csv.DictReader(text.splitlines())
        fields = [f.strip() for f in (reader.fieldnames or [])]
        reader.fieldnames = fields
        rows = [{(k or "").strip(): (v.strip() if isinstance(v, str) else v) for k, v in r.items()} for r in reader]
    except csv.Error as exc:
        raise InputError(f"{what} {path} is not a readable CSV ({exc}){hint}") from None
    missing = [c for c in required if c not in fields]
    if missing and (rows or fields):
        raise InputError(f"{path} is not a {what}: it has no column {', '.join(repr(m) for m in missing)} (it has "
                         f"{', '.join(fields[:8]) or 'none'}{' ...' if len(fields) > 8 else ''}){hint}")
    return rows


def read_rows(path: str, required: tuple[str, ...] = (), what: str = "CSV", fix: str = "") -> list[dict]:
    """The complete rows of a CSV written by :class:`CsvAppender` (a torn last line, from a killed run, is left out);
    [] when the file does not exist or is empty. A file that is not such a CSV is refused (:func:`read_csv`)."""
    if not os.path.exists(path) or (os.path.isfile(path) and os.path.getsize(path) == 0):
        return []
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # CsvAppender reports and cuts a torn line itself
        return read_csv(path, what, required, fix)


class CsvAppender:
    """Append rows to a CSV as tasks finish (flushed per task), in the file's own column order when it exists.

    Holds an exclusive lock on ``path + '.lock'`` while open: a second sweep on the same file is refused
    (it would write every row twice). A torn last line left by a killed run is cut off on opening,
    and reported on stderr.
    """

    def __init__(self, path: str, fields: list[str], required: tuple[str, ...] = (), what: str = "CSV", fix: str = ""):
        self.path, self.fields = path, fields
        self.required, self.what, self.fix = tuple(required), what, fix
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
            try:  # a file this appender can resume: a text CSV with the key columns (else refused, the lock let go)
                import warnings

                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    read_csv(self.path, self.what, self.required, self.fix)
            except BaseException:
                self._release()
                raise
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
        self._release()

    def _release(self) -> None:
        if self._lock is not None:
            self._lock.close()
            try:
                os.remove(self.path + ".lock")
            except OSError:
                pass
