"""The fleet's place memory across robots: every robot's searched keyframe entries, each keyed by ``(robot,
keyframe)``, searched for the most similar entries of the *other* robots. Two kinds behind one interface, picked by
``recognition.places.name`` (``FLEET_PLACES``)::

    entry = places.entry(code)           # a keyframe's raw code (``FrameResult.code``) -> its entry here, in the
                                         # memory's one fixed whitening (the weights'), whatever its robot's
                                         # detector searches with (a detector calibrating online refits its own)
    places.add(robot, keyframes (n,), entries (n, d))   # a key already held is not held twice
    places.search(robot, entry (d,), k)  # {other robot: (keyframes (m,) int64, scores (m,) float32)}, best first:
                                         # the k entries most similar to ``entry`` of robots other than ``robot``
    (robot, keyframe) in places; len(places); places.shared; places.close()

- ``local`` (``LocalPlaces``, the embedded default): a ``retrieval.places`` memory in this process (the detectors'
  own kind, built by ``create_places``: codes in a faiss index, ``index``; MILD hashes), with no recency exclusion
  (another robot's frame is never "recent"). Each process holds its own (``shared`` False): Ray workers copy every
  keyframe's entry to each other (``FleetRecognizer.export`` -> ``adopt``).
- ``milvus`` (``MilvusPlaces``): one Milvus collection ``(key, robot, keyframe, vector)`` shared by every process
  connected to it (``shared`` True): an entry is inserted once, by the worker that owns its robot, and every worker
  searches all robots' entries. The primary key is ``"ROBOT:KEYFRAME"``, so an insert is an upsert (two replicas, a
  re-sent keyframe, a restarted worker adding its robots again: never a duplicate); the collection has strong
  consistency (an entry is searchable as soon as ``add`` returns); the search leaves the querying robot out with the
  filter ``robot != "NAME"``, built only from a checked robot name (``cae_lcd.fleet.store.ROBOT_NAME``: letters, digits,
  ``_``, ``-``; nothing that could end the string). ``uri``: a Milvus server (``http://HOST:19530``), a milvus-lite
  folder, or empty: the milvus-lite folder ``STATE/places.db``. A milvus-lite folder is served by one process
  (``retrieval.milvus_index.serve_lite``: this one, or for Ray workers a named actor, ``cae_lcd.fleet.workers``, that gives
  them its ``http://127.0.0.1:PORT``: the workers of one machine).
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from cae_lcd.core.conf import ConfigError, Int, Registry, Text, configure, merge_conf
from retrieval.descriptors import GlobalDescriptor
from retrieval.detector import resolve_conf
from retrieval.milvus_index import COLLECTION_NAME, LITE_BUFFER_KB, MilvusIndex, is_server_uri, milvus_client
from retrieval.places import Places, code_entry, create_places

from .store import check_robot_name

__all__ = ["FleetPlaces", "LocalPlaces", "MilvusPlaces", "FLEET_PLACES", "create_fleet_places", "resolve_places",
           "LITE_FOLDER"]

log = logging.getLogger(__name__)

LITE_FOLDER = "places.db"  #: the milvus-lite folder of ``MilvusPlaces`` in the state folder (``uri`` empty)
MAX_LIMIT = 16_384  #: the most hits one Milvus search returns (Milvus's topk limit)


def _appears(check: Any, seconds: float = 10.0) -> bool:
    """Polls ``check()`` until it is true (another worker creating the same collection: milvus-lite makes its folder
    before the collection is listed) or ``seconds`` pass."""
    deadline = time.monotonic() + seconds
    while not check():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


class FleetPlaces:
    """Base of the fleet's place memories (see the module doc).

    Args (every kind): descriptor, whitening: the detectors' (they decide what an entry is); detector_conf: a
    resolved detector conf; conf: this kind's resolved conf (``resolve_places``); state_dir: the server's state folder.
    """

    default_conf: dict[str, Any] = {}
    conf_rules: dict[str, Any] = {}
    shared = False  #: True: every process connected to the memory sees every entry (each inserted once)

    @classmethod
    def resolve(cls, conf: Mapping[str, Any] | None) -> dict[str, Any]:
        """``conf`` merged onto ``default_conf`` and checked."""
        return configure(cls, conf, "recognition.places")

    @classmethod
    def lite_path(cls, conf: dict[str, Any], state_dir: str | Path) -> Path | None:
        """The milvus-lite folder that one process must serve to every worker (``cae_lcd.fleet.workers``); None: none."""
        return None

    def entry(self, code: np.ndarray) -> np.ndarray:
        """A keyframe's entry in this memory from its raw code (``(D,)``; MILD: its descriptors): in the memory's
        own fixed whitening (``retrieval.places.code_entry``), so that every robot's entries share one code space."""
        raise NotImplementedError

    def add(self, robot: str, keyframes: Any, entries: Any) -> None:
        """Holds the robot's ``keyframes (n,)`` with their searched ``entries`` (``(n, d)``, one per keyframe); a key
        already held is held once.

        Raises:
            ConfigError: a name that is not a robot's (``cae_lcd.fleet.store.ROBOT_NAME``), counts that differ.
        """
        raise NotImplementedError

    def search(self, robot: str, entry: np.ndarray, k: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The ``k`` entries most similar to ``entry (d,)`` of the robots other than ``robot``.

        Returns:
            ``{other robot: (keyframes (m,) int64, scores (m,) float32)}``, best first.

        Raises:
            ConfigError: a name that is not a robot's.
        """
        raise NotImplementedError

    def remove(self, robot: str) -> None:
        """Forgets every entry of ``robot`` (an admin's reset); its keyframe ids may be held again."""
        raise NotImplementedError

    def __contains__(self, key: object) -> bool:
        """True when ``(robot, keyframe)`` is held."""
        raise NotImplementedError

    def __len__(self) -> int:
        """Entries held (all robots')."""
        raise NotImplementedError

    def close(self) -> None:
        """Releases what the memory holds (a connection)."""


FLEET_PLACES: Registry[FleetPlaces] = Registry("fleet place memory")


def _grouped(hits: list[tuple[str, int, float]]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``[(robot, keyframe, score)]`` best first -> ``{robot: (keyframes (m,) int64, scores (m,) float32)}``."""
    out: dict[str, tuple[list[int], list[float]]] = {}
    for robot, keyframe, score in hits:
        found = out.setdefault(robot, ([], []))
        found[0].append(int(keyframe))
        found[1].append(float(score))
    return {r: (np.asarray(kf, np.int64), np.asarray(s, np.float32)) for r, (kf, s) in out.items()}


def _rows(keyframes: Any, entries: Any, dim: int | None = None) -> tuple[list[int], Any]:
    """Keyframe ids as ints, and their entries: a list of one entry each, or (``dim`` given) an ``(n, dim)`` float32
    matrix.

    Raises:
        ConfigError: counts that differ, or (``dim`` given) entries that are not ``(n, dim)`` finite numbers.
    """
    ids = [int(k) for k in np.asarray(keyframes).reshape(-1).tolist()]
    if dim is None:
        rows = list(entries)
        if len(rows) != len(ids):
            raise ConfigError(f"{len(ids)} keyframes with {len(rows)} entries")
        return ids, rows
    matrix = np.asarray(entries, np.float32)
    if matrix.shape != (len(ids), dim) or not np.isfinite(matrix).all():
        raise ConfigError(f"{len(ids)} keyframes with entries of shape {matrix.shape} (expected ({len(ids)}, {dim}), "
                          "finite)")
    return ids, matrix


@FLEET_PLACES.register("local")
class LocalPlaces(FleetPlaces):
    """Every robot's entries in a ``retrieval.places`` memory of this process (see the module doc). A query is
    registered in the memory's similarity table by its search and forgotten right after (``Places.undo``), so the
    memory holds each entry once, in its index; what stays here per keyframe is its key."""

    default_conf: dict[str, Any] = {
        "name": "local",
        "index": {"name": "fp16"},  # its code index (retrieval.index; fp16: exact for the float16-rounded entries,
        #                             half of flat's memory)
    }

    @classmethod
    def resolve(cls, conf: Mapping[str, Any] | None) -> dict[str, Any]:
        """``conf`` merged onto ``default_conf``; ``index`` checked by the index's own rules (as a detector's)."""
        merged = merge_conf(cls.default_conf, conf, "recognition.places", strict=False)
        if set(merged) != {"name", "index"}:
            raise ConfigError(f"recognition.places (local) has only 'index'; got {sorted(set(merged) - {'name'})}")
        index = resolve_conf({"index": merged["index"]})["index"]
        if index["name"] == MilvusIndex.default_conf["name"]:
            raise ConfigError("recognition.places.index: milvus would be a private collection in each process; for "
                              "one Milvus place memory shared by every worker set recognition.places.name: milvus")
        return {"name": "local", "index": index}

    def __init__(self, descriptor: GlobalDescriptor, whitening: Any, detector_conf: dict[str, Any],
                 conf: dict[str, Any], state_dir: str | Path | None = None) -> None:
        search = {**detector_conf["search"], "exclude_recent": 0, "exclude_recent_s": None}
        self.places: Places = create_places(descriptor, whitening, {**detector_conf, "search": search,
                                                                    "index": conf["index"]})
        self.keys: list[tuple[str, int]] = []  # place id -> (robot, keyframe)
        self._known: set[tuple[str, int]] = set()
        self._own: Counter[str] = Counter()  # entries per robot
        self._removed = 0  # entries of removed robots still in the index (``remove``)

    def __len__(self) -> int:
        return len(self.keys)

    def entry(self, code: np.ndarray) -> np.ndarray:
        return self.places.entry(code)

    def __contains__(self, key: object) -> bool:
        return key in self._known

    def add(self, robot: str, keyframes: Any, entries: Any) -> None:
        """Inserts keyframes' searched entries (``(n, d)`` codes, or a list of MILD's descriptors: one a keyframe)."""
        check_robot_name(robot)
        for keyframe, entry in zip(*_rows(keyframes, entries)):
            key = (robot, keyframe)
            if key not in self._known:
                self.places.insert(len(self.keys), entry, None)
                self.keys.append(key)
                self._known.add(key)
                self._own[robot] += 1

    def remove(self, robot: str) -> None:
        """The robot's entries stay in the index (it cannot delete) but are no longer keys: never returned, counted
        among the removed ones that a search asks for beyond its ``k``."""
        for pid, key in enumerate(self.keys):
            if key[0] == robot:
                self._known.discard(key)
                self.keys[pid] = ("", -1)
                self._removed += 1
        self._own.pop(robot, None)

    def search(self, robot: str, entry: np.ndarray, k: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The ``k`` entries most similar to ``entry`` of the other robots (the memory's top ``k`` + the robot's own
        count + the removed ones, those then left out: exact for an exact index), grouped by robot, best first."""
        check_robot_name(robot)
        query = len(self.keys)  # the id the next entry would take: registered by the search, then forgotten
        wanted = int(k) + self._own[robot] + self._removed
        scores, ids = self.places.search(query, entry, None, max(1, min(wanted, len(self.keys))))
        self.places.undo(query)
        hits = [(*self.keys[pid], score) for score, pid in zip(scores.tolist(), ids.tolist())
                if pid >= 0 and self.keys[pid][0] not in (robot, "")]
        return _grouped(hits[:max(int(k), 0)])


@FLEET_PLACES.register("milvus")
class MilvusPlaces(FleetPlaces):
    """One Milvus collection of every robot's entries, shared by every process connected to it (see the module doc).

    Raises:
        ConfigError: a descriptor compared by hashing, a collection of another layout or dimension.
    """

    default_conf: dict[str, Any] = {
        "name": "milvus",
        "uri": "",  # http://HOST:19530: a Milvus server; a milvus-lite folder; "": STATE/places.db (milvus-lite)
        "collection": "fleet_places",  # the collection (letters, digits, _): one a fleet on a shared server
        "batch": 1000,  # entries per upsert request
        "lite_buffer_kb": LITE_BUFFER_KB,  # milvus-lite only: its insert buffer (retrieval.milvus_index)
    }
    conf_rules: dict[str, Any] = {"uri": Text(), "collection": Text(COLLECTION_NAME), "batch": Int(1, 100_000),
                                  "lite_buffer_kb": MilvusIndex.conf_rules["lite_buffer_kb"]}
    shared = True
    FIELDS = ("key", "robot", "keyframe", "vector")  #: the collection's fields

    @classmethod
    def lite_path(cls, conf: dict[str, Any], state_dir: str | Path) -> Path | None:
        return None if is_server_uri(conf["uri"]) else Path(conf["uri"] or Path(state_dir) / LITE_FOLDER).resolve()

    def __init__(self, descriptor: GlobalDescriptor, whitening: Any, detector_conf: dict[str, Any],
                 conf: dict[str, Any], state_dir: str | Path | None = None) -> None:
        if descriptor.searched_by != "cosine":
            raise ConfigError(f"the {descriptor.conf['name']!r} descriptor is compared by hashing: the fleet's Milvus "
                              "place memory holds codes (set recognition.places.name: local)")
        self.conf = self.resolve(conf)
        self.dim = int(descriptor.dim if whitening is None else whitening.dim)
        self.whitening = whitening
        self.collection = self.conf["collection"]
        uri = self.conf["uri"] or str(Path(state_dir or ".") / LITE_FOLDER)
        self.client = milvus_client(uri, self.conf["lite_buffer_kb"])
        try:
            self._open()
        except BaseException:
            self.client.close()
            raise

    def _open(self) -> None:
        """Creates the collection, or continues one of this layout and dimension (another worker may create it at
        the same time)."""
        from pymilvus import DataType, MilvusException

        c, name = self.client, self.collection
        if not c.has_collection(name):
            schema = c.create_schema(auto_id=False, enable_dynamic_field=False)
            schema.add_field("key", DataType.VARCHAR, is_primary=True, max_length=96)  # "ROBOT:KEYFRAME"
            schema.add_field("robot", DataType.VARCHAR, max_length=64)
            schema.add_field("keyframe", DataType.INT64)
            schema.add_field("vector", DataType.FLOAT_VECTOR, dim=self.dim)
            index = c.prepare_index_params()
            index.add_index(field_name="vector", index_type="FLAT", metric_type="IP")
            try:
                c.create_collection(name, schema=schema, index_params=index, consistency_level="Strong")
                return
            except MilvusException:
                if not _appears(lambda: c.has_collection(name)):  # not a creation raced by another worker
                    raise
        fields = {f["name"]: f for f in c.describe_collection(name)["fields"]}
        if tuple(sorted(fields)) != tuple(sorted(self.FIELDS)):
            raise ConfigError(f"Milvus collection {name!r} has the fields {sorted(fields)}, not a fleet place "
                              f"memory's {sorted(self.FIELDS)}: choose another recognition.places.collection")
        if int(fields["vector"]["params"]["dim"]) != self.dim:
            raise ConfigError(f"Milvus collection {name!r} holds {fields['vector']['params']['dim']}-d entries; this "
                              f"fleet's are {self.dim}-d")
        c.load_collection(name)

    def entry(self, code: np.ndarray) -> np.ndarray:
        return code_entry(code, self.whitening)

    def add(self, robot: str, keyframes: Any, entries: np.ndarray) -> None:
        """Upserts keyframes' ``(n, d)`` entries: searchable by every process when this returns."""
        check_robot_name(robot)
        ids, rows = _rows(keyframes, entries, self.dim)
        data = [{"key": f"{robot}:{k}", "robot": robot, "keyframe": k, "vector": v}
                for k, v in zip(ids, rows.tolist())]
        for start in range(0, len(data), self.conf["batch"]):
            self.client.upsert(self.collection, data[start:start + self.conf["batch"]])

    def search(self, robot: str, entry: np.ndarray, k: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The ``k`` (at most ``MAX_LIMIT``) entries most similar to ``entry`` of the other robots, grouped by robot,
        best first (ties: by robot, then keyframe)."""
        filter_ = f'robot != "{check_robot_name(robot)}"'  # a checked name: nothing in it can end the string
        query = np.asarray(entry, np.float32).reshape(1, self.dim).tolist()
        hits = self.client.search(self.collection, data=query, limit=max(1, min(int(k), MAX_LIMIT)), filter=filter_,
                                  output_fields=["robot", "keyframe"], search_params={"metric_type": "IP"})[0]
        found = sorted(((h["entity"]["robot"], int(h["entity"]["keyframe"]), float(h["distance"])) for h in hits),
                       key=lambda h: (-h[2], h[0], h[1]))
        return _grouped(found[:max(int(k), 0)])

    def remove(self, robot: str) -> None:
        """Deletes the robot's entries from the collection."""
        self.client.delete(self.collection, filter=f'robot == "{check_robot_name(robot)}"')

    def __contains__(self, key: object) -> bool:
        if not (isinstance(key, tuple) and len(key) == 2 and isinstance(key[1], (int, np.integer))):
            return False
        try:
            robot = check_robot_name(key[0])
        except ConfigError:
            return False
        return bool(self.client.get(self.collection, ids=[f"{robot}:{int(key[1])}"], output_fields=["keyframe"]))

    def __len__(self) -> int:
        return int(self.client.query(self.collection, filter="", output_fields=["count(*)"])[0]["count(*)"])

    def close(self) -> None:
        """Closes the client (the collection stays, in Milvus)."""
        self.client.close()


def resolve_places(conf: Mapping[str, Any] | None) -> dict[str, Any]:
    """The fleet place memory's conf (``recognition.places``) resolved by its kind's rules (``name``: local, milvus).

    Raises:
        ConfigError: an unknown kind or key, a bad value.
    """
    if conf is not None and not isinstance(conf, Mapping):
        raise ConfigError(f"config section 'recognition.places' must be a mapping, got {type(conf).__name__}")
    return FLEET_PLACES.get((conf or {}).get("name", LocalPlaces.default_conf["name"])).resolve(conf)


def create_fleet_places(descriptor: GlobalDescriptor, whitening: Any, detector_conf: dict[str, Any],
                        conf: dict[str, Any], state_dir: str | Path) -> FleetPlaces:
    """The place memory ``conf`` names (resolved by ``resolve_places``), for the detectors' ``descriptor`` and
    ``whitening``."""
    return FLEET_PLACES.get(conf["name"])(descriptor, whitening, detector_conf, conf, state_dir)
