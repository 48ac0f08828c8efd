"""One way to start or join Ray, for every part that uses it (``retrieval.batch``: many sequences; ``cae_lcd.fleet.workers``:
robots sharded over workers) and for their tests.

A local Ray is always a new one of our own (``address="local"``: never another program's cluster found on this
machine), without the dashboard, with a small object store (tasks and actors pass paths, codes and summaries, never
images in bulk): Ray's default sizes the store from free memory and ``/dev/shm``, which differ from machine to
machine. Ray itself resolves a loopback node address to the machine's own (its ports then listen there) and
requires its cluster token on them (Ray's token authentication, on by default for a new local Ray since 2.5x).
Starting a local Ray launches a handful of processes and picks free ports; on a loaded machine that can fail once
for reasons of the moment (a start-up timeout, a port taken between its pick and its use), so a local start is
tried ``START_ATTEMPTS`` times, each failure logged, before it is reported. Joining a cluster by address is tried
once: an unreachable address is the user's to fix.

Ray is an optional extra (``[ray]``), imported only when one of these is called.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from cae_lcd.core.errors import ConfigError

__all__ = ["local_ray_options", "start_ray", "OBJECT_STORE_BYTES", "START_ATTEMPTS"]

log = logging.getLogger(__name__)

OBJECT_STORE_BYTES = 128 * 1024 ** 2  #: a local Ray's object store
START_ATTEMPTS = 3  #: tries to start a local Ray before its failure is reported


def local_ray_options(cpus: int | None) -> dict[str, Any]:
    """``ray.init`` arguments of a new local Ray of ``cpus`` CPUs (None: Ray counts the machine's)."""
    return {"address": "local", "num_cpus": cpus, "include_dashboard": False, "log_to_driver": False,
            "configure_logging": False, "object_store_memory": OBJECT_STORE_BYTES}


def start_ray(address: str | None = None, cpus: int | None = None) -> tuple[Any, bool]:
    """The ``ray`` module, initialised: the running Ray if this process has one, else the cluster at ``address``,
    else a new local Ray of ``cpus`` CPUs.

    Returns:
        ``(ray, started)``: ``started`` is True when this call initialised Ray (the caller then shuts it down).

    Raises:
        ConfigError: Ray not installed, or it could not be started or joined (the cause in one line).
    """
    try:
        import ray
    except ImportError:
        raise ConfigError("this needs Ray: pip install 'cae-loop-closure[ray]'") from None
    if ray.is_initialized():
        return ray, False
    attempts = 1 if address else START_ATTEMPTS
    options = {"address": address, "log_to_driver": False, "configure_logging": False} if address else \
        local_ray_options(cpus)
    error: Exception | None = None
    for attempt in range(1, attempts + 1):
        if error is not None:
            log.warning("a local Ray did not start (try %d of %d): %s; trying again", attempt - 1, attempts,
                        _one_line(error))
            time.sleep(2.0 * (attempt - 1))
        try:
            ray.init(**options)
            return ray, True
        except Exception as err:  # Ray raises many kinds (ConnectionError, TimeoutError, ValueError, RuntimeError)
            ray.shutdown()  # whatever half of it started
            error = err
    where = f"the Ray cluster at {address!r} could not be joined" if address else \
        f"a local Ray could not be started ({attempts} tries)"
    raise ConfigError(f"{where}: {_one_line(error)}") from error


def _one_line(err: BaseException | None) -> str:
    """An error's message on one line (at most 300 characters), or its type's name when it has none."""
    return " ".join(str(err).split())[:300] or type(err).__name__
