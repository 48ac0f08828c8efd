"""One thread policy for torch, OpenCV, faiss and numpy's BLAS (``core.threads``)."""

import os
import platform
import subprocess
import sys
from pathlib import Path

import cv2
import faiss
import numpy as np  # noqa: F401 - loads the BLAS that threadpoolctl reports
import pytest
import torch
from threadpoolctl import threadpool_info, threadpool_limits

from core.threads import apply_thread_policy, cpu_count

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
    from core.threads import reexec_with_capped_arenas
    reexec_with_capped_arenas(1)  # runs this script again with MALLOC_ARENA_MAX=1
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


@pytest.mark.skipif(sys.platform != "linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
class TestMallocArenas:
    def _heaps(self, mode: str) -> int:
        env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
        out = subprocess.run([sys.executable, "-c", _ARENAS_SCRIPT, mode], env=env, cwd=REPO, check=True,
                             capture_output=True, text=True).stdout
        return int(out.split()[-1])

    def test_threads_share_the_capped_arenas(self):
        assert self._heaps("no") > 1  # without the cap, threads grow arenas of their own
        assert self._heaps("cap") == 1

    def test_the_environment_wins(self, monkeypatch):
        from core.threads import reexec_with_capped_arenas

        monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
        assert reexec_with_capped_arenas() is None  # returned: no restart (the test process would be replaced)
