"""cae_lcd.core.cluster: a local Ray of our own (a small object store, no dashboard), tried again when its start fails for a
reason of the moment, and reported in one line when it keeps failing."""

from __future__ import annotations

import logging

import pytest

from cae_lcd.core import cluster
from cae_lcd.core.errors import ConfigError

ray = pytest.importorskip("ray")


@pytest.fixture
def no_sleep(monkeypatch):
    monkeypatch.setattr(cluster.time, "sleep", lambda _: None)


def test_a_local_ray_is_our_own():
    options = cluster.local_ray_options(2)
    assert options["address"] == "local" and options["num_cpus"] == 2 and options["include_dashboard"] is False
    assert options["object_store_memory"] == cluster.OBJECT_STORE_BYTES


def test_a_failed_start_is_tried_again(monkeypatch, no_sleep, caplog):
    """The first start fails (as a start-up timeout would), the next starts a real local Ray (on a loaded machine a
    real start may fail too: it is then tried again like any other)."""
    real_init, calls = ray.init, []

    def flaky_init(**options):
        calls.append(options)
        if len(calls) == 1:
            raise TimeoutError("the raylet did not register in time")
        return real_init(**options)

    monkeypatch.setattr(ray, "init", flaky_init)
    assert not ray.is_initialized()
    with caplog.at_level(logging.WARNING, logger="cae_lcd.core.cluster"):
        module, started = cluster.start_ray(cpus=1)
    try:
        assert module is ray and started and ray.is_initialized()
        assert 2 <= len(calls) <= cluster.START_ATTEMPTS and all(c == cluster.local_ray_options(1) for c in calls)
        assert sum("did not start" in r.getMessage() for r in caplog.records) == len(calls) - 1
        assert cluster.start_ray(cpus=1) == (ray, False)  # a running Ray is used, not started again
    finally:
        ray.shutdown()


def test_a_start_that_keeps_failing_is_one_line(monkeypatch, no_sleep):
    def broken_init(**options):
        raise ValueError("Ray component worker_ports is trying to use a port number\nthat is used by others")

    monkeypatch.setattr(ray, "init", broken_init)
    with pytest.raises(ConfigError, match=rf"local Ray could not be started \({cluster.START_ATTEMPTS} tries\): "
                                          r"Ray component .* used by others$") as err:
        cluster.start_ray(cpus=1)
    assert "\n" not in str(err.value)
    assert not ray.is_initialized()


def test_an_address_is_tried_once(monkeypatch, no_sleep):
    calls = []

    def unreachable(**options):
        calls.append(options)
        raise ConnectionError("could not connect to 10.0.0.1:6379")

    monkeypatch.setattr(ray, "init", unreachable)
    with pytest.raises(ConfigError, match=r"the Ray cluster at '10.0.0.1:6379' could not be joined"):
        cluster.start_ray("10.0.0.1:6379")
    assert len(calls) == 1 and calls[0]["address"] == "10.0.0.1:6379"
