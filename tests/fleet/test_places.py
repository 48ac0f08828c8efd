"""cae_lcd.fleet.places: the place memory across robots behind one interface, in this process (``local``: faiss) and in one
Milvus collection shared by processes (``milvus``: milvus-lite served on loopback), on real CAE codes of the bundled
sample; every interface test runs against both kinds."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from cae_lcd.fleet.places import LITE_FOLDER, LocalPlaces, MilvusPlaces, create_fleet_places, resolve_places
from retrieval.detector import resolve_conf

REPO = Path(__file__).resolve().parents[2]
#: robot -> its keyframes (frames of the sample): neighbouring frames look alike, so a robot's own are its best matches
ROBOTS = {"A": [0, 1, 2, 3], "B": [4, 5, 6, 7], "C": [54, 55, 56, 57]}
KINDS = {"local fp16": {"name": "local"}, "local flat": {"name": "local", "index": {"name": "flat"}},
         "milvus": {"name": "milvus"}}
HOSTILE = ['A" or robot != "x', 'A\\', "A\n", "", "x" * 65, "A B", "A'", 7, None]


@pytest.fixture(scope="module")
def entries(cae_descriptor, sample_image):
    """Frame -> ``(4096,)`` searched entry (unit norm, float16-rounded as a detector's ``FrameResult.entry``)."""
    out = {}
    for frames in ROBOTS.values():
        for i in frames:
            code = cae_descriptor(sample_image(i))
            out[i] = np.asarray(code / np.linalg.norm(code), np.float16).astype(np.float32)
    return out


def memory(conf, cae_descriptor, state: Path):
    return create_fleet_places(cae_descriptor, None, resolve_conf(), resolve_places(conf), state)


@pytest.fixture(params=list(KINDS))
def places(request, cae_descriptor, entries, tmp_path):
    """A memory of each kind holding every robot of ``ROBOTS`` (Milvus: milvus-lite in ``tmp_path``)."""
    p = memory(KINDS[request.param], cae_descriptor, tmp_path)
    for robot, frames in ROBOTS.items():
        p.add(robot, frames, np.stack([entries[i] for i in frames]))
    yield p
    p.close()


def brute_force(robot: str, query: np.ndarray, k: int, entries) -> list[tuple[str, int]]:
    """The ``k`` most similar ``(robot, frame)`` of the other robots, by numpy."""
    others = [(r, i) for r, frames in ROBOTS.items() if r != robot for i in frames]
    scores = np.array([entries[i] @ query for _, i in others])
    return [others[j] for j in np.argsort(-scores, kind="stable")[:k]]


class TestInterface:
    def test_the_top_k_of_the_other_robots_best_first(self, places, entries):
        for robot, frame, k in (("A", 1, 1), ("A", 1, 3), ("B", 5, 6), ("C", 55, 20)):
            found = places.search(robot, entries[frame], k)
            assert robot not in found  # its own entries are the most similar, and left out
            got = sorted(((o, int(kf), float(s)) for o, (kfs, ss) in found.items() for kf, s in zip(kfs, ss)),
                         key=lambda h: -h[2])
            assert [(o, kf) for o, kf, _ in got] == brute_force(robot, entries[frame], k, entries)
            for o, kf, s in got:
                assert s == pytest.approx(float(entries[kf] @ entries[frame]), abs=1e-4)
            for kfs, ss in found.values():  # grouped by robot, best first
                assert kfs.dtype == np.int64 and ss.dtype == np.float32 and np.all(np.diff(ss) <= 0)

    def test_a_key_is_held_once(self, places, entries):
        assert len(places) == 12 and ("B", 5) in places and ("B", 54) not in places and ("Z", 0) not in places
        places.add("B", [5, 6], np.stack([entries[5], entries[6]]))  # a re-sent keyframe, another replica's insert
        places.add("B", [5], np.stack([entries[5]]))
        assert len(places) == 12
        found = places.search("A", entries[5], 12)
        assert sorted(found["B"][0].tolist()) == [4, 5, 6, 7]  # each once

    @pytest.mark.parametrize("name", HOSTILE, ids=repr)
    def test_a_hostile_robot_name_is_refused_and_changes_nothing(self, places, entries, name):
        with pytest.raises(ConfigError, match="robot name"):
            places.search(name, entries[1], 5)
        with pytest.raises(ConfigError, match="robot name"):
            places.add(name, [99], np.stack([entries[1]]))
        assert len(places) == 12 and (name, 99) not in places
        assert "A" not in places.search("A", entries[1], 12)  # the filter is intact

    def test_bad_entries_are_refused(self, places, entries):
        with pytest.raises(ConfigError, match="keyframes"):
            places.add("D", [1, 2], np.stack([entries[1]]))
        assert len(places) == 12

    def test_an_empty_memory_finds_nothing(self, cae_descriptor, entries, tmp_path):
        for conf in KINDS.values():
            p = memory(conf, cae_descriptor, tmp_path / conf["name"])
            assert p.search("A", entries[1], 5) == {} and len(p) == 0
            p.add("A", [1], np.stack([entries[1]]))
            assert p.search("A", entries[1], 5) == {}  # only its own
            p.close()


class TestMilvus:
    def test_two_processes_share_one_collection(self, cae_descriptor, entries, tmp_path):
        """One process serves the milvus-lite folder; another connects by its URI: an entry either inserts is found by
        the other's search as soon as the insert returned, and an upsert of the same key keeps one row."""
        from retrieval.milvus_index import serve_lite

        uri = serve_lite(tmp_path / LITE_FOLDER)
        assert uri.startswith("http://127.0.0.1:")
        here = memory({"name": "milvus", "uri": uri}, cae_descriptor, tmp_path)
        here.add("A", [1], np.stack([entries[1]]))
        np.save(tmp_path / "b.npy", np.stack([entries[4], entries[1]]))
        child = f"""
import json, sys, numpy as np
from cae_lcd.fleet.places import create_fleet_places, resolve_places
from retrieval.descriptors import create_descriptor
from retrieval.detector import resolve_conf
p = create_fleet_places(create_descriptor({{"name": "cae"}}), None, resolve_conf(),
                        resolve_places({{"name": "milvus", "uri": {uri!r}}}), ".")
b = np.load({str(tmp_path / "b.npy")!r})
found = p.search("B", b[1], 5)  # A's entry, inserted by the other process
p.add("B", [4], b[:1])
p.add("B", [4], b[:1])  # again: an upsert
print(json.dumps({{o: kf.tolist() for o, (kf, _) in found.items()}}))
"""
        out = subprocess.run([sys.executable, "-c", child], cwd=REPO, capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
        assert json.loads(out.stdout.strip().splitlines()[-1]) == {"A": [1]}
        found = here.search("A", entries[4], 5)  # B's entry, inserted by the child
        assert list(found) == ["B"] and found["B"][0].tolist() == [4]
        assert len(here) == 2 and ("B", 4) in here
        here.close()

    def test_an_in_process_memory_continues_its_folder(self, cae_descriptor, entries, tmp_path):
        """Without a URI the memory is ``STATE/places.db``: reopened, it holds what it held (a restart adds the
        robots' entries again: upserts)."""
        first = memory({"name": "milvus"}, cae_descriptor, tmp_path)
        first.add("A", [1, 2], np.stack([entries[1], entries[2]]))
        first.close()
        assert (tmp_path / LITE_FOLDER).is_dir()
        again = memory({"name": "milvus"}, cae_descriptor, tmp_path)
        again.add("A", [1, 2], np.stack([entries[1], entries[2]]))
        assert len(again) == 2 and again.search("B", entries[1], 1)["A"][0].tolist() == [1]
        again.close()

    def test_a_collection_of_another_layout_is_refused(self, cae_descriptor, tmp_path):
        from retrieval.index import create_index

        uri = str(tmp_path / "x.db")
        create_index(16, {"name": "milvus", "uri": uri, "collection": "codes"}).close()  # (id, vector): the index's
        with pytest.raises(ConfigError, match="fields"):
            memory({"name": "milvus", "uri": uri, "collection": "codes"}, cae_descriptor, tmp_path)


class TestConf:
    @pytest.mark.parametrize("conf, match", [
        ({"name": "faiss"}, "unknown fleet place memory"),
        ({"name": "milvus", "collection": "no spaces; drop"}, r"places\.collection"),
        ({"name": "milvus", "collection": ""}, r"places\.collection"),
        ({"name": "milvus", "index": {"name": "flat"}}, "unknown config key"),
        ({"name": "local", "uri": "http://x:19530"}, "only 'index'"),
        ({"name": "local", "index": {"name": "milvus"}}, "places.name: milvus"),
        ({"name": "local", "index": {"name": "nope"}}, "unknown index"),
        ("milvus", "mapping"),
    ])
    def test_bad_conf_is_refused_before_milvus_is_touched(self, conf, match):
        with pytest.raises(ConfigError, match=match):
            resolve_places(conf)

    def test_defaults(self):
        assert resolve_places(None) == {"name": "local", "index": resolve_conf({"index": {"name": "fp16"}})["index"]}
        assert resolve_places({"name": "milvus"})["collection"] == "fleet_places"
        assert not LocalPlaces.shared and MilvusPlaces.shared

    def test_a_hashing_descriptor_cannot_use_milvus(self, tmp_path):
        from retrieval.methods import method_conf
        from retrieval.mild import MildDescriptor

        conf = resolve_conf(method_conf("mild"))
        with pytest.raises(ConfigError, match="hashing"):
            create_fleet_places(MildDescriptor(conf["descriptor"]), None, conf, resolve_places({"name": "milvus"}),
                                tmp_path)
        assert not (tmp_path / LITE_FOLDER).exists()
