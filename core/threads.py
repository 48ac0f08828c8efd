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
import platform
import sys

import cv2
import torch
from threadpoolctl import threadpool_limits

__all__ = ["apply_thread_policy", "cpu_count", "reexec_with_capped_arenas", "MALLOC_ARENAS"]

log = logging.getLogger(__name__)

MALLOC_ARENAS = 2  #: glibc malloc arenas a long-running server keeps (``reexec_with_capped_arenas``)


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


def reexec_with_capped_arenas(arenas: int = MALLOC_ARENAS) -> None:
    """Restarts this process (same pid, same command line) with ``MALLOC_ARENA_MAX=arenas`` in its environment, for a
    long-running server: each of its threads (uvicorn's, the optimiser's, robots processed in parallel) otherwise
    grows a glibc malloc arena of its own, and its RSS keeps growing with the keyframes streamed although nothing is
    kept. ``mallopt(M_ARENA_MAX)`` at run time cannot undo the arenas the imports already made, hence the restart
    (both measured with ``python -m bench.fleet_memory``: BENCHMARKS.md, issue 19). Returns at once where the
    environment already says (a user's own ``MALLOC_ARENA_MAX`` wins) or elsewhere than glibc; call it in a command's
    entry point once its arguments are checked, before anything is started or written.
    """
    if os.environ.get("MALLOC_ARENA_MAX") or platform.libc_ver()[0] != "glibc":
        return
    os.environ["MALLOC_ARENA_MAX"] = str(int(arenas))
    os.execv(sys.executable, [sys.executable, *sys.orig_argv[1:]])

