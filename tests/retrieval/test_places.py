"""retrieval.places: the two place memories behind one interface, on real sample frames."""

from __future__ import annotations

import numpy as np
import pytest

from cae_lcd.core.errors import ConfigError
from retrieval.detector import resolve_conf
from retrieval.methods import method_conf
from retrieval.mild import MildDescriptor
from retrieval.places import CodePlaces, HashPlaces, RowTable, create_places


@pytest.fixture(scope="module")
def mild_entries(sample_image):
    """MILD entries (ORB descriptors) of sample frames 0..11 and of 55 (a revisit of 5)."""
    desc = MildDescriptor({"max_features": 200})
    return {i: desc(sample_image(i)) for i in [*range(12), 55]}


def hash_places(exclude_recent: int = 3) -> HashPlaces:
    conf = resolve_conf(method_conf("mild", {"search": {"exclude_recent": exclude_recent},
                                             "descriptor": {"max_features": 200}}))
    return create_places(MildDescriptor(conf["descriptor"]), None, conf)


class TestHashPlaces:
    def test_whole_row_best_first_recent_excluded(self, mild_entries):
        places = hash_places(exclude_recent=3)
        for i in range(12):
            places.insert(i, mild_entries[i], None)
        scores, ids = places.search(12, mild_entries[55], None, k=2)
        assert sorted(ids.tolist()) == list(range(10))  # every admitted keyframe (not k); 10, 11 too recent
        assert np.all(np.diff(scores) <= 0) and ids[0] in (4, 5, 6)  # frame 55 revisits 5
        reference = places.hash.query(mild_entries[55])  # the row is the hash's eq. 3 similarity, by frame id
        np.testing.assert_allclose(scores, reference[ids], rtol=1e-6)
        assert len(places) == 12

    def test_source_and_undo(self, mild_entries):
        places = hash_places(exclude_recent=0)
        for i in range(3):
            places.insert(i, mild_entries[i], None)
        scores, ids = places.search(3, mild_entries[3], None, k=10)
        got = places.source.pairs(np.full(3, 3), np.array([0, 1, 2]))
        np.testing.assert_allclose(got, scores[np.argsort(ids)], rtol=1e-6)
        assert places.source.searchable(np.array([0, 2, 7])).tolist() == [True, True, False]
        places.undo(3)
        assert np.isnan(places.source.pairs(np.array([3]), np.array([0]))).all()

    def test_refuses_codes_and_whitening(self, mild_entries):
        places = hash_places()
        places.check(mild_entries[0])
        with pytest.raises(ConfigError, match="uint8"):
            places.check(np.zeros(4096, np.float32))
        conf = resolve_conf(method_conf("mild"))
        with pytest.raises(ConfigError, match="whitening"):
            HashPlaces(MildDescriptor(), object(), conf)  # type: ignore[arg-type]

    def test_empty_map(self, mild_entries):
        scores, ids = hash_places().search(0, mild_entries[0], None, k=5)
        assert scores.shape == (0,) and ids.shape == (0,)


class TestCodePlaces:
    def test_cosine_top_k_with_exclusion(self, encoder, sample_image):
        from retrieval.descriptors import CAEDescriptor

        conf = resolve_conf({"search": {"exclude_recent": 2}})
        places = create_places(CAEDescriptor(encoder=encoder), None, conf)
        assert isinstance(places, CodePlaces)
        codes = {i: CAEDescriptor(encoder=encoder)(sample_image(i)) for i in (4, 5, 6, 30, 55)}
        for n, i in enumerate((4, 5, 6, 30)):
            places.insert(n, codes[i], None)
        scores, ids = places.search(4, codes[55], None, k=2)
        assert ids.tolist()[0] in (0, 1, 2) and len(ids) == 2 and 3 not in ids.tolist()  # 30 too recent
        assert len(places) == 4
        with pytest.raises(ConfigError, match="shape"):
            places.check(np.zeros((3, 32), np.uint8))


    @pytest.mark.parametrize("index", [{"name": "auto"}, {"name": "flat"}, {"name": "hnsw"},
                                       {"name": "auto", "switch_at": 8}])
    def test_codes_read_back_from_the_index_as_a_table_keeps_them(self, encoder, sample_image, index):
        """An index that gives its codes back exactly serves the similarities itself (no second copy): the same
        pairs, membership and items as a memory that keeps a table (sq8), through searches, inserts and an undo."""
        from retrieval.descriptors import CAEDescriptor
        from retrieval.places import IndexedCodes
        from retrieval.temporal import CodeTable

        descriptor = CAEDescriptor(encoder=encoder)
        codes = [descriptor(sample_image(i)) for i in range(0, 100, 5)]
        memories = [create_places(descriptor, None, resolve_conf({"search": {"exclude_recent": 3}, "index": conf}))
                    for conf in (index, {"name": "sq8"})]
        assert isinstance(memories[0].source, IndexedCodes) and isinstance(memories[1].source, CodeTable)
        for places in memories:
            for n, code in enumerate(codes):
                places.search(n, places.entry(code), None, k=3)
                if n == 7:
                    places.undo(n)  # searched, then not inserted after all
                else:
                    places.insert(n, places.entry(code), None)
            places.search(len(codes), places.entry(codes[2]), None, k=3)  # a query not inserted (yet)
        q, r = np.meshgrid(np.arange(-1, len(codes) + 2), np.arange(-1, len(codes) + 2))
        got, want = (m.source.pairs(q.ravel(), r.ravel()) for m in memories)
        np.testing.assert_array_equal(got, want)  # NaN where either frame is not held (7, -1, past the end)
        assert np.isnan(got).sum() > 0 and np.isfinite(got).sum() > 100
        assert [i in memories[0].source for i in range(-1, 23)] == [i in memories[1].source for i in range(-1, 23)]
        assert len(memories[0].source) == len(memories[1].source) == len(codes)
        for a, b in zip(memories[0].source.items(), memories[1].source.items()):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(memories[0].source.searchable(np.arange(22)),
                                      memories[1].source.searchable(np.arange(22)))

    def test_a_milvus_memory_answers_like_faiss(self, encoder, sample_image, tmp_path):
        """The place memory on a Milvus index (milvus-lite file): the same candidates and scores as on faiss."""
        from retrieval.descriptors import CAEDescriptor

        descriptor = CAEDescriptor(encoder=encoder)
        codes = [descriptor(sample_image(i)) for i in range(0, 100, 4)]
        found = {}
        for name, index in (("flat", {"name": "flat"}), ("milvus", {"name": "milvus", "uri": str(tmp_path / "p.db")})):
            places = create_places(descriptor, None, resolve_conf({"search": {"exclude_recent": 3}, "index": index}))
            found[name] = []
            for n, code in enumerate(codes):
                found[name].append(places.search(n, code, None, k=3))
                places.insert(n, code, None)
            getattr(places.index.index, "close", lambda: None)()
        for (s_flat, i_flat), (s_milvus, i_milvus) in zip(found["flat"], found["milvus"]):
            np.testing.assert_array_equal(i_flat, i_milvus)
            np.testing.assert_allclose(s_flat, s_milvus, atol=1e-5)
        assert sum(len(i) for _, i in found["milvus"]) > 40


class TestRowTable:
    def test_pairs_searchable_and_keep(self):
        table = RowTable(keep=2)
        table.set(10, np.array([1, 3, 5]), np.array([0.1, 0.3, 0.5]))
        table.set(11, np.array([1, 3, 5, 6]), np.array([0.2, 0.4, 0.6, 0.7]))
        got = table.pairs(np.array([10, 11, 11, 10, 9]), np.array([3, 6, 2, 6, 1]))
        np.testing.assert_allclose(got, [0.3, 0.7, np.nan, np.nan, np.nan])
        assert table.searchable(np.array([6, 2])).tolist() == [True, False]
        table.set(12, np.zeros(0, np.int64), np.zeros(0))
        assert np.isnan(table.pairs(np.array([10, 12]), np.array([3, 3]))).all()  # 10 dropped (keep=2); 12 empty
