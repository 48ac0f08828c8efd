"""The feature worker (each job done once, by the worker or by the thread that needs it first) and the grey copy a
keyframe keeps to extract its features again."""

import threading
import time

import numpy as np
import pytest

from cae_lcd.core.errors import DatabaseError
from retrieval.feature_jobs import FeatureJobs, grey_copy, read_grey_copy
from verify.features import SIFT


def same(a, b):
    return np.array_equal(a.keypoints, b.keypoints) and np.array_equal(a.descriptors, b.descriptors)


@pytest.fixture()
def jobs():
    j = FeatureJobs(SIFT, keep=4)
    yield j
    j.close()


class TestFeatureJobs:
    def test_a_job_gives_the_features_the_caller_would_extract(self, jobs, sample_image):
        sift = SIFT()
        for i in (0, 50):
            jobs.submit(i, lambda ex, i=i: ex.extract(sample_image(i)), urgent=bool(i))
        assert 0 in jobs and 50 in jobs
        for i in (50, 0):
            assert same(jobs.take(i, sift), sift.extract(sample_image(i)))
        assert 0 not in jobs and jobs.take(0, sift) is None  # taken once; no job: None

    def test_the_caller_runs_a_job_the_worker_has_not_started(self, sample_image):
        gate = threading.Event()
        ran_on = {}
        jobs = FeatureJobs(SIFT)
        try:
            jobs.submit(1, lambda ex: gate.wait(10) and ex.extract(sample_image(1)))  # keeps the worker busy
            jobs.submit(2, lambda ex: ran_on.setdefault(2, threading.current_thread().name) and ex.extract(
                sample_image(2)))
            feats = jobs.take(2, SIFT())  # queued behind job 1: run here at once, not waited for
            assert ran_on[2] == threading.current_thread().name and len(feats) > 0
            gate.set()
            assert len(jobs.take(1, SIFT())) > 0
        finally:
            gate.set()
            jobs.close()

    def test_an_error_reaches_the_thread_that_takes_the_result(self, jobs):
        jobs.submit(3, lambda ex: ex.extract("not an image"))
        with pytest.raises(Exception):
            jobs.take(3, SIFT())
        assert 3 not in jobs

    def test_results_nobody_takes_are_bounded(self, jobs, sample_image):
        for i in range(10):
            jobs.submit(i, lambda ex: ex.extract(sample_image(0)[:40, :40]))
        deadline = time.monotonic() + 30
        while not all(t.done.is_set() for t in list(jobs._tasks.values())) and time.monotonic() < deadline:
            time.sleep(0.01)  # the worker runs them all
        jobs.submit(10, lambda ex: ex.extract(sample_image(0)[:40, :40]))
        assert sum(i in jobs for i in range(11)) <= jobs.keep + 1

    def test_after_close_take_still_runs_a_queued_job(self, sample_image):
        jobs = FeatureJobs(SIFT)
        jobs.close()
        jobs.submit(5, lambda ex: ex.extract(sample_image(5)))  # refused after close: no job
        assert jobs.take(5, SIFT()) is None


class TestGreyCopy:
    def test_lossless_copy_gives_the_same_features(self, sample_image):
        sift = SIFT()
        small, scale = sift.prepare(sample_image(7))
        back, s = read_grey_copy(grey_copy(small, scale))
        assert np.array_equal(back, small) and s == scale
        assert same(sift.extract_prepared(back, s), sift.extract(sample_image(7)))

    def test_jpeg_copy_is_small_and_close(self, sample_image):
        small, scale = SIFT().prepare(sample_image(7))
        copy = grey_copy(small, scale, 90)
        back, s = read_grey_copy(copy)
        assert len(copy) < len(grey_copy(small, scale)) and s == scale and back.shape == small.shape
        assert np.abs(back.astype(int) - small).mean() < 3

    @pytest.mark.parametrize("data", [b"", b"12345678", b"\0" * 8 + b"not an image"])
    def test_damaged_copy_is_one_line_error(self, data):
        with pytest.raises(DatabaseError, match="cannot be decoded"):
            read_grey_copy(data)
