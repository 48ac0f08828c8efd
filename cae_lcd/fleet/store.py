"""The fleet server's state besides the keyframe images: robots and their hashed tokens, acknowledged keyframes (id,
timestamp, local pose), edges (odometry, loop, overlap, with their relative similarity and score), accepted overlaps
between robots and each robot's map-to-global transform.

``FleetStore`` is the interface the server uses; ``SQLiteStore`` implements it on an embedded SQLite file (stdlib
``sqlite3``: WAL journal, ``synchronous=FULL``, every write one transaction, foreign keys on), so a server killed
with ``kill -9`` and restarted has every keyframe it acknowledged. A server database could implement the same
interface: ``cae_lcd.fleet.postgres.PostgresStore`` does (``cae_lcd.fleet.stores.open_store`` picks one by location).

Tokens are never stored: a salted PBKDF2-HMAC-SHA256 hash is (salt and iteration count kept per robot), and a token
is checked with ``hmac.compare_digest``. Similarities are stored as their 4x4 matrices (``Sim3.matrix``) in JSON.

Layout (``format_version`` 1, in table ``meta``)::

    meta(key, value)                    format_version, created, anchor (the global frame's robot),
                                        retired:NAME (when robot NAME was retired)
    robots(name, salt, token_hash, iterations, created)
    keyframes(robot, keyframe, timestamp, pose)                      pose: 16 numbers, row-major 4x4
    edges(id, kind, robot_a, keyframe_a, robot_b, keyframe_b, sim3, score)
    overlaps(robot_a, robot_b, sim3, matches, accepted)              sim3 maps robot_b's map into robot_a's
    transforms(robot, sim3, updated)                                 robot's map -> the global frame
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import re
import sqlite3
import struct
import threading
import time
from abc import ABC, abstractmethod
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Self, Sequence

import numpy as np

from cae_lcd.core.conf import ConfigError, Int, configure
from cae_lcd.core.errors import ConflictError, DatabaseError

from .graph import EDGE_KINDS
from .sim3 import Sim3

__all__ = ["FORMAT_VERSION", "KeyframeAck", "EdgeRecord", "OverlapRecord", "FleetStore", "SQLStore", "SQLiteStore",
           "hash_token", "check_wal", "pose_json", "sim3_json", "sim3_from_json", "ROBOT_NAME", "check_robot_name"]

log = logging.getLogger(__name__)

FORMAT_VERSION = 1  #: version of the SQLite layout; a file of another version is refused
ROBOT_NAME = r"[A-Za-z0-9_-]{1,64}"  #: what a robot's name may be


def check_robot_name(name: Any) -> str:
    """``name`` when it is a robot name (``ROBOT_NAME``, in full).

    Raises:
        ConfigError: anything else (one line, the value quoted).
    """
    if not isinstance(name, str) or not re.fullmatch(ROBOT_NAME, name):
        raise ConfigError(f"a robot name must match {ROBOT_NAME}; got {name!r}")
    return name


@dataclass(frozen=True)
class KeyframeAck:
    """A keyframe the server acknowledged."""

    robot: str
    keyframe: int
    timestamp: float
    pose: np.ndarray  #: (4, 4) camera-to-map pose in the robot's own map


@dataclass(frozen=True)
class EdgeRecord:
    """A pose-graph edge measuring ``node_a^-1 o node_b`` (``cae_lcd.fleet.graph``)."""

    kind: str  #: one of ``cae_lcd.fleet.graph.EDGE_KINDS``
    robot_a: str
    keyframe_a: int
    robot_b: str
    keyframe_b: int
    relative: Sim3
    score: float = 0.0  #: how strong the evidence is (e.g. RANSAC inliers); 0 for odometry


@dataclass(frozen=True)
class OverlapRecord:
    """An accepted overlap: ``transform`` maps robot_b's map into robot_a's."""

    robot_a: str
    robot_b: str
    transform: Sim3
    matches: int  #: consecutive matching keyframes that led to the acceptance
    accepted: float  #: Unix time


def hash_token(token: str, salt: bytes, iterations: int) -> bytes:
    """PBKDF2-HMAC-SHA256 of ``token`` (32 bytes)."""
    return hashlib.pbkdf2_hmac("sha256", token.encode("utf-8"), salt, iterations)


def _sim3_json(T: Sim3) -> str:
    return json.dumps(T.matrix().ravel().tolist())


def _sim3_from_json(text: str) -> Sim3:
    return Sim3.from_matrix(np.array(json.loads(text), np.float64).reshape(4, 4))


def _loadable(rows: Sequence[tuple], load: Callable[[tuple], Any], what: str) -> list[Any]:
    """``load(row)`` of every row that can be loaded; one that cannot (e.g. a similarity with an infinite scale
    stored by an older version) is reported and skipped, so that a bad value never stops a server from starting."""
    out = []
    for row in rows:
        try:
            out.append(load(row))
        except (ConfigError, ValueError, TypeError) as err:
            log.warning("stored %s skipped (cannot be loaded): %s", what, str(err).splitlines()[0][:200])
    return out


# shared with the other backends (cae_lcd.fleet.postgres)
sim3_json, sim3_from_json, loadable = _sim3_json, _sim3_from_json, _loadable


def pose_json(pose: np.ndarray) -> str:
    """A ``(4, 4)`` pose as the stored JSON text (16 numbers, row-major): a retry compares this text exactly."""
    return json.dumps(np.asarray(pose, np.float64).reshape(4, 4).ravel().tolist())


class FleetStore(ABC):
    """What the fleet server keeps besides images; every method is atomic, readers see only committed data."""

    @abstractmethod
    def add_robot(self, name: str, token: str) -> None:
        """Registers a robot with its token (stored hashed). Raises ``ConfigError`` if the name is taken."""

    @abstractmethod
    def robots(self) -> list[str]:
        """Registered robot names, in registration order."""

    @abstractmethod
    def verify_token(self, name: str, token: str) -> bool:
        """True when ``token`` is ``name``'s token (False for an unknown robot)."""

    @abstractmethod
    def ack_keyframe(self, ack: KeyframeAck, edges: Sequence[EdgeRecord] = ()) -> bool:
        """Stores a keyframe and edges that come with it, all or nothing.

        Returns:
            True when stored, False when exactly this keyframe was stored before (a retry).

        Raises:
            ConfigError: an unknown robot, or the same keyframe id stored before with other content.
        """

    @abstractmethod
    def keyframes(self, robot: str, after: int = -1) -> list[KeyframeAck]:
        """The robot's acknowledged keyframes with ids after ``after`` (all by default), by id."""

    @abstractmethod
    def keyframe(self, robot: str, keyframe: int) -> KeyframeAck | None:
        """The robot's acknowledged keyframe ``keyframe`` (None: not stored); one row read, not the robot's all."""

    @abstractmethod
    def last_keyframe(self, robot: str) -> KeyframeAck | None:
        """The robot's acknowledged keyframe with the largest id (None: none yet); one row read."""

    @abstractmethod
    def add_edges(self, edges: Sequence[EdgeRecord]) -> None:
        """Stores edges between stored keyframes, all or nothing."""

    @abstractmethod
    def edges(self, kind: str | None = None, robot: str | None = None) -> list[EdgeRecord]:
        """Stored edges (of one kind; touching one robot), in insertion order."""

    @abstractmethod
    def add_overlap(self, overlap: OverlapRecord) -> None:
        """Stores (or replaces) the accepted overlap of a robot pair."""

    @abstractmethod
    def overlaps(self) -> list[OverlapRecord]:
        """Accepted overlaps, in acceptance order."""

    @abstractmethod
    def set_transforms(self, transforms: dict[str, Sim3]) -> None:
        """Stores the robots' map-to-global transforms of the latest solution, all in one transaction; robots absent
        from ``transforms`` are not merged (their old transform is dropped)."""

    @abstractmethod
    def transforms(self) -> dict[str, Sim3]:
        """Each merged robot's map-to-global transform."""

    @abstractmethod
    def anchor(self) -> str | None:
        """The robot whose map frame is the global frame (None: none chosen yet)."""

    @abstractmethod
    def set_anchor(self, robot: str, replace: bool = False) -> str:
        """Stores ``robot`` as the anchor when none is stored (``replace``: in any case, an admin's choice); returns
        the anchor stored now (another front end's when it chose first). Raises ``ConfigError``: unknown robot."""

    @abstractmethod
    def drop_keyframes(self, robot: str) -> int:
        """Deletes the robot's keyframes, the edges touching them, its overlaps and transform (one transaction);
        returns how many keyframes were deleted."""

    @abstractmethod
    def set_token(self, robot: str, token: str) -> None:
        """Replaces the robot's token (stored hashed; the old one no longer verifies). Raises ``ConfigError``: unknown
        robot."""

    @abstractmethod
    def retire(self, robot: str) -> None:
        """Retires a robot: its token no longer verifies, its name stays taken, its keyframes stay (``drop_keyframes``
        deletes them)."""

    @abstractmethod
    def retired(self) -> list[str]:
        """Retired robots' names."""

    @abstractmethod
    def close(self) -> None:
        """Releases the store; further calls fail."""


_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE robots (name TEXT PRIMARY KEY, salt BLOB NOT NULL, token_hash BLOB NOT NULL,
                     iterations INTEGER NOT NULL, created REAL NOT NULL);
CREATE TABLE keyframes (robot TEXT NOT NULL REFERENCES robots(name), keyframe INTEGER NOT NULL,
                        timestamp REAL NOT NULL, pose TEXT NOT NULL, PRIMARY KEY (robot, keyframe));
CREATE TABLE edges (id INTEGER PRIMARY KEY AUTOINCREMENT, kind TEXT NOT NULL,
                    robot_a TEXT NOT NULL, keyframe_a INTEGER NOT NULL, robot_b TEXT NOT NULL,
                    keyframe_b INTEGER NOT NULL, sim3 TEXT NOT NULL, score REAL NOT NULL,
                    FOREIGN KEY (robot_a, keyframe_a) REFERENCES keyframes(robot, keyframe),
                    FOREIGN KEY (robot_b, keyframe_b) REFERENCES keyframes(robot, keyframe));
CREATE TABLE overlaps (robot_a TEXT NOT NULL REFERENCES robots(name), robot_b TEXT NOT NULL REFERENCES robots(name),
                       sim3 TEXT NOT NULL, matches INTEGER NOT NULL, accepted REAL NOT NULL,
                       PRIMARY KEY (robot_a, robot_b));
CREATE TABLE transforms (robot TEXT PRIMARY KEY REFERENCES robots(name), sim3 TEXT NOT NULL, updated REAL NOT NULL);
"""


class SQLStore(FleetStore):
    """What the SQL backends share (``SQLiteStore``, ``cae_lcd.fleet.postgres.PostgresStore``): robots and their tokens,
    keyframe reads, edge checks. A backend gives its parameter placeholder ``_P``, the column that orders rows as
    they were inserted ``_ORDER``, ``_transaction()`` (a write transaction yielding a connection) and ``_read``."""

    _P = "?"  #: the driver's parameter placeholder
    _ORDER = "rowid"  #: orders a table's rows as they were inserted
    conf: dict[str, Any]
    _db: Any  #: the driver's connection
    _lock: threading.Lock  #: guards ``_db``

    @abstractmethod
    def _transaction(self) -> Any: ...

    @abstractmethod
    def _read(self, sql: str, args: Sequence[Any] = ()) -> list[tuple]: ...

    def add_robot(self, name: str, token: str) -> None:
        if not name or not token:
            raise ConfigError("a robot needs a non-empty name and token")
        salt = os.urandom(16)
        iterations = self.conf["token_iterations"]
        p = self._P
        with self._transaction() as db:
            if db.execute(f"SELECT 1 FROM robots WHERE name = {p}", (name,)).fetchone():
                raise ConfigError(f"robot {name!r} is already registered")
            db.execute("INSERT INTO robots (name, salt, token_hash, iterations, created) "
                       f"VALUES ({p}, {p}, {p}, {p}, {p})",
                       (name, salt, hash_token(token, salt, iterations), iterations, time.time()))

    def robots(self) -> list[str]:
        return [r[0] for r in self._read(f"SELECT name FROM robots ORDER BY {self._ORDER}")]

    def verify_token(self, name: str, token: str) -> bool:
        rows = self._read(f"SELECT salt, token_hash, iterations FROM robots WHERE name = {self._P}", (name,))
        # an unknown robot costs a hash too, so the answer's timing does not tell which names exist
        salt, stored, iterations = rows[0] if rows else (b"", b"", self.conf["token_iterations"])
        return hmac.compare_digest(hash_token(token, bytes(salt), iterations), bytes(stored)) and bool(rows)

    def _acks(self, robot: str, where: str, args: tuple, order: str = "") -> list[KeyframeAck]:
        """The robot's keyframes matching ``where`` (with ``args``), ordered by ``order``."""
        rows = self._read(f"SELECT keyframe, timestamp, pose FROM keyframes WHERE robot = {self._P} AND {where} "
                          f"ORDER BY keyframe {order}", (robot, *args))
        return [KeyframeAck(robot, k, t, np.array(json.loads(p)).reshape(4, 4)) for k, t, p in rows]

    def keyframes(self, robot: str, after: int = -1) -> list[KeyframeAck]:
        return self._acks(robot, f"keyframe > {self._P}", (int(after),))

    def keyframe(self, robot: str, keyframe: int) -> KeyframeAck | None:
        return next(iter(self._acks(robot, f"keyframe = {self._P}", (int(keyframe),))), None)

    def last_keyframe(self, robot: str) -> KeyframeAck | None:
        return next(iter(self._acks(robot, "TRUE", (), "DESC LIMIT 1")), None)

    @staticmethod
    def _edge_rows(edges: Sequence[EdgeRecord]) -> list[tuple]:
        """The rows of ``edges`` for ``INSERT INTO edges (kind, robot_a, keyframe_a, robot_b, keyframe_b, sim3,
        score)``, each kind checked first (ConfigError: nothing is written)."""
        for e in edges:
            if e.kind not in EDGE_KINDS:
                raise ConfigError(f"edge kind must be one of {', '.join(EDGE_KINDS)}; got {e.kind!r}")
        return [(e.kind, e.robot_a, int(e.keyframe_a), e.robot_b, int(e.keyframe_b), _sim3_json(e.relative),
                 float(e.score)) for e in edges]

    def add_edges(self, edges: Sequence[EdgeRecord]) -> None:
        with self._transaction() as db:
            self._insert_edges(db, edges)

    @staticmethod
    @abstractmethod
    def _insert_edges(db: Any, edges: Sequence[EdgeRecord]) -> None: ...

    def overlaps(self) -> list[OverlapRecord]:
        rows = self._read('SELECT robot_a, robot_b, sim3, matches, accepted FROM "overlaps" '  # a keyword in PostgreSQL
                          f"ORDER BY accepted, {self._ORDER}")
        return _loadable(rows, lambda r: OverlapRecord(r[0], r[1], _sim3_from_json(r[2]), r[3], r[4]), "overlap")

    def transforms(self) -> dict[str, Sim3]:
        rows = self._read(f"SELECT robot, sim3 FROM transforms ORDER BY {self._ORDER}")
        return dict(_loadable(rows, lambda r: (r[0], _sim3_from_json(r[1])), "transform"))

    def anchor(self) -> str | None:
        rows = self._read(f"SELECT value FROM meta WHERE key = {self._P}", ("anchor",))
        return rows[0][0] if rows else None

    def set_anchor(self, robot: str, replace: bool = False) -> str:
        p = self._P
        with self._transaction() as db:
            if not db.execute(f"SELECT 1 FROM robots WHERE name = {p}", (robot,)).fetchone():
                raise ConfigError(f"unknown robot {robot!r}")
            old = db.execute(f"SELECT value FROM meta WHERE key = {p}", ("anchor",)).fetchone()
            if old is None:
                db.execute(f"INSERT INTO meta VALUES ({p}, {p})", ("anchor", robot))
            elif replace:
                db.execute(f"UPDATE meta SET value = {p} WHERE key = {p}", (robot, "anchor"))
            else:
                return old[0]
        return robot

    def drop_keyframes(self, robot: str) -> int:
        p = self._P
        with self._transaction() as db:
            db.execute(f"DELETE FROM edges WHERE robot_a = {p} OR robot_b = {p}", (robot, robot))
            db.execute(f'DELETE FROM "overlaps" WHERE robot_a = {p} OR robot_b = {p}', (robot, robot))
            db.execute(f"DELETE FROM transforms WHERE robot = {p}", (robot,))
            n = db.execute(f"SELECT COUNT(*) FROM keyframes WHERE robot = {p}", (robot,)).fetchone()[0]
            db.execute(f"DELETE FROM keyframes WHERE robot = {p}", (robot,))
        return int(n)

    def set_token(self, robot: str, token: str) -> None:
        if not token:
            raise ConfigError("a robot's token must not be empty")
        salt, iterations, p = os.urandom(16), self.conf["token_iterations"], self._P
        with self._transaction() as db:
            if not db.execute(f"SELECT 1 FROM robots WHERE name = {p}", (robot,)).fetchone():
                raise ConfigError(f"unknown robot {robot!r}")
            db.execute(f"UPDATE robots SET salt = {p}, token_hash = {p}, iterations = {p} WHERE name = {p}",
                       (salt, hash_token(token, salt, iterations), iterations, robot))
            db.execute(f"DELETE FROM meta WHERE key = {p}", (f"retired:{robot}",))

    def retire(self, robot: str) -> None:
        p = self._P
        with self._transaction() as db:
            if not db.execute(f"SELECT 1 FROM robots WHERE name = {p}", (robot,)).fetchone():
                raise ConfigError(f"unknown robot {robot!r}")
            # a random hash: no token verifies any more
            db.execute(f"UPDATE robots SET token_hash = {p} WHERE name = {p}", (os.urandom(32), robot))
            db.execute(f"DELETE FROM meta WHERE key = {p}", (f"retired:{robot}",))
            db.execute(f"INSERT INTO meta VALUES ({p}, {p})", (f"retired:{robot}", repr(time.time())))

    def retired(self) -> list[str]:
        rows = self._read(f"SELECT key FROM meta WHERE key LIKE {self._P} ORDER BY key", ("retired:%",))
        return [r[0].split(":", 1)[1] for r in rows]

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_WAL_MAGIC = (0x377F0682, 0x377F0683)  #: a SQLite WAL's first 4 bytes (little-, big-endian checksums)
_WAL_HEADER, _WAL_FRAME_HEADER = 32, 24  #: bytes


def _wal_checksum(data: bytes, big_endian: bool) -> tuple[int, int]:
    """SQLite's WAL checksum of ``data`` (a multiple of 8 bytes)."""
    words = struct.unpack((">" if big_endian else "<") + f"{len(data) // 4}I", data)
    s0 = s1 = 0
    for i in range(0, len(words), 2):
        s0 = (s0 + words[i] + s1) & 0xFFFFFFFF
        s1 = (s1 + words[i + 1] + s0) & 0xFFFFFFFF
    return s0, s1


def check_wal(path: Path) -> None:
    """Refuses a SQLite write-ahead log that SQLite would silently skip (whole or from a point on), opening the
    database at an older state: a header that is not a WAL's or fails its checksum, a length that is not whole frames
    (a frame cut by a crash is at most its 24-byte header: SQLite writes the header, then the page).

    Raises:
        DatabaseError: one line, what is wrong and what to do.
    """
    wal = Path(f"{path}-wal")
    try:
        size = wal.stat().st_size
    except FileNotFoundError:
        return
    if size == 0:
        return
    with open(wal, "rb") as f:
        head = f.read(_WAL_HEADER)
    fix = ("the database would open at an older state; restore the file from a backup, or move it aside to accept "
           "the state without it")
    if len(head) < _WAL_HEADER or struct.unpack(">I", head[:4])[0] not in _WAL_MAGIC:
        raise DatabaseError(f"{wal} is damaged (not a SQLite WAL header): {fix}")
    magic, _, page = struct.unpack(">III", head[:12])
    if _wal_checksum(head[:24], bool(magic & 1)) != struct.unpack(">II", head[24:32]):
        raise DatabaseError(f"{wal} is damaged (its header fails its checksum): {fix}")
    frame = _WAL_FRAME_HEADER + (page if page != 1 else 65536)
    if (size - _WAL_HEADER) % frame not in (0, _WAL_FRAME_HEADER):
        raise DatabaseError(f"{wal} is damaged ({size} bytes: not whole {frame}-byte frames; cut short?): {fix}")


class SQLiteStore(SQLStore):
    """``FleetStore`` on one SQLite file; safe to share between the threads of one process (one lock).

    Args:
        path: the database file (created with its folder if missing).
        conf: overrides of ``default_conf``.

    Raises:
        DatabaseError: the file is not a fleet database, has another ``format_version``, or is damaged or locked, or
            its write-ahead log is damaged (``check_wal``).
    """

    default_conf: dict[str, Any] = {
        "token_iterations": 100_000,  # PBKDF2 iterations for a new robot's token (kept per robot)
        "busy_timeout_ms": 5000,  # how long a write waits for another process's lock before failing
    }
    conf_rules: dict[str, Any] = {"token_iterations": Int(1, 10_000_000), "busy_timeout_ms": Int(0, 3_600_000)}

    def __init__(self, path: str | Path, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "store")
        self.path = Path(path)
        self._lock = threading.Lock()
        check_wal(self.path)  # before SQLite opens it: it would skip a damaged log without a word
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            self._db.execute(f"PRAGMA busy_timeout = {self.conf['busy_timeout_ms']}")
            self._db.execute("PRAGMA journal_mode = WAL")
            self._db.execute("PRAGMA synchronous = FULL")
            self._db.execute("PRAGMA foreign_keys = ON")
            self._open_or_create()
        except sqlite3.DatabaseError as err:
            raise DatabaseError(f"{self.path}: not a usable fleet database ({err})") from None

    def _open_or_create(self) -> None:
        tables = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if not tables:
            with self._transaction() as db:
                for statement in filter(str.strip, _SCHEMA.split(";")):
                    db.execute(statement)
                db.executemany("INSERT INTO meta VALUES (?, ?)",
                               [("format_version", str(FORMAT_VERSION)), ("created", repr(time.time()))])
            return
        row = self._db.execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone() \
            if "meta" in tables else None
        if row is None:
            raise DatabaseError(f"{self.path} is not a fleet database (no format_version)")
        if row[0] != str(FORMAT_VERSION):
            raise DatabaseError(f"{self.path} has format_version {row[0]}; this version reads {FORMAT_VERSION}")
        if self._db.execute("PRAGMA quick_check").fetchone()[0] != "ok":
            raise DatabaseError(f"{self.path} is damaged (SQLite quick_check failed)")

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE ... COMMIT, ROLLBACK on any error), under the thread lock."""
        with self._lock:
            try:
                self._db.execute("BEGIN IMMEDIATE")
                try:
                    yield self._db
                except BaseException:
                    self._db.execute("ROLLBACK")
                    raise
                self._db.execute("COMMIT")
            except sqlite3.IntegrityError as err:
                raise ConfigError(f"refused by the fleet database: {err}") from None
            except sqlite3.OperationalError as err:
                raise DatabaseError(f"{self.path}: {err}") from None

    def _read(self, sql: str, args: Sequence[Any] = ()) -> list[tuple]:
        with self._lock:
            try:
                return self._db.execute(sql, args).fetchall()
            except sqlite3.Error as err:
                raise DatabaseError(f"{self.path}: {err}") from None

    # -------------------------------------------------------------------------------------------------- keyframes
    def ack_keyframe(self, ack: KeyframeAck, edges: Sequence[EdgeRecord] = ()) -> bool:
        pose = pose_json(ack.pose)
        with self._transaction() as db:
            if not db.execute("SELECT 1 FROM robots WHERE name = ?", (ack.robot,)).fetchone():
                raise ConfigError(f"unknown robot {ack.robot!r}")
            old = db.execute("SELECT timestamp, pose FROM keyframes WHERE robot = ? AND keyframe = ?",
                             (ack.robot, int(ack.keyframe))).fetchone()
            if old is not None:
                if old != (float(ack.timestamp), pose):
                    raise ConflictError(f"robot {ack.robot!r} sent keyframe {ack.keyframe} before, with other content")
                return False
            db.execute("INSERT INTO keyframes VALUES (?, ?, ?, ?)",
                       (ack.robot, int(ack.keyframe), float(ack.timestamp), pose))
            self._insert_edges(db, edges)
        return True

    # ------------------------------------------------------------------------------------------------------ edges
    @staticmethod
    def _insert_edges(db: sqlite3.Connection, edges: Sequence[EdgeRecord]) -> None:
        db.executemany("INSERT INTO edges (kind, robot_a, keyframe_a, robot_b, keyframe_b, sim3, score) "
                       "VALUES (?, ?, ?, ?, ?, ?, ?)", SQLStore._edge_rows(edges))

    def edges(self, kind: str | None = None, robot: str | None = None) -> list[EdgeRecord]:
        rows = self._read("SELECT kind, robot_a, keyframe_a, robot_b, keyframe_b, sim3, score FROM edges "
                          "WHERE (?1 IS NULL OR kind = ?1) AND (?2 IS NULL OR robot_a = ?2 OR robot_b = ?2) "
                          "ORDER BY id", (kind, robot))
        return _loadable(rows, lambda r: EdgeRecord(*r[:5], _sim3_from_json(r[5]), r[6]), "edge")

    # ------------------------------------------------------------------------------------- overlaps, transforms
    def add_overlap(self, overlap: OverlapRecord) -> None:
        with self._transaction() as db:
            db.execute("INSERT OR REPLACE INTO overlaps VALUES (?, ?, ?, ?, ?)",
                       (overlap.robot_a, overlap.robot_b, _sim3_json(overlap.transform), int(overlap.matches),
                        float(overlap.accepted)))

    def set_transforms(self, transforms: dict[str, Sim3]) -> None:
        now = time.time()
        with self._transaction() as db:
            db.execute("DELETE FROM transforms")
            db.executemany("INSERT INTO transforms VALUES (?, ?, ?)",
                           [(robot, _sim3_json(T), now) for robot, T in transforms.items()])

