"""cae_lcd.fleet.limits over real HTTP on loopback: a chunked body that lies about its length, half-sent requests, and a
flood of wrong tokens, against a live server with small limits (bounded counts and times, loopback only)."""

from __future__ import annotations

import select
import socket
import time

import httpx
import pytest

from cae_lcd.fleet.client import FleetClient
from cae_lcd.fleet.limits import AuthThrottle
from cae_lcd.fleet.runner import ServerThread
from cae_lcd.fleet.server import create_app

ADMIN = "limits-admin-secret"
LIMITS = {"limits": {"max_request_mb": 1.0, "header_timeout_s": 1.0, "body_timeout_s": 2.0, "auth_failures": 5,
                     "robot_hash_burst": 10,  # the address limit is what TestAuthThrottle checks
                     "auth_window_s": 60.0}}


@pytest.fixture(scope="module")
def live(tmp_path_factory, cae_descriptor):
    """A server with small limits and robot A registered: ``(url, A's token)``."""
    state = tmp_path_factory.mktemp("limits_state")
    with ServerThread(create_app(state, ADMIN, LIMITS, descriptor=cae_descriptor)) as server:
        yield server, FleetClient(server.url, ADMIN).register("A")


def raw(server, parts: list[bytes], timeout: float = 10.0) -> bytes:
    """Sends ``parts`` one by one on a new loopback connection, stopping once the server answers; returns the
    answer's first bytes."""
    with socket.create_connection((server.host, server.port), timeout=timeout) as s:
        for part in parts:
            if select.select([s], [], [], 0)[0]:
                break
            try:
                s.sendall(part)
            except (BrokenPipeError, ConnectionResetError):
                break
        return s.recv(65536)


class TestBodyLimit:
    def test_a_chunked_body_that_claims_two_bytes_is_counted(self, live, sample_poses, jpeg):
        server, token = live
        head = (f"POST /robots/A/keyframes HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
                "Content-Type: application/json\r\nContent-Length: 2\r\nTransfer-Encoding: chunked\r\n\r\n").encode()
        chunk = b"x" * 65536
        answer = raw(server, [head] + [b"%x\r\n%s\r\n" % (len(chunk), chunk)] * 40 + [b"0\r\n\r\n"])  # 2.5 MB
        status = int(answer.split(b" ", 2)[1])
        assert status in (400, 413), answer[:200]  # h11 may refuse the two headers itself; never a 2xx or 5xx

    def test_a_chunked_body_over_the_limit_is_413(self, live):
        server, token = live
        with httpx.Client() as http:
            r = http.post(f"{server.url}/robots/A/keyframes", content=iter([b"x" * 65536] * 40),
                          headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"})
        assert r.status_code == 413 and "bytes" in r.json()["detail"]

    @pytest.mark.parametrize("token", ["A.wrong", None], ids=["wrong-token", "A"])
    def test_a_body_of_too_many_json_values_is_413_before_it_is_parsed(self, live, token):
        """30 MB of ``{},`` were parsed into 800 MB of dicts (1.5 s in the event loop) before the token was looked
        at; a few kB show that the values are counted, not the bytes."""
        server, good = live
        r = httpx.post(f"{server.url}/robots/A/keyframes", content=b'{"x": [' + b",".join([b"{}"] * 5000) + b"]}",
                       headers={"Authorization": f"Bearer {token or good}", "Content-Type": "application/json"})
        assert r.status_code == 413 and "JSON values" in r.json()["detail"]

    def test_a_body_sent_too_slowly_is_408(self, live):
        server, token = live
        head = (f"POST /robots/A/keyframes HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
                "Content-Type: application/json\r\nContent-Length: 1000\r\n\r\n{").encode()
        with socket.create_connection((server.host, server.port), timeout=10) as s:
            s.sendall(head)
            started = time.monotonic()
            answer = s.recv(65536)
        assert answer.startswith(b"HTTP/1.1 408") and time.monotonic() - started < 6


class TestHalfSentRequests:
    def test_connections_with_incomplete_headers_are_closed(self, live):
        server, _ = live
        sockets = [socket.create_connection((server.host, server.port), timeout=10) for _ in range(30)]
        try:
            for s in sockets:
                s.sendall(b"POST /robots/A/keyframes HTTP/1.1\r\nHost: x\r\n")  # and never the rest
            started = time.monotonic()
            closed = [s.recv(1024) == b"" for s in sockets]  # b"": the server closed it
            assert all(closed) and time.monotonic() - started < 8
        finally:
            for s in sockets:
                s.close()
        assert httpx.get(f"{server.url}/overlaps", headers={"Authorization": f"Bearer {ADMIN}"}).status_code == 200


class TestBodiesInMemory:
    def test_bodies_past_an_addresss_budget_are_429_and_it_is_given_back(self, tmp_path):
        """Bodies are read before the token is looked at: 30 unauthenticated 30 MB bodies held 1 GB at once. Per
        address: one client cannot use up the others' share."""
        conf = {"limits": {"max_request_mb": 1.0, "max_buffered_mb": 1.5, "body_timeout_s": 20.0}}
        with ServerThread(create_app(tmp_path, ADMIN, conf, recognize=False)) as server:
            def post(source: str = "127.0.0.1") -> httpx.Response:
                with httpx.Client(transport=httpx.HTTPTransport(local_address=source)) as http:
                    return http.post(f"{server.url}/robots", content=b"x" * 800_000,
                                     headers={"Authorization": "Bearer nobody", "Content-Type": "application/json"})

            with socket.create_connection((server.host, server.port), timeout=10) as held:
                held.sendall(b"POST /robots HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer nobody\r\n"
                             b"Content-Type: application/json\r\nContent-Length: 900000\r\n\r\n" + b"x" * 800_000)
                deadline, r = time.monotonic() + 10, post()
                while r.status_code != 429 and time.monotonic() < deadline:  # once the server holds the 800 kB
                    time.sleep(0.05)
                    r = post()
                assert r.status_code == 429 and "in memory" in r.json()["detail"]
                assert post("127.0.0.2").status_code == 422  # another address has its own share
                held.sendall(b"x" * 100_000)
                assert held.recv(1024).startswith(b"HTTP/1.1 422")  # read in full: then not JSON
            assert post().status_code == 422  # its bytes were given back


class TestKeyframesInFlight:
    def test_a_robots_keyframes_beyond_its_slots_are_429_at_once(self, live, sample_poses, jpeg, monkeypatch):
        """A robot's keyframes sent at once queued for its lock, each holding its decoded image (a 3 MB PNG of 16-bit
        RGBA zeros: 380 MB each, 2 GB for 8): beyond ``limits.keyframes_in_flight`` (2) they are refused first."""
        import base64
        import threading

        server, token = live
        service, release, entered = server.app.state.service, threading.Event(), threading.Semaphore(0)
        submit = service.submit_keyframe

        def held(*args, **kwargs):
            entered.release()
            release.wait(20)
            return submit(*args, **kwargs)

        monkeypatch.setattr(service, "submit_keyframe", held)
        payload = {"keyframe": 0, "timestamp": 0.0, "pose": sample_poses[0].tolist(),
                   "image": base64.b64encode(jpeg(0)).decode()}
        auth = {"Authorization": f"Bearer {token}"}
        codes: list[int] = []

        def post() -> None:
            codes.append(httpx.post(f"{server.url}/robots/A/keyframes", json=payload, headers=auth, timeout=30)
                         .status_code)

        first = [threading.Thread(target=post) for _ in range(2)]
        for t in first:
            t.start()
        try:
            assert entered.acquire(timeout=20) and entered.acquire(timeout=20)  # both in flight, held
            r = httpx.post(f"{server.url}/robots/A/keyframes", json=payload, headers=auth, timeout=5)
            assert r.status_code == 429 and "in flight" in r.json()["detail"]
        finally:
            release.set()
            for t in first:
                t.join(30)
        assert sorted(codes) == [200, 200]  # one stored, the other its identical retry
        assert FleetClient(server.url, token).submit_keyframe("A", 0, 0.0, sample_poses[0], jpeg(0)) is False


class TestConnectionsPerAddress:
    def test_an_address_beyond_its_connections_is_closed_and_others_are_served(self, tmp_path):
        """400 idle connections from one address took every file descriptor: good robots waited 10 s for an answer.
        The flood comes from 127.0.0.2 (loopback too), the good client from 127.0.0.1."""
        conf = {"limits": {"max_connections_per_address": 8, "header_timeout_s": 30.0}}
        with ServerThread(create_app(tmp_path, ADMIN, conf, recognize=False)) as server:
            flood = [socket.create_connection((server.host, server.port), timeout=10, source_address=("127.0.0.2", 0))
                     for _ in range(20)]
            try:
                deadline, closed = time.monotonic() + 5, set()
                while len(closed) < 12 and time.monotonic() < deadline:
                    for s in select.select([s for s in flood if s not in closed], [], [], 0.2)[0]:
                        if s.recv(1024) == b"":
                            closed.add(s)
                assert len(closed) == 12  # the 8 first ones are held (until their header deadline)
                assert httpx.get(f"{server.url}/overlaps", headers={"Authorization": f"Bearer {ADMIN}"}).json() == []
            finally:
                for s in flood:
                    s.close()
            time.sleep(0.3)  # their slots are given back once the server saw them go
            with socket.create_connection((server.host, server.port), timeout=10,
                                          source_address=("127.0.0.2", 0)) as s:
                s.sendall(b"GET /map HTTP/1.1\r\nHost: x\r\n\r\n")
                assert s.recv(1024).startswith(b"HTTP/1.1 200")


class TestAuthThrottle:
    def test_wrong_tokens_are_429_after_the_limit_and_good_tokens_still_work(self, live):
        server, token = live
        FleetClient(server.url, token).overlaps()  # A's token verified once (then remembered: no hash)
        store = server.app.state.service.store
        hashes = []
        verify = store.verify_token
        store.verify_token = lambda *a: hashes.append(a) or verify(*a)
        codes = [httpx.get(f"{server.url}/overlaps", headers={"Authorization": f"Bearer A.wrong{i}"}).status_code
                 for i in range(8)]
        assert codes == [401] * 5 + [429] * 3
        assert len(hashes) == 5  # the 429s were refused before the PBKDF2 hash (34 ms each)
        assert FleetClient(server.url, token).overlaps() == []
        assert FleetClient(server.url, ADMIN).overlaps() == []

    def test_the_window_forgets_and_addresses_are_bounded(self, monkeypatch):
        clock = [0.0]
        monkeypatch.setattr(time, "monotonic", lambda: clock[0])
        t = AuthThrottle(2, 10.0, max_clients=3)
        t.failed("a"), t.failed("a")
        assert t.blocked("a") and not t.blocked("b")
        clock[0] = 11.0
        assert not t.blocked("a")
        for c in "bcde":
            t.failed(c)
        assert len(t._failures) <= 3


class TestHashBudget:
    def test_rotating_addresses_buy_no_more_hashes_and_cached_robots_are_not_slowed(self, tmp_path):
        """The audit: 500 addresses x 20 bad tokens bought 1832 PBKDF2 hashes in 93 s. Here 40 loopback addresses x
        5 bad tokens (each address within its own failure limit) buy at most the server's burst; a robot whose token
        was verified before is answered at once all along."""
        limits = {"limits": {"auth_failures": 20, "token_hashes_per_s": 0.01, "token_hash_burst": 10,
                             "robot_hashes_per_s": 0.01, "robot_hash_burst": 5}}
        with ServerThread(create_app(tmp_path, ADMIN, limits, recognize=False)) as server:
            token = FleetClient(server.url, ADMIN).register("A")
            FleetClient(server.url, token).overlaps()  # verified once: remembered
            store = server.app.state.service.store
            hashes = []
            verify = store.verify_token
            store.verify_token = lambda *a: hashes.append(a) or verify(*a)
            codes, honest = [], []
            for i in range(40):
                transport = httpx.HTTPTransport(local_address=f"127.0.{i // 200}.{2 + i % 200}")
                with httpx.Client(transport=transport, base_url=server.url) as c:
                    codes += [c.get("/overlaps", headers={"Authorization": f"Bearer R{i}x{j}.bad"}).status_code
                              for j in range(5)]
                start = time.monotonic()
                assert FleetClient(server.url, token).overlaps() == []
                honest.append(time.monotonic() - start)
            assert len(hashes) <= 11 and codes.count(401) == len(hashes) and codes.count(429) == 200 - len(hashes)
            assert sorted(honest)[len(honest) // 2] < 0.5 and max(honest) < 3.0  # loose: a loaded CI machine
            # one robot's name from many addresses: its own budget (the server's has none left either)
            store.verify_token = verify
            codes = [httpx.get(f"{server.url}/overlaps", headers={"Authorization": f"Bearer A.bad{j}"}).status_code
                     for j in range(3)]
            assert codes == [429] * 3

    def test_per_name_buckets_refill_and_are_bounded(self, monkeypatch):
        from cae_lcd.fleet.limits import HashBudget

        clock = [0.0]
        monkeypatch.setattr(time, "monotonic", lambda: clock[0])
        b = HashBudget(rate=10.0, burst=100, name_rate=1.0, name_burst=2, max_names=3)
        assert [b.take("a") for _ in range(3)] == [True, True, False]  # a's burst
        assert b.take("b")  # another name: the server's budget has room
        clock[0] = 1.0
        assert b.take("a") and not b.take("a")  # one a second
        for name in "cdef":
            b.take(name)
        assert len(b._names) <= 3
        g = HashBudget(rate=1.0, burst=2, name_rate=100.0, name_burst=100)
        assert [g.take(f"n{i}") for i in range(3)] == [True, True, False]  # the server's burst, whatever the names
