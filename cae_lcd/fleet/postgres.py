"""``FleetStore`` on a PostgreSQL server (psycopg 3): the scale-out backend, shared by several front-end replicas and
workers, with the semantics of ``SQLiteStore`` (``cae_lcd.fleet.store``): one transaction per keyframe with its edges, a
``format_version`` in table ``meta``, salted PBKDF2 tokens compared in constant time, a retry of an acknowledged
keyframe idempotent and a conflicting one refused.

Selected by a URL (``cae-lcd serve --store postgresql://USER@HOST:PORT/DB``); the layout is ``cae_lcd.fleet.store``'s, with
PostgreSQL types (``BYTEA`` salts and hashes, ``DOUBLE PRECISION`` times, ``BIGSERIAL`` insertion order). Two
processes creating the layout at once are serialised by an advisory lock.
"""

from __future__ import annotations

import logging
import threading
import time
from contextlib import contextmanager
from typing import Any, Iterator, Sequence

from cae_lcd.core.conf import ConfigError, Int, configure
from cae_lcd.core.errors import ConflictError, DatabaseError

from .sim3 import Sim3
from .store import (FORMAT_VERSION, EdgeRecord, KeyframeAck, OverlapRecord, SQLStore, loadable, pose_json,
                    sim3_from_json, sim3_json)

__all__ = ["PostgresStore", "is_postgres_url"]

log = logging.getLogger(__name__)

_SCHEMA_LOCK = 0x6C6364  #: advisory lock id held while the layout is created

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE robots (seq BIGSERIAL UNIQUE, name TEXT PRIMARY KEY, salt BYTEA NOT NULL, token_hash BYTEA NOT NULL,
                     iterations INTEGER NOT NULL, created DOUBLE PRECISION NOT NULL);
CREATE TABLE keyframes (robot TEXT NOT NULL REFERENCES robots(name), keyframe BIGINT NOT NULL,
                        timestamp DOUBLE PRECISION NOT NULL, pose TEXT NOT NULL, PRIMARY KEY (robot, keyframe));
CREATE TABLE edges (id BIGSERIAL PRIMARY KEY, kind TEXT NOT NULL, robot_a TEXT NOT NULL, keyframe_a BIGINT NOT NULL,
                    robot_b TEXT NOT NULL, keyframe_b BIGINT NOT NULL, sim3 TEXT NOT NULL,
                    score DOUBLE PRECISION NOT NULL,
                    FOREIGN KEY (robot_a, keyframe_a) REFERENCES keyframes(robot, keyframe),
                    FOREIGN KEY (robot_b, keyframe_b) REFERENCES keyframes(robot, keyframe));
CREATE INDEX edges_a ON edges (robot_a);
CREATE INDEX edges_b ON edges (robot_b);
CREATE TABLE "overlaps" (seq BIGSERIAL, robot_a TEXT NOT NULL REFERENCES robots(name),
                       robot_b TEXT NOT NULL REFERENCES robots(name), sim3 TEXT NOT NULL, matches INTEGER NOT NULL,
                       accepted DOUBLE PRECISION NOT NULL, PRIMARY KEY (robot_a, robot_b));
CREATE TABLE transforms (seq BIGSERIAL, robot TEXT PRIMARY KEY REFERENCES robots(name), sim3 TEXT NOT NULL,
                         updated DOUBLE PRECISION NOT NULL)
"""


def is_postgres_url(location: str) -> bool:
    """True for a ``postgresql://`` (or ``postgres://``) URL."""
    return str(location).startswith(("postgresql://", "postgres://"))


class PostgresStore(SQLStore):
    """``FleetStore`` on one PostgreSQL database; one connection per store, shared by its threads under a lock.

    Args:
        url: ``postgresql://USER[:PASSWORD]@HOST[:PORT]/DBNAME[?host=/socket/dir]`` (libpq syntax).
        conf: overrides of ``default_conf``.

    Raises:
        DatabaseError: the server cannot be reached, or the database holds other tables, another ``format_version``.
    """

    _P = "%s"
    _ORDER = "seq"
    default_conf: dict[str, Any] = {
        "token_iterations": 100_000,  # PBKDF2 iterations for a new robot's token (kept per robot)
        "connect_timeout_s": 10,  # how long opening the connection may take before failing
        "lock_timeout_ms": 5000,  # how long a write waits for another writer's row lock before failing
    }
    conf_rules: dict[str, Any] = {"token_iterations": Int(1, 10_000_000), "connect_timeout_s": Int(1, 3600),
                                  "lock_timeout_ms": Int(0, 3_600_000)}

    def __init__(self, url: str, conf: dict[str, Any] | None = None) -> None:
        import psycopg  # here: only this backend needs it

        self._pg = psycopg
        self.conf = configure(self, conf, "store")
        self.url = url
        self._where = url.split("@")[-1]  # never a password in a message
        self._lock = threading.Lock()
        try:
            self._db = psycopg.connect(url, autocommit=True, connect_timeout=self.conf["connect_timeout_s"])
            self._db.execute(f"SET lock_timeout = {int(self.conf['lock_timeout_ms'])}")
            self._open_or_create()
        except psycopg.Error as err:
            raise DatabaseError(f"{self._where}: not a usable fleet database ({_one_line(err)})") from None

    def _open_or_create(self) -> None:
        with self._transaction() as db:
            db.execute("SELECT pg_advisory_xact_lock(%s)", (_SCHEMA_LOCK,))
            tables = {r[0] for r in db.execute("SELECT table_name FROM information_schema.tables "
                                               "WHERE table_schema = current_schema()")}
            if not tables:
                for statement in filter(str.strip, _SCHEMA.split(";")):
                    db.execute(statement)
                db.execute("INSERT INTO meta VALUES ('format_version', %s), ('created', %s)",
                           (str(FORMAT_VERSION), repr(time.time())))
                return
            row = db.execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone() \
                if "meta" in tables else None
        if row is None:
            raise DatabaseError(f"{self._where} is not a fleet database (no format_version)")
        if row[0] != str(FORMAT_VERSION):
            raise DatabaseError(f"{self._where} has format_version {row[0]}; this version reads {FORMAT_VERSION}")

    @contextmanager
    def _transaction(self) -> Iterator[Any]:
        """One write transaction (COMMIT, or ROLLBACK on any error), under the thread lock; integrity errors become
        ``ConfigError``, the server's other errors ``DatabaseError``."""
        pg = self._pg
        with self._lock:
            try:
                with self._db.transaction():
                    yield self._db
            except pg.errors.IntegrityError as err:
                raise ConfigError(f"refused by the fleet database: {_one_line(err)}") from None
            except pg.Error as err:
                raise DatabaseError(f"{self._where}: {_one_line(err)}") from None

    def _read(self, sql: str, args: Sequence[Any] = ()) -> list[tuple]:
        with self._lock:
            try:
                return self._db.execute(sql, args).fetchall()
            except self._pg.Error as err:
                raise DatabaseError(f"{self._where}: {_one_line(err)}") from None

    # -------------------------------------------------------------------------------------------------- keyframes
    def ack_keyframe(self, ack: KeyframeAck, edges: Sequence[EdgeRecord] = ()) -> bool:
        pose = pose_json(ack.pose)
        with self._transaction() as db:
            if not db.execute("SELECT 1 FROM robots WHERE name = %s", (ack.robot,)).fetchone():
                raise ConfigError(f"unknown robot {ack.robot!r}")
            # ON CONFLICT: a replica inserting the same keyframe at the same moment makes this a retry, not an error
            inserted = db.execute("INSERT INTO keyframes VALUES (%s, %s, %s, %s) ON CONFLICT DO NOTHING RETURNING 1",
                                  (ack.robot, int(ack.keyframe), float(ack.timestamp), pose)).fetchone()
            if inserted is None:
                old = db.execute("SELECT timestamp, pose FROM keyframes WHERE robot = %s AND keyframe = %s",
                                 (ack.robot, int(ack.keyframe))).fetchone()
                if tuple(old) != (float(ack.timestamp), pose):
                    raise ConflictError(f"robot {ack.robot!r} sent keyframe {ack.keyframe} before, with other content")
                return False
            self._insert_edges(db, edges)
        return True

    # ------------------------------------------------------------------------------------------------------ edges
    @staticmethod
    def _insert_edges(db: Any, edges: Sequence[EdgeRecord]) -> None:
        rows = SQLStore._edge_rows(edges)
        if rows:
            with db.cursor() as cur:
                cur.executemany("INSERT INTO edges (kind, robot_a, keyframe_a, robot_b, keyframe_b, sim3, score) "
                                "VALUES (%s, %s, %s, %s, %s, %s, %s)", rows)

    def edges(self, kind: str | None = None, robot: str | None = None) -> list[EdgeRecord]:
        rows = self._read("SELECT kind, robot_a, keyframe_a, robot_b, keyframe_b, sim3, score FROM edges "
                          "WHERE (%(k)s::text IS NULL OR kind = %(k)s) "
                          "AND (%(r)s::text IS NULL OR robot_a = %(r)s OR robot_b = %(r)s) ORDER BY id",
                          {"k": kind, "r": robot})
        return loadable(rows, lambda r: EdgeRecord(*r[:5], sim3_from_json(r[5]), r[6]), "edge")

    # ------------------------------------------------------------------------------------- overlaps, transforms
    def add_overlap(self, overlap: OverlapRecord) -> None:
        with self._transaction() as db:
            db.execute('INSERT INTO "overlaps" (robot_a, robot_b, sim3, matches, accepted) VALUES (%s, %s, %s, %s, %s) '
                       "ON CONFLICT (robot_a, robot_b) DO UPDATE SET sim3 = EXCLUDED.sim3, "
                       "matches = EXCLUDED.matches, accepted = EXCLUDED.accepted, seq = DEFAULT",
                       (overlap.robot_a, overlap.robot_b, sim3_json(overlap.transform), int(overlap.matches),
                        float(overlap.accepted)))

    def set_transforms(self, transforms: dict[str, Sim3]) -> None:
        now = time.time()
        with self._transaction() as db:
            # replicas' optimisers replace the set at once: one after the other (readers are not blocked), else the
            # second one's DELETE misses the first one's new rows and its INSERT collides with them
            db.execute("LOCK TABLE transforms IN SHARE ROW EXCLUSIVE MODE")
            db.execute("DELETE FROM transforms")
            if transforms:
                with db.cursor() as cur:
                    cur.executemany("INSERT INTO transforms (robot, sim3, updated) VALUES (%s, %s, %s)",
                                    [(robot, sim3_json(T), now) for robot, T in transforms.items()])



def _one_line(err: Exception) -> str:
    """A psycopg error's first line."""
    return (str(err).strip().splitlines() or [type(err).__name__])[0]
