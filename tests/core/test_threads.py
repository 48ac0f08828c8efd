"""One thread policy for torch, OpenCV, faiss and numpy's BLAS (``core.threads``)."""

import cv2
import faiss
import numpy as np  # noqa: F401 - loads the BLAS that threadpoolctl reports
import pytest
import torch
from threadpoolctl import threadpool_info, threadpool_limits

from core.threads import apply_thread_policy, cpu_count


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
