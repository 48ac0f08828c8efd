"""One thread policy for every numeric library in the process: torch, OpenCV, faiss and numpy's BLAS together.

Each library keeps its own pool (torch's OpenMP team, OpenCV's, faiss's OpenMP), and a pool of N threads that
waits at a barrier after each operation stalls as soon as one of its threads is descheduled: beside a busy
neighbour process (a SLAM system's tracking and mapping threads) a 2-thread encoder went from 7 to 44 ms, and two
pools side by side oversubscribe the cores. The policy is therefore: **each library single-threaded by default**
(``threads=1``), and the cores used by the pipeline's own workers instead (``retrieval.detect`` reads, decodes and
encodes ahead in a worker thread while the main thread decides), which a busy neighbour slows in proportion but
cannot stall. numpy's BLAS (OpenBLAS) follows the same number through ``threadpoolctl``: besides the stalls, a
BLAS that splits a product over another number of threads sums in another order, and a run would then differ in
the last digits from the same run in a worker process that has one thread (``cae-lcd detect`` over many sequences
on Ray).

    >>> from cae_lcd.core.threads import apply_thread_policy
    >>> apply_thread_policy(1)
    1
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import platform
import sys
import threading
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from typing import Any, Callable

import cv2
import torch
from threadpoolctl import threadpool_limits

__all__ = ["apply_thread_policy", "cpu_count", "reexec_with_server_malloc", "release_free_memory", "BesideCaller",
           "BesideExecutor", "in_turn", "side_by_side", "MALLOC_ARENAS", "MMAP_THRESHOLD"]

log = logging.getLogger(__name__)

MALLOC_ARENAS = 2  #: glibc malloc arenas a long-running server keeps (``reexec_with_server_malloc``)
MMAP_THRESHOLD = 128 * 1024  #: bytes from which a server's malloc maps each block on its own (glibc's initial value)


def cpu_count() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def apply_thread_policy(threads: int | None = 1) -> int:
    """Sets the intra-op threads of torch, OpenCV, faiss and numpy's BLAS to the same number (process-wide).

    Args:
        threads: threads each library may use; None = every core this process may run on.

    Returns:
        The number applied.
    """
    n = cpu_count() if threads is None else max(1, int(threads))
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    cv2.setNumThreads(n)
    try:
        import faiss  # optional here: the base layer does not need it
    except ImportError:  # pragma: no cover - faiss is a dependency of retrieval
        pass
    else:
        faiss.omp_set_num_threads(n)
    threadpool_limits(n, user_api="blas")  # numpy's OpenBLAS (and any other BLAS loaded), from now on
    log.debug("thread policy: %d thread(s) for torch, OpenCV, faiss and BLAS", n)
    return n


def reexec_with_server_malloc(arenas: int = MALLOC_ARENAS, mmap_threshold: int = MMAP_THRESHOLD) -> None:
    """Restarts this process (same pid, same command line) with glibc's malloc set for a long-running server:
    ``MALLOC_ARENA_MAX=arenas`` and ``MALLOC_MMAP_THRESHOLD_=mmap_threshold`` in its environment.

    - Arenas: each of a server's threads (uvicorn's, the optimiser's, robots processed in parallel) otherwise grows
      an arena of its own, and RSS keeps growing with the keyframes streamed although nothing is kept.
    - A fixed mmap threshold: by default glibc raises the threshold to the size of each large block freed (up to
      32 MiB), so that blocks which grow with the map (a column, an index's storage, a similarity row) come from the
      heap once the first of them is freed; each larger one then leaves the smaller one's hole behind it, and the
      heap holds hundreds of MiB it cannot give back (one robot, 200 keyframes: 404 MiB free inside a 550 MiB heap,
      2 MiB with the threshold fixed at 128 KiB). Fixed, every block of at least ``mmap_threshold`` bytes is mapped
      on its own and returned to the system when freed.

    ``mallopt`` at run time cannot undo the arenas the imports already made, hence the restart (both measured with
    ``python -m bench.fleet_memory``: BENCHMARKS.md, issue 19). Returns at once where the environment already sets
    both (a user's own values win) or elsewhere than glibc; call it in a command's entry point once its arguments
    are checked, before anything is started or written.
    """
    wanted = {"MALLOC_ARENA_MAX": str(int(arenas)), "MALLOC_MMAP_THRESHOLD_": str(int(mmap_threshold))}
    missing = {k: v for k, v in wanted.items() if not os.environ.get(k)}
    if not missing or platform.libc_ver()[0] != "glibc":
        return
    os.environ.update(missing)
    os.execv(sys.executable, [sys.executable, *sys.orig_argv[1:]])


@functools.lru_cache(maxsize=1)
def _malloc_trim() -> Any:
    """glibc's ``malloc_trim`` (None elsewhere)."""
    if platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


def release_free_memory() -> bool:
    """Gives the pages of freed heap memory back to the system (glibc ``malloc_trim(0)``: every arena, holes in
    the middle included, not only the top). A server calls it after work that allocates and frees much (a pose
    graph solved on a copy of the graph): the freed pages otherwise stay resident until malloc reuses them.

    Returns:
        True where memory was released, False where nothing was (or elsewhere than glibc).
    """
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False


@functools.lru_cache(maxsize=1)
def _sched_getcpu() -> Any:
    """glibc's ``sched_getcpu`` (None elsewhere, or where threads cannot be given an affinity)."""
    if platform.libc_ver()[0] != "glibc" or not hasattr(os, "sched_setaffinity"):
        return None
    try:
        return ctypes.CDLL("libc.so.6").sched_getcpu
    except (OSError, AttributeError):
        return None


class BesideCaller:
    """Keeps one worker thread off the core of the thread that hands it work, so that the two run side by side.

    Woken after an idle spell (a frame at the camera rate: the cores idle ~80 ms between frames), Linux often wakes
    the worker on the core of the thread that woke it, and the two share that core until the load balancer moves
    one: on the 2-core machine a frame's encoding beside its SIFT extraction took 9.6 ms instead of 5.4, the
    extraction 13.5 instead of 10.2 (back to back, with both cores already busy, 5.5 and 10.2). ``steer``, called by
    the caller before it wakes the worker, sets the worker's affinity to its own allowed cores less the caller's
    current one (one ``sched_getcpu``, and a ``sched_setaffinity`` when the caller's core changed): 5.8 and 10.5
    at the camera rate, back to back unchanged (BENCHMARKS.md, issue 18). Nothing where the worker may use one core
    only, elsewhere than Linux, or before ``attach``.
    """

    def __init__(self) -> None:
        self._tid: int | None = None
        self._cores: frozenset[int] = frozenset()
        self._avoided: int | None = None  # the core the worker was last kept off

    def attach(self) -> None:
        """Called once in the worker thread (its id and its allowed cores)."""
        if _sched_getcpu() is not None:
            self._cores = frozenset(os.sched_getaffinity(0))
            self._tid = threading.get_native_id()

    def steer(self) -> None:
        """Called by the caller before it hands the worker work: the worker may run on any allowed core but this
        thread's current one."""
        if self._tid is None or len(self._cores) < 2:
            return
        core = int(_sched_getcpu()())
        if core == self._avoided or core not in self._cores:
            return
        try:
            os.sched_setaffinity(self._tid, self._cores - {core})
        except OSError as err:  # the worker is gone, or the system refuses: left where the scheduler puts it
            log.debug("worker affinity not set: %s", err)
            self._tid = None
            return
        self._avoided = core


class BesideExecutor(ThreadPoolExecutor):
    """A one-thread executor whose thread runs beside the caller's, off its core (``BesideCaller``)."""

    def __init__(self, thread_name_prefix: str = "") -> None:
        self.steering = BesideCaller()
        super().__init__(1, thread_name_prefix=thread_name_prefix, initializer=self.steering.attach)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:  # type: ignore[override]
        self.steering.steer()
        return super().submit(fn, *args, **kwargs)


def in_turn(lane: Callable[[], None], pool: Executor | None, n: int) -> None:
    """Runs ``lane`` (a loop that takes the next of ``n`` items until none is left) on this thread and, when ``pool``
    is given and there is more than one item, on ``pool``'s thread too; returns when both are done (an error of
    either is raised here)."""
    helper = pool.submit(lane) if pool is not None and n > 1 else None
    try:
        lane()
    finally:
        if helper is not None:
            helper.result()


def side_by_side(work: Callable[[Any], Any], items: list[Any], pool: Executor | None) -> list[Any]:
    """``[work(item) for item in items]``, the items taken in turn by this thread and ``pool``'s (when given)."""
    out: list[Any] = [None] * len(items)
    state, lock = {"next": 0}, threading.Lock()

    def lane() -> None:
        while True:
            with lock:
                k = state["next"]
                state["next"] = k + 1
            if k >= len(items):
                return
            out[k] = work(items[k])

    in_turn(lane, pool, len(items))
    return out
