"""The fleet server on uvicorn in a background thread (tests, the demo, the load test): ``with ServerThread(app) as
srv: FleetClient(srv.url, token)``. Port 0 picks a free port; loopback by default.
"""

from __future__ import annotations

import collections
import logging
import threading
import time

import uvicorn
from fastapi import FastAPI

from cae_lcd.core.errors import LCDError

from .limits import TimedH11Protocol

__all__ = ["ServerThread", "server_config"]

log = logging.getLogger(__name__)


def server_config(app: FastAPI, host: str = "127.0.0.1", port: int = 0, log_level: str = "warning") -> uvicorn.Config:
    """The uvicorn configuration of the fleet server (``cae-lcd serve`` and ``ServerThread`` alike): the h11 protocol
    with a header read deadline (``limits.header_timeout_s``) and open connections bounded per client address
    (``limits.max_connections_per_address``), a short keep-alive and bounded request heads."""
    limits = app.state.service.conf["limits"]
    protocol = type("FleetH11", (TimedH11Protocol,), {"header_timeout_s": float(limits["header_timeout_s"]),
                                                      "max_per_address": int(limits["max_connections_per_address"]),
                                                      "open_per_address": collections.Counter()})
    return uvicorn.Config(app, host=host, port=port, log_level=log_level, lifespan="on", access_log=False,
                          http=protocol, timeout_keep_alive=5, h11_max_incomplete_event_size=64 * 1024)


class ServerThread:
    """Serves ``app`` on ``host:port`` in a daemon thread until ``stop`` (or the end of the ``with`` block).

    Args:
        app: the FastAPI app (``cae_lcd.fleet.server.create_app``).
        host: interface to listen on.
        port: TCP port; 0 = a free one (read it from ``port`` once started).
        start_timeout: seconds to wait for the server to listen.
    """

    def __init__(self, app: FastAPI, host: str = "127.0.0.1", port: int = 0, start_timeout: float = 30.0) -> None:
        self.app, self.host = app, host
        self._server = uvicorn.Server(server_config(app, host, port))
        self._thread = threading.Thread(target=self._server.run, name="fleet-server", daemon=True)
        self._timeout = start_timeout
        self.port = port

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def start(self) -> "ServerThread":
        """Starts serving and waits until the socket listens.

        Raises:
            LCDError: the server did not start within ``start_timeout`` (e.g. the port is taken).
        """
        self._thread.start()
        deadline = time.monotonic() + self._timeout
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise LCDError(f"the fleet server did not start on {self.host}:{self.port}")
            time.sleep(0.02)
        self.port = self._server.servers[0].sockets[0].getsockname()[1]
        log.info("fleet server listening on %s", self.url)
        return self

    def stop(self) -> None:
        """Stops serving (open requests finish, the app's shutdown handlers run) and waits for the thread."""
        self._server.should_exit = True
        self._thread.join(timeout=60)

    def __enter__(self) -> "ServerThread":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
