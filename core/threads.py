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

    >>> from core.threads import apply_thread_policy
    >>> apply_thread_policy(1)
    1
"""

from __future__ import annotations

import logging
import os

import cv2
import torch
from threadpoolctl import threadpool_limits

__all__ = ["apply_thread_policy", "cpu_count", "limit_malloc_arenas", "MALLOC_ARENAS"]

log = logging.getLogger(__name__)

MALLOC_ARENAS = 2  #: glibc malloc arenas a long-running server keeps (``limit_malloc_arenas``)
_M_ARENA_MAX = -8  # glibc's mallopt parameter number for M_ARENA_MAX (malloc.h)


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


def limit_malloc_arenas(arenas: int = MALLOC_ARENAS) -> bool:
    """Caps glibc's malloc arenas for this process (``mallopt(M_ARENA_MAX, arenas)``), as ``MALLOC_ARENA_MAX`` in the
    environment would, for a long-running server whose threads (uvicorn's, the optimiser's, robots processed in
    parallel) otherwise each grow an arena of their own: the fleet server's RSS then keeps growing with the keyframes
    streamed although nothing is kept (BENCHMARKS.md, issue 19: 1.35x from 200 to 500 keyframes, flat with 2 arenas).
    Call it before the threads start. A ``MALLOC_ARENA_MAX`` already in the environment wins; elsewhere than glibc
    (macOS, musl) it does nothing.

    Returns:
        True where the cap was set.
    """
    if os.environ.get("MALLOC_ARENA_MAX"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        done = bool(libc.mallopt(_M_ARENA_MAX, int(arenas)))
    except (OSError, AttributeError):
        return False
    log.debug("malloc arenas capped at %d: %s", arenas, done)
    return done
