"""Re-optimisation of the global pose graph in a worker thread: every change (a keyframe, a loop or overlap edge)
asks for a new solution; the worker solves a snapshot of the graph and publishes it, so reads never wait for gtsam
and always get the latest finished result. Changes that arrive while it solves are folded into the next run.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable

from cae_lcd.core.conf import Bool, Float, configure
from cae_lcd.core.threads import release_free_memory

from .graph import GraphResult, PoseGraph

__all__ = ["BackgroundOptimizer"]

log = logging.getLogger(__name__)


class BackgroundOptimizer:
    """Solves the graph that ``snapshot`` returns whenever ``changed`` was called since the last solution.

    Args:
        snapshot: returns a copy of the current graph (called in the worker, under the owner's lock if it needs one).
        publish: called with each new result in the worker thread (e.g. to store the robots' transforms).
        conf: overrides of ``default_conf``.
    """

    default_conf: dict[str, Any] = {
        "background": True,  # solve in a worker thread; False: in the reading thread, when a read needs it
        "min_interval_s": 0.2,  # at least this long between two solutions (changes arriving meanwhile are batched)
    }
    conf_rules: dict[str, Any] = {"background": Bool(), "min_interval_s": Float(0, 3600)}

    def __init__(self, snapshot: Callable[[], PoseGraph], publish: Callable[[GraphResult], None] | None = None,
                 conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "optimizer")
        self._snapshot, self._publish = snapshot, publish
        self._cond = threading.Condition()
        self._wanted, self._done = 1, 0  # generations asked for / solved (the graph as built at start is wanted)
        self._latest = GraphResult()
        self._closed = False
        self._solve_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        if self.conf["background"]:
            self._thread = threading.Thread(target=self._work, name="fleet-optimizer", daemon=True)
            self._thread.start()

    def changed(self) -> None:
        """The graph changed: a new solution is wanted."""
        with self._cond:
            self._wanted += 1
            self._cond.notify_all()

    def latest(self) -> GraphResult:
        """The latest finished solution (empty before the first)."""
        with self._cond:
            return self._latest

    def wait(self, timeout: float = 30.0) -> GraphResult:
        """A solution that includes every change made before this call (waits up to ``timeout`` seconds; then the
        latest one)."""
        with self._cond:
            target = self._wanted
        if self._thread is None:
            self._solve(target)
        with self._cond:
            self._cond.wait_for(lambda: self._done >= target or self._closed, timeout)
            return self._latest

    def _solve(self, generation: int) -> None:
        with self._solve_lock:
            if self._done >= generation:
                return
            started = time.perf_counter()
            result = self._snapshot().optimize()
            if self._publish is not None:
                self._publish(result)
            release_free_memory()  # the solve freed its copy of the graph: those pages go back to the system
            with self._cond:
                self._latest, self._done = result, max(self._done, generation)
                self._cond.notify_all()
            log.debug("graph solved (generation %d) in %.3f s", generation, time.perf_counter() - started)

    def _work(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._wanted > self._done or self._closed)
                if self._closed:
                    return
                generation = self._wanted
            try:
                self._solve(generation)
            except Exception:  # noqa: BLE001 - keep serving the last result; the next change tries again
                log.exception("pose graph optimisation failed")
                with self._cond:
                    self._done = generation
                    self._cond.notify_all()
            time.sleep(self.conf["min_interval_s"])

    def close(self) -> None:
        """Stops the worker (a solution in progress finishes)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=30)
