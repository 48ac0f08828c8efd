"""A write-ahead log beside the keyframe store: each frame is appended here first (one ``write`` call, no HDF5),
and moved into the store's columns a block at a time (``retrieval.database``).

Writing a frame's dozen HDF5 columns one row at a time cost ~4.5 ms a frame (h5py's per-call overhead, and a
gzip chunk recompressed on every append); the log costs one ``os.write`` of a few kB. A record is::

    magic b"KFL1" | payload length (u32 LE) | BLAKE2b-128 of the payload | payload
    payload = header length (u32 LE) | header (JSON: metadata, and each array's name, dtype and shape) | array bytes

A kill at any moment leaves whole records followed at most by one torn record: ``read_records`` stops at the first
record that is short or fails its checksum (what follows it is never used), so a resumed run sees exactly the
frames whose record was complete. Like the store's own flush, a record is in the operating system's hands once
``append`` returns (it survives a killed process, not a power cut).

    >>> log = FrameLog(path)                                       # doctest: +SKIP
    >>> log.append({"frame_id": 3}, {"code": np.zeros(4, np.float16)})  # doctest: +SKIP
    >>> [meta["frame_id"] for meta, arrays in read_records(path)]  # doctest: +SKIP
    [3]
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Iterator

import numpy as np

__all__ = ["FrameLog", "encode_record", "decode_record", "read_records", "MAGIC"]

MAGIC = b"KFL1"  #: the first bytes of every record
_HEAD = len(MAGIC) + 4 + 16  # magic, payload length, digest
_MAX_HEADER = 1 << 20  #: a record header longer than this is damage, not a frame


def encode_record(meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> bytes:
    """One record: JSON-able ``meta`` and named arrays (any shape; dtype kept), framed and checksummed."""
    blobs = [np.ascontiguousarray(a) for a in arrays.values()]
    header = json.dumps({"meta": meta, "arrays": [[k, a.dtype.str, list(a.shape)]
                                                   for k, a in zip(arrays, blobs)]}).encode()
    payload = b"".join([len(header).to_bytes(4, "little"), header, *(a.tobytes() for a in blobs)])
    digest = hashlib.blake2b(payload, digest_size=16).digest()
    return MAGIC + len(payload).to_bytes(4, "little") + digest + payload


def decode_record(payload: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``(meta, arrays)`` of a checked payload (``read_records`` gives them).

    Raises:
        ValueError: the payload does not hold what its header says.
    """
    size = int.from_bytes(payload[:4], "little")
    if size > min(_MAX_HEADER, len(payload) - 4):
        raise ValueError("record header longer than the record")
    header = json.loads(payload[4:4 + size])
    arrays, pos = {}, 4 + size
    for name, dtype, shape in header["arrays"]:
        dt = np.dtype(dtype)
        if dt.hasobject:
            raise ValueError("object arrays are not stored")
        n = dt.itemsize * int(np.prod(shape))
        if pos + n > len(payload):
            raise ValueError("record shorter than its arrays")
        arrays[name] = np.frombuffer(payload, dt, int(np.prod(shape)), pos).reshape(shape)
        pos += n
    return header["meta"], arrays


def read_records(path: Path) -> Iterator[tuple[dict[str, Any], dict[str, np.ndarray]]]:
    """The complete records of the log at ``path`` in order (none when it does not exist); stops at the first torn
    or damaged one."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return
    pos = 0
    while pos + _HEAD <= len(data) and data[pos:pos + len(MAGIC)] == MAGIC:
        size = int.from_bytes(data[pos + 4:pos + 8], "little")
        payload = data[pos + _HEAD:pos + _HEAD + size]
        if len(payload) != size or hashlib.blake2b(payload, digest_size=16).digest() != data[pos + 8:pos + _HEAD]:
            return
        try:
            yield decode_record(payload)
        except (ValueError, KeyError, TypeError, json.JSONDecodeError):
            return
        pos += _HEAD + size


class FrameLog:
    """The append side of a log file (created when missing; appends go to its end).

    Args:
        path: the log file.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)

    def append(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        """Appends one record (``encode_record``) in one ``write``.

        Raises:
            OSError: the write failed or was short (e.g. the disk is full).
        """
        data = encode_record(meta, arrays)
        if os.write(self._fd, data) != len(data):
            raise OSError(f"short write to {self.path}")

    def clear(self) -> None:
        """Empties the log (its records are safely elsewhere)."""
        os.ftruncate(self._fd, 0)

    def close(self, remove: bool = False) -> None:
        """Closes the file; ``remove`` deletes it (only when it is empty: nothing would be lost)."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
            if remove and self.path.exists() and self.path.stat().st_size == 0:
                self.path.unlink()
