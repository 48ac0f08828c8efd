"""A throwaway PostgreSQL server in a temporary folder, for the tests and the benchmarks of ``cae_lcd.fleet.postgres``.

``initdb``/``pg_ctl`` from PATH; the server listens on a unix socket in its folder only (no TCP), trusts local
connections, and is stopped and deleted on ``stop``. PostgreSQL refuses to run as root: as root, the folder is given
to the ``postgres`` user and the tools run through ``runuser -u postgres``.

    >>> with LocalPostgres() as pg:               # doctest: +SKIP
    ...     url = pg.create_database("t1")        # postgresql:///t1?host=/tmp/pg-xxx&user=postgres
"""

from __future__ import annotations

import logging
import os
import pwd
import shutil
import subprocess
import tempfile
from pathlib import Path

from cae_lcd.core.errors import DatabaseError

__all__ = ["LocalPostgres", "postgres_available"]

log = logging.getLogger(__name__)

_USER = "postgres"  #: the user the server runs as when we are root


def postgres_available() -> str | None:
    """None when a local server can be started here, else why not (one line)."""
    missing = [tool for tool in ("initdb", "pg_ctl", "postgres") if shutil.which(tool) is None]
    if missing:
        return f"PostgreSQL is not on PATH (no {', '.join(missing)})"
    if os.geteuid() == 0:
        try:
            pwd.getpwnam(_USER)
        except KeyError:
            return f"running as root and there is no {_USER!r} user to run PostgreSQL as"
        if shutil.which("runuser") is None:
            return "running as root and runuser is not on PATH"
    return None


class LocalPostgres:
    """A PostgreSQL server of its own in a temporary folder, listening on a unix socket there.

    Raises:
        DatabaseError: PostgreSQL is not available or did not start (the reason in one line).
    """

    def __init__(self) -> None:
        why = postgres_available()
        if why:
            raise DatabaseError(why)
        self.root = Path(tempfile.mkdtemp(prefix="pg-", dir="/tmp"))  # short: a socket path has < 108 bytes
        self.data = self.root / "data"
        self._as_root = os.geteuid() == 0
        self.user = _USER if self._as_root else pwd.getpwuid(os.geteuid()).pw_name
        if self._as_root:
            entry = pwd.getpwnam(_USER)
            os.chown(self.root, entry.pw_uid, entry.pw_gid)
        try:
            self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", self.user, "--no-sync", "-E", "UTF8")
            options = f"-c listen_addresses='' -c unix_socket_directories={self.root} -c fsync=on -k {self.root}"
            self._run("pg_ctl", "-D", str(self.data), "-l", str(self.root / "log"), "-o", options, "-w", "-t", "60",
                      "start")
        except DatabaseError:
            shutil.rmtree(self.root, ignore_errors=True)
            raise

    def _run(self, *cmd: str) -> None:
        full = (["runuser", "-u", _USER, "--"] if self._as_root else []) + list(cmd)
        done = subprocess.run(full, capture_output=True, text=True, timeout=120)
        if done.returncode != 0:
            tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
            raise DatabaseError(f"{cmd[0]} failed: {tail[0]}")

    def url(self, database: str = "postgres") -> str:
        """The libpq URL of ``database`` on this server (through its socket)."""
        return f"postgresql:///{database}?host={self.root}&user={self.user}"

    def create_database(self, name: str) -> str:
        """Creates an empty database ``name`` (letters, digits, underscores) and returns its URL."""
        import psycopg

        if not name.replace("_", "").isalnum():
            raise DatabaseError(f"a database name must be letters, digits and underscores; got {name!r}")
        with psycopg.connect(self.url(), autocommit=True) as db:
            db.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def stop(self) -> None:
        """Stops the server (immediate shutdown: it is thrown away) and deletes its folder."""
        try:
            self._run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop")
        except (DatabaseError, subprocess.TimeoutExpired) as err:
            log.warning("stopping the local PostgreSQL: %s", err)
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> "LocalPostgres":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
