"""A code index on Milvus (``index.name: milvus``), and the one home of the Milvus client's setup (``milvus_client``,
``serve_lite``: also used by the fleet's shared place memory, ``cae_lcd.fleet.places.MilvusPlaces``).

The same ``CodeIndex`` interface as the faiss indexes (``retrieval.index``): ``add`` appends codes whose positions
continue from ``ntotal``, ``search`` returns ``D (nq, k)`` inner products and ``I (nq, k)`` positions with ``-1``
padding. Exact search (a ``FLAT`` index, inner-product metric, strong consistency: a code is searchable as soon as
``add`` returns). The client is pymilvus: ``uri`` a local file runs milvus-lite embedded, ``http://HOST:19530`` a
Milvus server; with ``uri`` empty, a private milvus-lite file in a temporary folder (deleted on ``close``). Reopening
an existing collection continues it (``ntotal`` = the rows stored); one process writes a collection at a time.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from cae_lcd.core.conf import ConfigError, Int, Text, configure

from .index import INDEXES, CodeIndex

__all__ = ["MilvusIndex", "milvus_client", "serve_lite", "is_server_uri", "LITE_BUFFER_KB", "COLLECTION_NAME"]

log = logging.getLogger(__name__)

_LITE_BUFFER = "MILVUS_LITE_MEMTABLE_MEMORY_LIMIT_BYTES"  #: milvus-lite's buffer size (bytes), from the environment
COLLECTION_NAME = r"[A-Za-z_][A-Za-z0-9_]{0,254}"  #: what Milvus accepts as a collection name
LITE_BUFFER_KB = 256  #: milvus-lite's insert buffer by default (see ``MilvusIndex.default_conf``)


def _set_lite_buffer(lite_buffer_kb: int) -> None:
    """milvus-lite reads its buffer size from the environment when imported (a user's own setting wins)."""
    os.environ.setdefault(_LITE_BUFFER, str(int(lite_buffer_kb) * 1024))


def is_server_uri(uri: str) -> bool:
    """True for a URI a Milvus server (or a hosted milvus-lite) answers on (``http://``, ``https://``, ...), False for
    a milvus-lite folder path."""
    return "://" in uri


def milvus_client(uri: str, lite_buffer_kb: int = LITE_BUFFER_KB) -> Any:
    """A ``pymilvus.MilvusClient`` on ``uri``: a Milvus server (``http://HOST:19530``, or a milvus-lite another process
    serves), or a milvus-lite folder, then served by this process (``serve_lite``; ``lite_buffer_kb`` its insert
    buffer, taken by the first milvus-lite of the process)."""
    from pymilvus import MilvusClient  # here: only Milvus users need it

    return MilvusClient(uri if is_server_uri(uri) else serve_lite(uri, lite_buffer_kb))


def serve_lite(path: str | Path, lite_buffer_kb: int = LITE_BUFFER_KB) -> str:
    """Serves the milvus-lite folder ``path`` from this process (a gRPC server in background threads, on loopback)
    and returns its URI ``http://127.0.0.1:PORT``: every process of this machine reaches it with the
    ``milvus_client`` it would use for a Milvus server. Serving the same folder again returns the same URI.

    Raises:
        ConfigError: milvus-lite could not serve it (its log says why).
    """
    _set_lite_buffer(lite_buffer_kb)
    from milvus_lite.server_manager import server_manager_instance

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    uri = server_manager_instance.start_and_get_uri(str(path))
    if not uri:
        raise ConfigError(f"milvus-lite could not serve {path}")
    return uri


@INDEXES.register("milvus")
class MilvusIndex(CodeIndex):
    """Exact inner-product search in a Milvus collection (see the module doc)."""

    default_conf: dict[str, Any] = {
        "name": "milvus",
        "uri": "",  # a milvus-lite folder (e.g. state/codes.db), http://host:19530 for a server; "": a private one
        "collection": "",  # collection name (letters, digits, _); "": a new unique one
        "batch": 1000,  # codes per insert request
        "lite_buffer_kb": LITE_BUFFER_KB,  # milvus-lite only: inserted rows buffered before they become a segment
        #   (it searches its buffer row by row in Python: 72 ms a query at 300 4096-d rows with its default 128 MB,
        #   19 ms with 256 kB; read once per process, by the first milvus-lite index)
    }
    conf_rules: dict[str, Any] = {"uri": Text(), "collection": Text(f"({COLLECTION_NAME})?"),
                                  "batch": Int(1, 100_000), "lite_buffer_kb": Int(16, 1_048_576)}
    save_with_store = False  # the collection lives in Milvus; a keyframe store's resume adds its codes again
    exact_codes = False  # not read back from Milvus: a place memory keeps its own copy

    def __init__(self, dim: int, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "index")
        self.dim = int(dim)
        self.collection = self.conf["collection"] or f"codes_{uuid.uuid4().hex}"
        self._tmp = None if self.conf["uri"] else Path(tempfile.mkdtemp(prefix="milvus-"))
        self.client = milvus_client(self.conf["uri"] or str(self._tmp / "codes.db"), self.conf["lite_buffer_kb"])
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    def _open(self) -> None:
        """Creates the collection (id, vector; FLAT, IP) or continues an existing one of the same dimension."""
        c = self.client
        if c.has_collection(self.collection):
            field = next(f for f in c.describe_collection(self.collection)["fields"] if f["name"] == "vector")
            if int(field["params"]["dim"]) != self.dim:
                raise ConfigError(f"Milvus collection {self.collection!r} holds {field['params']['dim']}-d codes; "
                                  f"this index has {self.dim}")
            c.load_collection(self.collection)
            self._ntotal = int(c.query(self.collection, filter="", output_fields=["count(*)"])[0]["count(*)"])
            return
        schema = c.create_schema(auto_id=False, enable_dynamic_field=False)
        schema.add_field("id", _datatype().INT64, is_primary=True)
        schema.add_field("vector", _datatype().FLOAT_VECTOR, dim=self.dim)
        index = c.prepare_index_params()
        index.add_index(field_name="vector", index_type="FLAT", metric_type="IP")
        c.create_collection(self.collection, schema=schema, index_params=index, consistency_level="Strong")
        self._ntotal = 0

    @property
    def ntotal(self) -> int:
        return self._ntotal

    def add(self, xb: np.ndarray) -> None:
        """Appends ``(n, d)`` codes; their positions continue from ``ntotal``."""
        xb = np.ascontiguousarray(xb, np.float32).reshape(-1, self.dim)
        for start in range(0, len(xb), self.conf["batch"]):
            chunk = xb[start:start + self.conf["batch"]]
            first = self._ntotal + start
            self.client.insert(self.collection, [{"id": first + i, "vector": v} for i, v in enumerate(chunk.tolist())])
        self._ntotal += len(xb)

    def search(self, xq: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-``k`` by inner product: ``D (nq, k)`` float32, ``I (nq, k)`` int64 (``-1`` and ``-inf`` padding)."""
        xq = np.ascontiguousarray(xq, np.float32).reshape(-1, self.dim)
        k = max(int(k), 0)
        D = np.full((len(xq), k), -np.inf, np.float32)
        I = np.full((len(xq), k), -1, np.int64)
        if len(xq) == 0 or k == 0 or self._ntotal == 0:
            return D, I
        hits = self.client.search(self.collection, data=xq.tolist(), limit=min(k, self._ntotal),
                                  output_fields=["id"], search_params={"metric_type": "IP"})
        for q, row in enumerate(hits):
            row = sorted(row, key=lambda h: (-h["distance"], h["id"]))  # ties: lower position first, like faiss
            D[q, :len(row)] = [h["distance"] for h in row]
            I[q, :len(row)] = [h["id"] for h in row]
        return D, I

    def bytes_per_code(self) -> float:
        """Float32 codes: 4 bytes per dimension (stored by Milvus, not in this process)."""
        return 4.0 * self.dim

    def close(self) -> None:
        """Closes the client; a private temporary folder is no longer served, and deleted."""
        self.client.close()
        if self._tmp is not None:
            from milvus_lite.server_manager import server_manager_instance

            server_manager_instance.release_server(str(self._tmp / "codes.db"))
            shutil.rmtree(self._tmp, ignore_errors=True)


def _datatype() -> Any:
    """pymilvus's ``DataType`` (imported on first use)."""
    from pymilvus import DataType

    return DataType
