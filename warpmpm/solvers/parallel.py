"""Several CPU cores for one simulation.

Warp's CPU backend runs each kernel launch on one core, so a frame on a two-core machine left half of it
idle. A launch is a call into the compiled module through ``ctypes``, which releases Python's global
interpreter lock while the kernel runs: launches of the same kernel over disjoint ranges of particles,
made from several threads, run at the same time. :class:`MPMSolver <warpmpm.solvers.explicit.MPMSolver>` splits its
particle kernels that way (P2G into a copy of the grid per thread, summed by the grid update; G2P; the
grid update over slabs of nodes); the launches that depend on a whole pass (the grid update after P2G,
G2P after the grid update) wait for every thread. :class:`QuasiStaticSolver <warpmpm.solvers.quasistatic.QuasiStaticSolver>`
splits its particle kernels the same way (the Newton iteration's forces and the conjugate gradient's product, each
thread into its own copy of the node arrays, added by the next kernel; the particle moves).

Nothing here runs on CUDA, where one launch already fills the device, nor while a graph is being
captured (the captured launch list must be the whole-array one).

How many threads: :attr:`SolverConfig.cpu_threads <warpmpm.solvers.config.SolverConfig.cpu_threads>`, else the
environment variable ``WARPMPM_CPU_THREADS``, else the cores this process may use, at most 2 (the most
measured). Work spread over several processes (``warpmpm sweep --workers N``) sets the variable for its
workers so that processes times threads does not exceed the cores.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import warp as wp

__all__ = ["cpu_cores", "THREADS_VARIABLE", "default_threads", "split", "run_together", "ChunkViews"]

_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_POOL_LOCK = threading.Lock()


def cpu_cores() -> int:
    """Cores this process may run on (its affinity mask where the platform tells it, else ``os.cpu_count``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


#: environment variable naming the default number of threads of a split CPU step
THREADS_VARIABLE = "WARPMPM_CPU_THREADS"


def default_threads() -> int:
    """Threads of a split CPU step when the solver's configuration names none: ``WARPMPM_CPU_THREADS`` when set
    (an integer >= 1), else the process's cores, at most 2."""
    value = os.environ.get(THREADS_VARIABLE)
    if value is not None and value.strip():
        try:
            n = int(value)
        except ValueError:
            n = 0
        if not 1 <= n <= 64:
            from ..errors import InputError

            raise InputError(f"{THREADS_VARIABLE}={value!r}: it must be an integer from 1 to 64 (threads of a CPU step)")
        return n
    return min(2, cpu_cores())


def split(n: int, parts: int) -> list[tuple[int, int]]:
    """``parts`` contiguous ranges ``[lo, hi)`` covering ``0..n``, sizes differing by at most one; empty ranges
    are left out (fewer items than parts)."""
    parts = max(1, min(int(parts), int(n))) if n > 0 else 1
    q, r = divmod(int(n), parts)
    out, lo = [], 0
    for k in range(parts):
        hi = lo + q + (1 if k < r else 0)
        if hi > lo:
            out.append((lo, hi))
        lo = hi
    return out or [(0, 0)]


def _pool(workers: int) -> ThreadPoolExecutor:
    """The process's worker threads (one pool, grown when a solver needs more)."""
    global _POOL, _POOL_SIZE
    with _POOL_LOCK:
        if _POOL is None or _POOL_SIZE < workers:
            old = _POOL
            _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="warpmpm-cpu")
            _POOL_SIZE = workers
            if old is not None:
                old.shutdown(wait=False)
        return _POOL


def run_together(tasks) -> None:
    """Run the callables ``tasks`` at once: the first on this thread, the others on worker threads; returns when
    all have finished and re-raises the first exception any of them raised."""
    tasks = list(tasks)
    if len(tasks) == 1:
        tasks[0]()
        return
    futures = [_pool(len(tasks) - 1).submit(t) for t in tasks[1:]]
    first = None
    try:
        tasks[0]()
    except BaseException as exc:  # noqa: BLE001 - wait for the others before raising
        first = exc
    for f in futures:
        try:
            f.result()
        except BaseException as exc:  # noqa: BLE001
            first = first or exc
    if first is not None:
        raise first


class ChunkViews:
    """Views of 1D Warp arrays over fixed particle ranges, made once per array and kept (making a view costs
    ~10 us of Python; a step asks for ~20). The cache holds the arrays it has seen, so an ``id`` is never
    reused while its entry lives; it is emptied when it grows past ``limit`` arrays (a caller passing a new
    array every step)."""

    def __init__(self, ranges: list[tuple[int, int]], limit: int = 64):
        self.ranges = ranges
        self.limit = limit
        self._cache: dict[int, tuple[wp.array, list[wp.array]]] = {}

    def __call__(self, arr: wp.array) -> list[wp.array]:
        hit = self._cache.get(id(arr))
        if hit is not None and hit[0] is arr:
            return hit[1]
        if len(self._cache) >= self.limit:
            self._cache.clear()
        views = [arr[lo:hi] for lo, hi in self.ranges]
        self._cache[id(arr)] = (arr, views)
        return views
