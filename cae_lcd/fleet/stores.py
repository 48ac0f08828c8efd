"""Which ``FleetStore`` a location names: a ``postgresql://`` URL is a ``PostgresStore`` (shared by replicas and
workers), anything else (or nothing) the embedded ``SQLiteStore`` file ``fleet.sqlite`` under the state folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .postgres import PostgresStore, is_postgres_url
from .store import FleetStore, SQLiteStore

__all__ = ["open_store", "SQLITE_NAME"]

SQLITE_NAME = "fleet.sqlite"  #: the embedded store's file in the state folder


def open_store(state_dir: str | Path, location: str | None = None, conf: dict[str, Any] | None = None) -> FleetStore:
    """The store at ``location``: a ``postgresql://`` URL, a SQLite file path, or None (``STATE/fleet.sqlite``).

    Raises:
        ConfigError: a bad conf. DatabaseError: a damaged, foreign or unreachable store.
    """
    if location and is_postgres_url(location):
        return PostgresStore(location, conf)
    return SQLiteStore(Path(location) if location else Path(state_dir) / SQLITE_NAME, conf)
