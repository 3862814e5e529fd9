"""Running independent tasks (one per case x deformation) here, in a local process pool or on Dask.

The three ways behave the same: each result is handed on as it finishes, and a task that raises is
reported (one stderr line) and returned in the failure list without stopping the others.
"""

from __future__ import annotations

import os
import sys
import threading
import time

__all__ = ["init_warp_muted", "run_tasks", "report_failures"]


def init_warp_muted() -> None:
    """Initialise Warp with file descriptor 2 muted: its native library prints "CUDA driver not found" straight to it
    on a machine without a GPU, whatever the log level (a run that asks for CUDA still gets a clear error from warpmpm
    when none is there)."""
    import warp as wp

    sys.stderr.flush()
    saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def _exit_with_parent(parent_pid: int, warp_log_level: int | None = None) -> None:
    """Worker initializer: end this worker when the sweep that started it is gone (``kill -9`` of the
    parent leaves no orphan workers simulating for nobody); and Warp as quiet as in the parent (no module-load lines
    from every worker when the command line asked for none)."""
    if warp_log_level is not None:
        import warp as wp

        wp.config.log_level = warp_log_level
        if warp_log_level >= wp.LOG_ERROR:  # no "CUDA driver not found" line per worker
            init_warp_muted()

    def watch():
        while True:
            if os.getppid() != parent_pid:
                os._exit(1)
            time.sleep(1.0)

    threading.Thread(target=watch, daemon=True).start()


def run_tasks(fn, args: list[tuple], on_result, *, workers: int = 1, scheduler: str | None = None) -> list[tuple]:
    """Call ``fn(*a)`` for every ``a`` in ``args`` and hand each result to ``on_result`` as it finishes.

    ``scheduler=None``: here (``workers <= 1``) or in a local process pool of ``workers`` (spawned,
    so each process initialises Warp itself); ``"local"``: a Dask ``LocalCluster`` of ``workers``
    single-threaded processes; any other value: the address of a running Dask scheduler. A task that
    raises does not stop the others: it is reported on stderr and returned as ``(args, message)``.
    ``KeyboardInterrupt`` is never swallowed.
    """
    failed: list[tuple] = []

    def fail(a, exc):
        msg = f"{type(exc).__name__}: {exc}"
        print(f"task {a[:2]} failed: {msg}", file=sys.stderr)
        failed.append((a, msg))

    def take(a, get) -> None:
        """Hand on the result of task ``a`` (``get()`` returns it or raises its error)."""
        try:
            result = get()
        except Exception as exc:  # noqa: BLE001 - one task's error must not lose the other tasks' rows
            fail(a, exc)
            return
        on_result(result)

    if scheduler is None and workers <= 1:
        for a in args:
            take(a, lambda: fn(*a))
        return failed
    # worker processes split their steps over the cores left to each (processes x threads <= cores): a process is
    # spawned with this environment, so the variable reaches Warp's step in every worker
    from ..solvers.parallel import THREADS_VARIABLE, cpu_cores

    old = os.environ.get(THREADS_VARIABLE)
    if old is None:
        os.environ[THREADS_VARIABLE] = str(max(1, cpu_cores() // max(1, workers)))
    try:
        _run_elsewhere(fn, args, take, workers, scheduler)
    finally:
        if old is None:
            os.environ.pop(THREADS_VARIABLE, None)
    return failed


def _run_elsewhere(fn, args, take, workers, scheduler) -> None:
    """:func:`run_tasks` in a local process pool (``scheduler`` None) or on Dask."""
    if scheduler is None:
        import concurrent.futures as cf
        import multiprocessing as mp

        level = None
        if "warp" in sys.modules:
            level = sys.modules["warp"].config.log_level
        with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_exit_with_parent,
                                    initargs=(os.getpid(), level)) as ex:
            futures = {ex.submit(fn, *a): a for a in args}
            try:
                for fut in cf.as_completed(futures):
                    take(futures[fut], fut.result)
            except BaseException:
                for fut in futures:
                    fut.cancel()
                for proc in list(getattr(ex, "_processes", {}).values()):  # do not leave workers running
                    proc.terminate()
                raise
    else:
        from ..errors import optional

        distributed = optional("distributed", "a Dask scheduler (--scheduler)")
        Client, LocalCluster, as_completed = distributed.Client, distributed.LocalCluster, distributed.as_completed

        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) if scheduler == "local" else None
        client = Client(cluster if cluster is not None else scheduler)
        try:
            futures = {client.submit(fn, *a, pure=False): a for a in args}
            for fut in as_completed(list(futures)):
                take(futures[fut], fut.result)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()


def report_failures(failed: list[tuple], n_tasks: int, second: str = "deformation") -> None:
    """One stderr line naming the tasks that failed (their case and ``second`` argument: the deformation of a sweep, the
    truth seed of a plane sweep) and why."""
    if failed:
        print(f"{len(failed)} of {n_tasks} tasks failed (re-run to retry them): "
              + "; ".join(f"{a[0].get('name', 'case')} {second} {a[1]}: {m}" for a, m in failed), file=sys.stderr)
