"""One thread policy for torch, OpenCV, faiss and numpy's BLAS (``cae_lcd.core.threads``)."""

import ctypes
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import faiss
import numpy as np  # noqa: F401 - loads the BLAS that threadpoolctl reports
import pytest
import torch
from threadpoolctl import threadpool_info, threadpool_limits

from cae_lcd.core.threads import BesideExecutor, apply_thread_policy, cpu_count, side_by_side

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads(), cv2.getNumThreads(), faiss.omp_get_max_threads()
    blas = threadpool_limits(None, user_api="blas")  # restores the BLAS threads on exit
    yield
    blas.restore_original_limits()
    torch.set_num_threads(before[0])
    cv2.setNumThreads(before[1])
    faiss.omp_set_num_threads(before[2])


def test_one_number_for_every_library(restore_threads):
    assert apply_thread_policy(1) == 1
    assert (torch.get_num_threads(), cv2.getNumThreads(), faiss.omp_get_max_threads()) == (1, 1, 1)
    assert {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"} == {1}
    n = apply_thread_policy(None)  # all the cores this process may use
    assert n == cpu_count() >= 1
    assert (torch.get_num_threads(), cv2.getNumThreads(), faiss.omp_get_max_threads()) == (n, n, n)


def test_detector_applies_its_runtime_threads(restore_threads, encoder):
    from retrieval.detector import LoopDetector

    apply_thread_policy(None)
    with LoopDetector(encoder=encoder):  # default: runtime.threads 1
        assert (torch.get_num_threads(), cv2.getNumThreads(), faiss.omp_get_max_threads()) == (1, 1, 1)


_ARENAS_SCRIPT = """
import ctypes, sys, tempfile, threading
if sys.argv[1] == "cap":
    from cae_lcd.core.threads import reexec_with_server_malloc
    reexec_with_server_malloc(1)  # runs this script again with MALLOC_ARENA_MAX=1 (and the mmap threshold fixed)
keep, together = [], threading.Barrier(4)
def work():  # four threads alive at once, each allocating: glibc gives each its own arena unless capped
    keep.append([bytearray(1000) for _ in range(100)])
    together.wait()
threads = [threading.Thread(target=work) for _ in range(4)]
[t.start() for t in threads]
[t.join() for t in threads]
libc = ctypes.CDLL("libc.so.6")
libc.fopen.restype = ctypes.c_void_p
path = tempfile.mktemp()
fp = ctypes.c_void_p(libc.fopen(path.encode(), b"w"))
libc.malloc_info(0, fp)
libc.fclose(fp)
print(open(path).read().count("<heap nr="))
"""


_THRESHOLD_SCRIPT = """
import ctypes, sys
if sys.argv[1] == "cap":
    from cae_lcd.core.threads import reexec_with_server_malloc
    reexec_with_server_malloc()
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = Info
libc.malloc.restype = ctypes.c_void_p
libc.free(ctypes.c_void_p(libc.malloc(4 << 20)))
before = libc.mallinfo2().hblkhd
block = libc.malloc(1 << 20)
print(int(libc.mallinfo2().hblkhd - before >= 1 << 20))  # 1: the 1 MiB block was mapped on its own
"""


@pytest.mark.skipif(sys.platform != "linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
class TestServerMalloc:
    def _run(self, script: str, mode: str) -> int:
        env = {k: v for k, v in os.environ.items() if k not in ("MALLOC_ARENA_MAX", "MALLOC_MMAP_THRESHOLD_")}
        out = subprocess.run([sys.executable, "-c", script, mode], env=env, cwd=REPO, check=True,
                             capture_output=True, text=True).stdout
        return int(out.split()[-1])

    def _heaps(self, mode: str) -> int:
        return self._run(_ARENAS_SCRIPT, mode)

    def test_a_freed_large_block_does_not_move_the_threshold(self):
        # glibc's default: freeing a 4 MiB mapped block raises the threshold, and the next 1 MiB block comes from
        # the heap (where blocks that grow with the map leave holes); with the server's malloc it is mapped
        assert self._run(_THRESHOLD_SCRIPT, "no") == 0
        assert self._run(_THRESHOLD_SCRIPT, "cap") == 1

    def test_threads_share_the_capped_arenas(self):
        assert self._heaps("no") > 1  # without the cap, threads grow arenas of their own
        assert self._heaps("cap") == 1

    def test_the_environment_wins(self, monkeypatch):
        from cae_lcd.core.threads import reexec_with_server_malloc

        monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
        monkeypatch.setenv("MALLOC_MMAP_THRESHOLD_", "65536")
        assert reexec_with_server_malloc() is None  # returned: no restart (the test process would be replaced)


_TRIM_SCRIPT = """
import ctypes, sys
from cae_lcd.core.threads import release_free_memory
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096
blocks = [libc.malloc(4000) for _ in range(50_000)]  # 200 MB of small blocks on the heap
for b in blocks:
    ctypes.memset(b, 1, 4000)
keep = libc.malloc(4000)  # a live block above them: the heap's top cannot shrink
for b in blocks:
    libc.free(ctypes.c_void_p(b))
before = rss()
released = release_free_memory() if sys.argv[1] == "trim" else False
print(int(released), (before - rss()) // 2**20)
"""


@pytest.mark.skipif(sys.platform != "linux" or platform.libc_ver()[0] != "glibc", reason="glibc's malloc_trim")
def test_release_free_memory_returns_freed_pages():
    def run(mode: str) -> tuple[int, int]:
        out = subprocess.run([sys.executable, "-c", _TRIM_SCRIPT, mode], cwd=REPO, check=True, capture_output=True,
                             text=True).stdout.split()
        return int(out[-2]), int(out[-1])

    released, mib = run("no")  # freed, yet resident: the hole below a live block stays (within a page or so of
    assert released == 0 and abs(mib) < 16  # the interpreter's own: it read -1 MiB once, rounded down)
    released, mib = run("trim")
    assert released == 1 and mib > 150


linux_two_cores = pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or platform.libc_ver()[0] != "glibc"
                                     or len(os.sched_getaffinity(0)) < 2, reason="thread affinity: Linux, >= 2 cores")


@linux_two_cores
def test_beside_executor_keeps_its_thread_off_the_callers_core():
    mine = os.sched_getaffinity(0)
    try:
        with BesideExecutor("t") as ex:
            tid = ex.submit(threading.get_native_id).result()  # started while the caller may use every core
            for core in sorted(mine)[:2]:  # the caller on one core, then on another: the worker moves off each
                os.sched_setaffinity(0, {core})
                ex.submit(lambda: None).result()
                assert os.sched_getaffinity(tid) == mine - {core}
    finally:
        os.sched_setaffinity(0, mine)


@linux_two_cores
def test_feature_jobs_worker_kept_off_the_submitting_core():
    from retrieval.feature_jobs import FeatureJobs
    from verify.features import create_extractor

    mine = os.sched_getaffinity(0)
    core = sorted(mine)[0]
    jobs = FeatureJobs(lambda: create_extractor({"name": "sift"}))
    try:
        os.sched_setaffinity(0, {core})
        tids: list[int] = []
        jobs.submit(0, lambda ex: tids.append(threading.get_native_id()))
        deadline = time.monotonic() + 10
        while not tids and time.monotonic() < deadline:
            time.sleep(0.01)
        jobs.submit(1, lambda ex: None)  # steered now that the worker has started
        assert tids and os.sched_getaffinity(tids[0]) == mine - {core}
    finally:
        os.sched_setaffinity(0, mine)
        jobs.close()


def test_beside_executor_runs_jobs_where_it_cannot_steer(monkeypatch):
    monkeypatch.setattr("cae_lcd.core.threads._sched_getcpu", lambda: None)
    with BesideExecutor("t") as ex:
        assert ex.submit(sum, [1, 2]).result() == 3 and ex.steering._tid is None



def test_side_by_side_runs_every_item_once_on_both_threads_and_raises_their_errors():
    """``side_by_side`` (over ``in_turn``): every item's result in order, the caller and the pool's thread both
    taking items when there are several; an item's error reaches the caller."""
    def slow(k: int) -> tuple[int, int]:
        time.sleep(0.002)
        return k * k, threading.get_ident()

    with BesideExecutor("test") as pool:
        out = side_by_side(slow, list(range(40)), pool)
        assert [v for v, _ in out] == [k * k for k in range(40)] and len({t for _, t in out}) == 2
        assert side_by_side(slow, [], pool) == [] and [v for v, _ in side_by_side(slow, [3], None)] == [9]
        with pytest.raises(ZeroDivisionError):
            side_by_side(lambda k: 1 // k, [1, 0, 2], pool)
