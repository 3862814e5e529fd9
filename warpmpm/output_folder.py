"""Output folders that never cost a user their data.

Every command that writes a folder (``track``, ``make-cine``, ``make-truth``) writes it through
:class:`OutputFolder`:

- **Nothing deleted that this tool did not write.** An existing, non-empty ``--out`` is replaced only with
  ``--overwrite`` and only when it holds this tool's record file (:data:`RECORD`, written into every folder the
  tool makes) of the same kind; an input of the run (the planning series, the cine folder, a label map ...) is
  never an output folder, nor inside one. A symbolic link is refused (name the real folder).
- **One writer.** A lock file beside ``--out`` (``.NAME.lock``, holding the writer's process id) makes a second
  run on the same ``--out`` fail at once; a lock whose process is gone (a killed run) is taken over.
- **Nothing half-written.** The result is written into a working folder beside ``--out`` and moved into place
  when it is complete; an old result is moved aside first and removed only once the new one is in place.
  A killed run leaves its working folder, which the next run in the same parent folder removes (it carries the
  dead process's id).

Every refusal is an :class:`~warpmpm.errors.InputError` naming the folder and the fix, raised before any work.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterable

from .errors import InputError, strict_json

__all__ = ["RECORD", "RECORD_NAMES", "record_name", "OutputFolder", "check_not_an_input", "remove_dead_work_folders",
           "written_by_warpmpm", "write_record",
           "LEGACY_LAYOUTS"]

RECORD = "warpmpm-output.json"
"""The record file in every output folder this tool writes (a track's is ``track.json``, :data:`RECORD_NAMES`): what it is (``kind``), what wrote it (``written_by``,
``commit`` where the package runs from a git checkout), when (``created``, ``wall_s``), from what (``inputs``: each
input's option, path and sha256; a folder's over its files' names and bytes), where (``machine``), with which
arguments, and every warning the run gave. ``--overwrite`` replaces a folder only when it holds this file."""

#: kinds whose record file has a name of its own (any other kind's is :data:`RECORD`)
RECORD_NAMES = {"track": "track.json"}

WORK_PREFIX = ".warpmpm-work-"


def record_name(kind: str) -> str:
    """The record file's name in a folder of ``kind``."""
    return RECORD_NAMES.get(kind, RECORD)

#: what a folder of each kind held before the record file existed (2026-12-03 and earlier): a folder holding nothing
#: else, and the first name listed, is taken as this tool's (so ``--overwrite`` replaces an older track too)
LEGACY_LAYOUTS = {
    "track": ("track.csv", "particles.npz", "labels", "displacement", "dicom", "dose"),
    "main-job": ("log.txt", "planning", "truth", "cine", "track", "track.rrd", "eval.json", "eval.png"),
}


def written_by_warpmpm(folder: str, kind: str) -> bool:
    """Whether ``folder`` is an output of this tool of ``kind``: its record file says so, or (written before records
    existed) it holds exactly :data:`LEGACY_LAYOUTS`' names of that kind and the first of them."""
    rec = OutputFolder._read_record(folder)
    if rec is not None:
        return rec.get("kind") == kind
    layout = LEGACY_LAYOUTS.get(kind)
    try:
        names = set(os.listdir(folder))
    except OSError:
        return False
    return bool(layout) and layout[0] in names and names <= set(layout)


def write_record(folder: str, kind: str, **fields) -> None:
    """Write the record file (:data:`RECORD`) of ``kind`` into ``folder`` (what :class:`OutputFolder` writes on commit;
    for a script that fills a folder step by step)."""
    from . import __version__

    rec = {"kind": kind, "written_by": f"warpmpm {__version__}", "commit": _commit(),
           "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": _machine(), **fields}
    with open(os.path.join(folder, record_name(kind)), "w") as fh:
        json.dump(strict_json(rec), fh, indent=1, allow_nan=False)


def _real(path: str) -> str:
    return os.path.realpath(os.path.abspath(path))


def _inside(path: str, folder: str) -> bool:
    """``path`` is ``folder`` or lies under it (both real paths)."""
    return path == folder or path.startswith(folder.rstrip(os.sep) + os.sep)


def check_not_an_input(out: str, option: str, inputs: Iterable[tuple[str, str]]) -> None:
    """Refuse an output path that is one of the run's inputs or holds one. ``inputs``: (option, path) pairs; None
    paths are skipped."""
    real = _real(out)
    for opt, path in inputs:
        if not path:
            continue
        p = _real(path)
        if _inside(p, real):
            what = "is" if p == real else "holds"
            raise InputError(f"{option} {out} {what} the input {opt} {path}: an output never replaces an input; name a "
                             "new folder")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _read_pid(path: str) -> int | None:
    try:
        with open(path) as fh:
            return int(fh.read().strip())
    except (OSError, ValueError):
        return None


def remove_dead_work_folders(parent: str) -> None:
    """Remove the working folders that killed runs left in ``parent``: those carrying the id of a process that is
    gone (a folder without one is not ours, or still being created, and is left alone)."""
    try:
        names = os.listdir(parent)
    except OSError:
        return
    for name in names:
        path = os.path.join(parent, name)
        if not (name.startswith((WORK_PREFIX, ".track-")) and os.path.isdir(path) and not os.path.islink(path)):
            continue
        pid = _read_pid(os.path.join(path, "pid"))
        if pid is None or _pid_alive(pid):
            continue
        shutil.rmtree(path, ignore_errors=True)
        print(f"removed {path}: the unfinished work of a run that was killed", file=sys.stderr)


def sha256_of(path: str) -> str | None:
    """The sha256 of a file, or of a folder (its files' relative names and bytes, in sorted order); None when unreadable."""
    import hashlib

    h = hashlib.sha256()
    try:
        if os.path.isdir(path):
            for d, dirs, files in sorted(os.walk(path)):
                dirs.sort()
                for f in sorted(files):
                    h.update(os.path.relpath(os.path.join(d, f), path).encode())
                    with open(os.path.join(d, f), "rb") as fh:
                        for chunk in iter(lambda: fh.read(1 << 20), b""):
                            h.update(chunk)
        else:
            with open(path, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
    except OSError:
        return None
    return h.hexdigest()


def _commit() -> str | None:
    """The git commit the package runs from (a checkout), else None."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if not os.path.isdir(os.path.join(root, ".git")):
        return None
    try:
        out = subprocess.run(["git", "-C", root, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def _machine() -> dict:
    import platform

    return {"system": platform.platform(), "python": platform.python_version(), "cpus": os.cpu_count(),
            "processor": platform.processor() or platform.machine()}


class OutputFolder:
    """A result folder written whole or not at all (module docstring).

    ``with OutputFolder(out, kind="track", overwrite=False, inputs=[("--cine", cine)]) as work:`` checks ``out`` and
    takes its lock on construction (so a refusal comes before any work), yields the working folder to write into,
    and on a clean exit moves it into place as ``out``; on an exception the working folder is removed and ``out``
    is left as it was.

    Args:
        out: the output folder.
        kind: what the folder holds (``track``, ``cine``, ``truth``); ``--overwrite`` replaces only a folder of the
            same kind.
        overwrite: replace an existing folder of this tool's of the same kind.
        inputs: (option, path) of every input of the run: none may be ``out`` or lie inside it.
        option: the option's name in messages.
        record: extra fields for the record file.
        make_parent: create ``out``'s parent folders when missing (``make-truth`` always did).
    """

    def __init__(self, out: str, *, kind: str, overwrite: bool = False, inputs: Iterable[tuple[str, str]] = (),
                 option: str = "--out", record: dict | None = None, make_parent: bool = False):
        self.given, self.kind, self.option = out, kind, option
        self.out = os.path.abspath(out)
        self.parent = os.path.dirname(self.out)
        self.record = dict(record or {})
        self.work: str | None = None
        self._lock: str | None = None
        self._replace = False
        if os.path.islink(self.out):
            raise InputError(f"{option} {out} is a symbolic link; name the folder itself ({os.path.realpath(self.out)}) "
                             "or a new one")
        if make_parent and not os.path.lexists(self.parent):
            try:  # creating folders deletes nothing
                os.makedirs(self.parent)
            except OSError as exc:
                raise InputError(f"the folder {self.parent} for {option} cannot be created ({exc.strerror}); name a folder "
                                 "you can write to") from None
        if not os.path.isdir(self.parent):
            raise InputError(f"the folder {self.parent} for {option} does not exist; create it first")
        if not os.access(self.parent, os.W_OK | os.X_OK):
            raise InputError(f"the folder {self.parent} for {option} is not writable; name a folder you can write to")
        if os.path.exists(self.out) and not os.path.isdir(self.out):
            raise InputError(f"{option} {out} is a file; name a new folder")
        check_not_an_input(self.out, option, inputs)
        if os.path.isdir(self.out):
            try:
                entries = os.listdir(self.out)
            except OSError as exc:
                raise InputError(f"{option} {out} cannot be read ({exc.strerror}); name a new folder") from None
            if entries:
                if not overwrite:
                    raise InputError(f"{option} {out} already holds files; name a new folder, or add --overwrite to "
                                     f"replace it whole (only an earlier {kind} of this tool's is replaced)")
                rec = self._read_record(self.out)
                if rec is not None and rec.get("kind") != kind:
                    raise InputError(f"{option} {out} holds a warpmpm {rec.get('kind')!r}, not a {kind}: --overwrite "
                                     f"replaces only an earlier {kind}; name a new folder")
                if not written_by_warpmpm(self.out, kind):
                    raise InputError(f"{option} {out} holds files this tool did not write (no {record_name(kind)}): --overwrite "
                                     f"replaces only an earlier {kind} of warpmpm's; name a new folder")
                self._replace = True
        self._take_lock()
        self.inputs = [(opt, path) for opt, path in inputs if path]
        self.warnings: list[str] = []
        self._t0 = time.perf_counter()
        self._showwarning = None
        #: the record written on commit (empty before)
        self.last_record: dict = {}

    @staticmethod
    def _read_record(folder: str) -> dict | None:
        """The folder's record: a kind's own record file written by this tool (``written_by`` says so), else
        :data:`RECORD`; None when there is none."""
        for name in (*sorted(set(RECORD_NAMES.values())), RECORD):
            path = os.path.join(folder, name)
            if not os.path.isfile(path) or os.path.islink(path):
                continue
            try:
                with open(path) as fh:
                    rec = json.load(fh)
            except (OSError, ValueError):
                continue
            if isinstance(rec, dict) and (name == RECORD or str(rec.get("written_by", "")).startswith("warpmpm")):
                return rec
        return None

    def _take_lock(self) -> None:
        lock = os.path.join(self.parent, f".{os.path.basename(self.out)}.lock")
        for _ in range(2):
            try:
                fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                pid = _read_pid(lock)
                if pid is not None and pid != os.getpid() and _pid_alive(pid):
                    raise InputError(f"{self.option} {self.given} is being written by another warpmpm run (process "
                                     f"{pid}, lock {lock}); wait for it to finish or name another folder") from None
                try:  # the lock of a run that was killed (or an unreadable one): taken over
                    os.remove(lock)
                except FileNotFoundError:
                    pass
                continue
            except OSError as exc:
                raise InputError(f"cannot lock {self.option} {self.given} ({lock}: {exc.strerror}); name a folder you "
                                 "can write to") from None
            with os.fdopen(fd, "w") as fh:
                fh.write(str(os.getpid()))
            self._lock = lock
            return
        raise InputError(f"{self.option} {self.given}: another run keeps taking its lock {lock}; wait for it to finish")

    def release(self) -> None:
        """Drop the lock (and a working folder not moved into place)."""
        if self.work is not None:
            shutil.rmtree(self.work, ignore_errors=True)
            self.work = None
        if self._lock is not None:
            try:
                os.remove(self._lock)
            except OSError:
                pass
            self._lock = None

    def __enter__(self) -> str:
        import warnings

        remove_dead_work_folders(self.parent)
        self._showwarning = warnings.showwarning

        def record(message, category, filename, lineno, file=None, line=None):  # kept for the record, and shown as before
            if not issubclass(category, (ResourceWarning, DeprecationWarning, PendingDeprecationWarning)):
                self.warnings.append(str(message))  # what the user was told, not the developers' notices
            if self._showwarning is getattr(warnings, "_showwarning_orig", None) and hasattr(warnings, "_showwarnmsg_impl"):
                # the standard hook: hand the warning on as `warnings` itself would (a recording catch_warnings included)
                warnings._showwarnmsg_impl(warnings.WarningMessage(message, category, filename, lineno, file, line))
            else:
                self._showwarning(message, category, filename, lineno, file, line)

        warnings.showwarning = record
        try:
            self.work = tempfile.mkdtemp(prefix=f"{WORK_PREFIX}{self.kind}-", dir=self.parent)
            with open(os.path.join(self.work, "pid"), "w") as fh:  # whose it is: a later run removes it if this one was killed
                fh.write(str(os.getpid()))
        except OSError as exc:
            self.release()
            raise InputError(f"cannot write beside {self.option} {self.given} ({exc.strerror}); name a folder you can "
                             "write to") from None
        return self.work

    def __exit__(self, exc_type, exc, tb) -> bool:
        import warnings

        try:
            if exc_type is None:
                self._commit()
        finally:
            if self._showwarning is not None:
                warnings.showwarning = self._showwarning
                self._showwarning = None
            self.release()
        return False

    def _commit(self) -> None:
        from . import __version__

        os.remove(os.path.join(self.work, "pid"))
        rec = {"kind": self.kind, "written_by": f"warpmpm {__version__}", "commit": _commit(),
               "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "wall_s": round(time.perf_counter() - self._t0, 3),
               "inputs": [{"option": opt, "path": os.path.abspath(p), "sha256": sha256_of(p)} for opt, p in self.inputs],
               "machine": _machine(), **self.record, "warnings": list(self.warnings)}
        rec = strict_json(rec)
        with open(os.path.join(self.work, record_name(self.kind)), "w") as fh:
            json.dump(rec, fh, indent=1, allow_nan=False)
        self.last_record = rec
        if os.path.lexists(self.out):
            if os.path.islink(self.out) or not os.path.isdir(self.out):
                raise InputError(f"{self.option} {self.given} appeared while this run wrote it; the result was not "
                                 "moved there: run again with a new folder")
            if os.listdir(self.out):
                if not self._replace or not written_by_warpmpm(self.out, self.kind):
                    raise InputError(f"{self.option} {self.given} was filled by someone else while this run wrote it; "
                                     "nothing was replaced: run again with a new folder")
                old = tempfile.mkdtemp(prefix=f"{WORK_PREFIX}old-", dir=self.parent)
                os.replace(self.out, os.path.join(old, "previous"))  # aside first: the old result survives a failure here
                os.replace(self.work, self.out)
                self.work = None
                shutil.rmtree(old, ignore_errors=True)
                return
            os.rmdir(self.out)
        os.replace(self.work, self.out)
        self.work = None
