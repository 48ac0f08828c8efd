"""What bounds one client of the fleet server before its request reaches a route:

- ``BodyLimit``: an ASGI middleware that counts a request body's bytes as they arrive (Content-Length or chunked,
  whatever the headers claim) and its read time: over ``max_bytes`` -> 413, slower than ``timeout_s`` -> 408, before
  the app sees any of it; then its JSON values (by their separators ``,`` ``[`` ``{``, which base64 never holds):
  over ``max_values`` -> 413 before it is parsed (30 MB of ``{},`` parsed into 800 MB of dicts for 1.5 s in the
  event loop, before the token was even looked at).
- ``TimedH11Protocol`` (uvicorn's h11 protocol): a connection whose request headers are not complete within
  ``header_timeout_s`` of its opening (or of its previous response) is closed: half-sent requests hold nothing; an
  address holding ``max_per_address`` connections has its next ones closed at once (400 idle connections from one
  address took every file descriptor of a server, whose good robots then waited 10 s for an answer).
- ``AuthThrottle``: failed authentications per client address in a sliding window; past the limit, requests that
  would need a token hash get 429 *before* the hash is computed.
- ``HashBudget``: token hashes (PBKDF2, ~0.1 s of CPU each) for the whole server and per robot name, token
  buckets: past either, 429 before the hash (500 addresses x 20 bad tokens bought 1832 hashes in 93 s from the
  per-address limit alone; robots whose token was verified before need no hash and are never slowed).
- ``InFlight``: requests at once per key (a robot's keyframes): past the limit, 429 before the body is decoded (a
  robot's concurrent 3 MB PNGs of 16-bit RGBA zeros each held 380 MB while they waited for its lock: 2 GB for 8).
"""

from __future__ import annotations

import asyncio
import collections
import json
import threading
import time
from typing import Any, Awaitable, Callable

from uvicorn.protocols.http.h11_impl import H11Protocol

__all__ = ["BodyLimit", "TimedH11Protocol", "AuthThrottle", "HashBudget", "InFlight"]

Scope = dict[str, Any]
Message = dict[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]


async def _refuse(send: Send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


class BodyLimit:
    """ASGI middleware: reads the whole body first (at most ``max_bytes``, within ``timeout_s``), then replays it to
    ``app``; a request over either limit, or whose body holds more than ``max_values`` JSON values, is answered 413
    or 408 and never reaches ``app``. The bodies in memory at once of one client address are at most
    ``max_buffered`` bytes (at least ``max_bytes``): past it, 429 (bodies are read before the token is looked at: 30
    unauthenticated 30 MB bodies held 1 GB; per address, so that one client cannot use up the others' share)."""

    def __init__(self, app: Callable[..., Awaitable[None]], max_bytes: int, timeout_s: float,
                 max_values: int = 1000, max_buffered: int = 256 * 2**20) -> None:
        self.app, self.max_bytes, self.timeout_s = app, int(max_bytes), float(timeout_s)
        self.max_values, self.max_buffered = int(max_values), max(int(max_buffered), int(max_bytes))
        #: bytes of the bodies in memory now per client address (the event loop's: no lock)
        self.buffered: collections.Counter[str] = collections.Counter()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length", b"0")
        if not declared.isdigit() or int(declared) > self.max_bytes:
            await _refuse(send, 413, f"request body over {self.max_bytes} bytes")
            return
        chunks: list[bytes] = []
        address = scope["client"][0] if scope.get("client") else "?"
        try:
            await self._serve(scope, receive, send, chunks, address)
        finally:
            self.buffered[address] -= sum(len(c) for c in chunks)
            if self.buffered[address] <= 0:
                del self.buffered[address]

    async def _serve(self, scope: Scope, receive: Receive, send: Send, chunks: list[bytes], address: str) -> None:
        """Reads the body into ``chunks`` (counted in ``buffered[address]``), refuses it or replays it to ``app``."""
        try:
            status = await asyncio.wait_for(self._read(receive, chunks, address), self.timeout_s)
        except asyncio.TimeoutError:
            status = 408
        if status == 429:
            await _refuse(send, 429, "too many request bodies from this address in memory at once; retry")
            return
        if status == 413:
            await _refuse(send, 413, f"request body over {self.max_bytes} bytes")
            return
        if status == 408:
            await _refuse(send, 408, f"request body not received within {self.timeout_s:g} s")
            return
        if status == 499:  # the client went away
            return
        body, sent = b"".join(chunks), False
        if sum(body.count(c) for c in (b",", b"[", b"{")) >= self.max_values:  # an upper bound of the values
            await _refuse(send, 413, f"request body holds more than {self.max_values} JSON values")
            return

        async def replay() -> Message:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()  # http.disconnect once the client goes

        await self.app(scope, replay, send)

    async def _read(self, receive: Receive, chunks: list[bytes], address: str) -> int:
        """Reads the body into ``chunks``: 200 read, 413 over the limit, 429 over ``max_buffered`` with the address's
        others, 499 the client disconnected."""
        size = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return 499
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_bytes:
                return 413
            if self.buffered[address] + len(chunk) > self.max_buffered:
                return 429
            chunks.append(chunk)
            self.buffered[address] += len(chunk)
            if not message.get("more_body", False):
                return 200


class TimedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol, closing a connection whose request headers are not in within ``header_timeout_s``, and
    the connections of an address beyond its ``max_per_address`` open ones (class attributes set by
    ``cae_lcd.fleet.runner.server_config``, with ``open_per_address``: the counts of one server, kept in its event loop)."""

    header_timeout_s: float = 10.0
    max_per_address: int = 256
    open_per_address: collections.Counter[str] = collections.Counter()

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._address = self.client[0] if self.client else "?"
        if self.open_per_address[self._address] >= self.max_per_address:
            self._address = None
            transport.close()
            return
        self.open_per_address[self._address] += 1
        self._arm_header_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        super().connection_lost(exc)
        if getattr(self, "_address", None) is not None:
            self.open_per_address[self._address] -= 1
            if self.open_per_address[self._address] <= 0:
                del self.open_per_address[self._address]
            self._address = None

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._arm_header_deadline()

    def _arm_header_deadline(self) -> None:
        old = getattr(self, "_header_deadline", None)
        if old is not None:
            old.cancel()
        self._header_deadline = self.loop.call_later(self.header_timeout_s, self._header_timeout)

    def _header_timeout(self) -> None:
        """Closes the connection unless a request's headers came in and it is being served."""
        busy = self.cycle is not None and not self.cycle.response_complete
        if not busy and not self.transport.is_closing():
            self.transport.close()


class AuthThrottle:
    """Failed authentications per client address: at most ``limit`` in ``window_s`` seconds, for at most
    ``max_clients`` addresses (the oldest forgotten first); thread-safe."""

    def __init__(self, limit: int, window_s: float, max_clients: int = 10_000) -> None:
        self.limit, self.window_s, self.max_clients = int(limit), float(window_s), int(max_clients)
        self._failures: collections.OrderedDict[str, collections.deque[float]] = collections.OrderedDict()
        self._lock = threading.Lock()

    def _recent(self, client: str, now: float) -> collections.deque[float]:
        times = self._failures.get(client)
        if times is None:
            times = self._failures[client] = collections.deque(maxlen=self.limit)
            while len(self._failures) > self.max_clients:
                self._failures.popitem(last=False)
        while times and now - times[0] > self.window_s:
            times.popleft()
        return times

    def blocked(self, client: str) -> bool:
        """True when ``client`` failed ``limit`` times within the window (refuse it before hashing its token)."""
        with self._lock:
            return len(self._recent(client, time.monotonic())) >= self.limit

    def failed(self, client: str) -> None:
        """Counts a failed authentication of ``client``."""
        with self._lock:
            now = time.monotonic()
            self._recent(client, now).append(now)
            self._failures.move_to_end(client)


class HashBudget:
    """Token buckets of hashes: one for the server (``rate`` a second, ``burst`` at once) and one per robot name
    (``name_rate``, ``name_burst``; at most ``max_names`` names kept, the least recently used forgotten: a forgotten
    name starts full, so a flood of names is still bounded by the server's bucket); thread-safe."""

    def __init__(self, rate: float, burst: int, name_rate: float, name_burst: int, max_names: int = 10_000) -> None:
        self.rate, self.burst, self.name_rate, self.name_burst = float(rate), int(burst), float(name_rate), \
            int(name_burst)
        self.max_names = int(max_names)
        self._all = (float(burst), time.monotonic())
        self._names: collections.OrderedDict[str, tuple[float, float]] = collections.OrderedDict()
        self._lock = threading.Lock()

    @staticmethod
    def _refill(bucket: tuple[float, float], rate: float, burst: int, now: float) -> float:
        level, then = bucket
        return min(float(burst), level + (now - then) * rate)

    def take(self, name: str) -> bool:
        """Takes one hash of the server's and of ``name``'s buckets: False (nothing taken) when either is empty."""
        with self._lock:
            now = time.monotonic()
            level = self._refill(self._all, self.rate, self.burst, now)
            own = self._refill(self._names.get(name, (float(self.name_burst), now)), self.name_rate, self.name_burst,
                               now)
            if level < 1.0 or own < 1.0:
                return False
            self._all = (level - 1.0, now)
            self._names[name] = (own - 1.0, now)
            self._names.move_to_end(name)
            while len(self._names) > self.max_names:
                self._names.popitem(last=False)
            return True


class InFlight:
    """At most ``limit`` requests at once per key (a robot's name: keys are bounded by the registered robots);
    thread-safe."""

    def __init__(self, limit: int) -> None:
        self.limit = int(limit)
        self._count: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()

    def acquire(self, key: str) -> bool:
        """Takes one of ``key``'s slots: False (nothing taken) when all ``limit`` are taken."""
        with self._lock:
            if self._count[key] >= self.limit:
                return False
            self._count[key] += 1
            return True

    def release(self, key: str) -> None:
        """Gives back a slot ``acquire`` took."""
        with self._lock:
            self._count[key] -= 1
            if self._count[key] <= 0:
                del self._count[key]
