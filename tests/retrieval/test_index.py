"""faiss and Milvus (milvus-lite, embedded) indexes against the numpy brute-force reference, and the keyframe index's
recent-frame exclusion."""

import os

import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from retrieval.index import (INDEXES, AutoIndex, FlatIndex, FP16Index, HNSWIndex, IVFPQIndex, KeyframeIndex,
                             brute_force_search, create_index, load_index)

D = 64


def unit(rng, n, d=D):
    x = rng.normal(size=(n, d)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(0)
    return unit(rng, 2000), unit(rng, 50)


@pytest.fixture(scope="module")
def milvus_uri(tmp_path_factory):
    """One milvus-lite file for the module (its server starts once); every index a collection of its own."""
    return str(tmp_path_factory.mktemp("milvus") / "codes.db")


@pytest.fixture(params=["flat", "milvus"])
def exact_index(request, milvus_uri):
    """``exact_index()`` -> a new exact index: faiss ``flat`` or ``milvus``; Milvus ones closed at the end."""
    made = []

    def make():
        conf = {"name": "milvus", "uri": milvus_uri} if request.param == "milvus" else {"name": "flat"}
        made.append(create_index(D, conf))
        return made[-1]

    yield make
    for index in made:
        getattr(index, "close", lambda: None)()


def recall_at_k(I, I_ref):
    return np.mean([len(set(a) & set(b)) / len(b) for a, b in zip(I, I_ref)])


class TestBruteForceSearch:
    def test_against_sort(self, data):
        xb, xq = data
        D_, I = brute_force_search(xq, xb, 5)
        sims = xq @ xb.T
        np.testing.assert_array_equal(I, np.argsort(-sims, axis=1)[:, :5])
        np.testing.assert_allclose(D_, np.sort(sims, axis=1)[:, ::-1][:, :5], rtol=1e-6)

    def test_padding_and_empty(self, data):
        xb, xq = data
        D_, I = brute_force_search(xq[:2], xb[:3], 5)
        assert I.shape == (2, 5) and (I[:, 3:] == -1).all() and np.isneginf(D_[:, 3:]).all()
        D_, I = brute_force_search(xq[:2], xb[:0], 4)
        assert (I == -1).all() and I.shape == (2, 4)


class TestExactIndexes:
    def test_equals_brute_force(self, data, exact_index):
        xb, xq = data
        index = exact_index()
        index.add(xb[:1000])
        index.add(xb[1000:])  # positions continue
        assert index.ntotal == 2000
        Df, If = index.search(xq, 10)
        Db, Ib = brute_force_search(xq, xb, 10)
        assert If.dtype == np.int64 and If.shape == (50, 10)
        np.testing.assert_array_equal(If, Ib)
        np.testing.assert_allclose(Df, Db, rtol=1e-5, atol=1e-6)

    def test_fewer_codes_than_k(self, data, exact_index):
        xb, xq = data
        index = exact_index()
        index.add(xb[:3])
        Df, If = index.search(xq[:4], 6)
        Db, Ib = brute_force_search(xq[:4], xb[:3], 6)
        np.testing.assert_array_equal(If, Ib)
        assert (If[:, 3:] == -1).all() and np.isneginf(Df[:, 3:]).all()

    def test_empty_index_and_empty_query(self, data, exact_index):
        xb, xq = data
        index = exact_index()
        Df, If = index.search(xq[:2], 5)
        assert If.shape == (2, 5) and (If == -1).all()
        index.add(xb[:0])
        assert index.ntotal == 0
        Df, If = index.search(xq[:0], 5)
        assert Df.shape == (0, 5) and If.shape == (0, 5)


class TestFP16Index:
    def test_close_to_brute_force(self, data):
        xb, xq = data
        index = FP16Index(D)
        index.add(xb)
        Df, If = index.search(xq, 10)
        Db, Ib = brute_force_search(xq, xb, 10)
        np.testing.assert_allclose(Df, Db, atol=2e-3)
        assert recall_at_k(If, Ib) >= 0.98
        assert (If[:, 0] == Ib[:, 0]).mean() >= 0.98

    def test_half_the_memory(self, data):
        xb, _ = data
        flat, fp16 = FlatIndex(D), FP16Index(D)
        flat.add(xb)
        fp16.add(xb)
        assert flat.bytes_per_code() == pytest.approx(4 * D, rel=0.05)
        assert fp16.bytes_per_code() == pytest.approx(2 * D, rel=0.05)


class TestHNSWIndex:
    def test_recall(self, data):
        xb, xq = data
        index = HNSWIndex(D, {"m": 16})
        assert index.conf["m"] == 16 and index.index.hnsw.efSearch == HNSWIndex.default_conf["ef_search"]
        index.add(xb)
        Dh, Ih = index.search(xq, 10)
        _, Ib = brute_force_search(xq, xb, 10)
        assert recall_at_k(Ih, Ib) >= 0.95
        assert (Ih >= 0).all()

    def test_unknown_option(self):
        with pytest.raises(ConfigError, match="index.M"):
            HNSWIndex(D, {"M": 16})

    def test_fp16_storage_halves_memory_and_finds_the_same(self, data):
        """The detector's entries are float16-rounded: a graph over float16 storage gives them back exactly and finds
        what one over float32 finds, in about half the memory (the graph's links stay the same size)."""
        xb, xq = (x.astype(np.float16).astype(np.float32) for x in data)
        half, full = HNSWIndex(D, {"m": 16}), HNSWIndex(D, {"m": 16, "storage": "flat"})
        for index in (half, full):
            index.add(xb)
        np.testing.assert_array_equal(half.reconstruct(np.arange(len(xb))), xb)
        _, Ib = brute_force_search(xq, xb, 10)
        assert recall_at_k(half.search(xq, 10)[1], Ib) >= recall_at_k(full.search(xq, 10)[1], Ib) - 0.01
        links = full.bytes_per_code() - 4 * D
        assert half.bytes_per_code() == pytest.approx(links + 2 * D, rel=0.05)

    def test_storage_is_checked(self):
        with pytest.raises(ConfigError, match="index.storage"):
            HNSWIndex(D, {"storage": "fp8"})


@pytest.mark.skipif("sq8" not in INDEXES.names(), reason="no sq8 index in this version")
class TestSQ8Index:
    def test_exact_until_trained_then_close(self, data):
        xb, xq = data
        index = create_index(D, {"name": "sq8", "train_size": 500})
        index.add(xb[:300])
        assert index.ntotal == 300 and not index.index.is_trained
        Ds, Is = index.search(xq, 10)
        Db, Ib = brute_force_search(xq, xb[:300], 10)
        np.testing.assert_array_equal(Is, Ib)  # below train_size the codes are kept exact
        assert index.bytes_per_code() == 4 * D
        index.add(xb[300:600])  # crosses train_size: the quantiser is learned, every code quantised
        index.add(xb[600:])
        assert index.ntotal == 2000 and index.index.is_trained
        Ds, Is = index.search(xq, 10)
        Db, Ib = brute_force_search(xq, xb, 10)  # positions continue across the training point
        assert recall_at_k(Is, Ib) >= 0.9
        np.testing.assert_allclose(Ds, Db, atol=0.03)
        assert index.bytes_per_code() == pytest.approx(D, rel=0.1)

    def test_empty(self, data):
        _, xq = data
        index = create_index(D, {"name": "sq8"})
        Ds, Is = index.search(xq[:2], 3)
        assert Is.shape == (2, 3) and (Is == -1).all()


class TestIVFPQIndex:
    def test_exact_until_trained(self, data):
        xb, xq = data
        index = create_index(D, {"name": "ivfpq", "m": 8, "nlist": 16})
        assert isinstance(index, IVFPQIndex) and index.conf["train_size"] > len(xb)
        index.add(xb[:700])
        index.add(xb[700:])
        assert index.ntotal == 2000 and not index.index.is_trained
        np.testing.assert_array_equal(index.search(xq, 10)[1], brute_force_search(xq, xb, 10)[1])

    def test_m_must_divide_the_dimension(self):
        with pytest.raises(ConfigError, match="index.m .*divide"):
            create_index(D, {"name": "ivfpq", "m": 24})


class TestAutoIndex:
    def test_exact_while_small_then_large(self, data):
        xb, xq = data
        index = create_index(D, {"name": "auto", "switch_at": 1000})
        assert isinstance(index, AutoIndex)
        index.add(xb[:999])
        assert index.chosen == "fp16"
        half = np.asarray(xb[:999], np.float16).astype(np.float32)  # what fp16 holds: float16-rounded codes
        np.testing.assert_array_equal(index.search(xq, 10)[1], brute_force_search(xq, half, 10)[1])
        index.add(xb[999:1500])  # crosses switch_at: rebuilt as HNSW from the codes held, positions kept
        index.add(xb[1500:])
        assert index.chosen == "hnsw" and index.ntotal == 2000 and index.index.ntotal == 0
        _, I = index.search(xq, 10)
        assert recall_at_k(I, brute_force_search(xq, xb, 10)[1]) >= 0.95

    def test_switches_by_search_cost(self, data):
        """codes x dimension: the same count of longer codes switches sooner."""
        xb, xq = data
        index = create_index(D, {"name": "auto", "switch_cost": 300 * D})
        index.add(xb[:299])
        assert index.chosen == "fp16"
        index.add(xb[299:400])
        assert index.chosen == "hnsw" and index.ntotal == 400
        wide = create_index(2 * D, {"name": "auto", "switch_cost": 300 * D})
        wide.add(np.hstack([xb[:150], xb[:150]]) / np.sqrt(2))
        assert wide.chosen == "hnsw"
        assert create_index(D, {"name": "auto", "switch_cost": None}).conf["switch_cost"] is None  # by count only

    def test_options_checked(self):
        with pytest.raises(ConfigError, match="index.large"):
            create_index(D, {"name": "auto", "large": "ivf"})
        with pytest.raises(ConfigError, match="index.small"):
            create_index(D, {"name": "auto", "small": "hnsw"})

    @pytest.mark.parametrize("small, nbytes", [("flat", 4), ("fp16", 2)])
    def test_small_index_exact_for_rounded_entries(self, data, small, nbytes):
        """The detector's entries are float16-rounded: the fp16 stage finds exactly what flat does, in half the
        memory."""
        xb, xq = (np.asarray(x, np.float16).astype(np.float32) for x in data)
        index = create_index(D, {"name": "auto", "small": small})
        index.add(xb[:500])
        assert index.chosen == small
        D_, I = index.search(xq, 10)
        want_D, want_I = brute_force_search(xq, xb[:500], 10)
        np.testing.assert_array_equal(I, want_I)
        np.testing.assert_allclose(D_, want_D, rtol=0, atol=1e-5)
        assert index.bytes_per_code() < nbytes * D + 64


@pytest.mark.parametrize("conf, n", [({"name": "flat"}, 2000), ({"name": "fp16"}, 2000), ({"name": "hnsw"}, 2000),
                                     ({"name": "sq8", "train_size": 500}, 300),
                                     ({"name": "sq8", "train_size": 500}, 2000),
                                     ({"name": "ivfpq", "m": 8, "nlist": 16}, 300),
                                     ({"name": "auto", "switch_at": 1000}, 500),
                                     ({"name": "auto", "switch_at": 1000, "small": "flat"}, 500),
                                     ({"name": "auto", "switch_at": 1000}, 2000)])
def test_save_and_load_give_the_same_search(tmp_path, data, conf, n):
    xb, xq = data
    index = create_index(D, conf)
    index.add(xb[:n])
    index.save(tmp_path / "codes.index")
    back = load_index(tmp_path / "codes.index")
    assert type(back) is type(index) and back.conf == index.conf and back.ntotal == n
    for got, want in zip(back.search(xq, 10), index.search(xq, 10)):
        np.testing.assert_array_equal(got, want)
    back.add(xb[n:n + 10])  # it goes on growing
    assert back.ntotal == min(n + 10, len(xb))


def test_load_refuses_a_damaged_file(tmp_path, data):
    index = create_index(D)
    index.add(data[0][:100])
    index.save(tmp_path / "codes.index")
    raw = (tmp_path / "codes.index").read_bytes()
    (tmp_path / "codes.index").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ConfigError, match="not a readable code index"):
        load_index(tmp_path / "codes.index")


class TestCreateIndex:
    def test_by_name(self):
        assert isinstance(create_index(D), FlatIndex)
        assert isinstance(create_index(D, {"name": "fp16"}), FP16Index)
        assert isinstance(create_index(D, {"name": "hnsw", "ef_search": 64}), HNSWIndex)
        assert {"flat", "fp16", "hnsw", "milvus"} <= set(INDEXES.names())
        with pytest.raises(ConfigError, match="unknown index 'ivf'"):
            create_index(D, {"name": "ivf"})
        with pytest.raises(ConfigError, match="index.m"):
            create_index(D, {"name": "flat", "m": 16})
        with pytest.raises(ConfigError, match="index.collection"):  # checked before Milvus is touched
            create_index(D, {"name": "milvus", "collection": "no spaces; drop"})

    def test_a_milvus_collection_continues_and_refuses_another_size(self, data, milvus_uri):
        xb, xq = data
        first = create_index(D, {"name": "milvus", "uri": milvus_uri, "collection": "shared"})
        first.add(xb[:300])
        first.close()
        again = create_index(D, {"name": "milvus", "uri": milvus_uri, "collection": "shared"})
        assert again.ntotal == 300
        again.add(xb[300:400])  # positions continue
        np.testing.assert_array_equal(again.search(xq, 5)[1], brute_force_search(xq, xb[:400], 5)[1])
        again.close()
        with pytest.raises(ConfigError, match="holds 64-d codes"):
            create_index(D + 1, {"name": "milvus", "uri": milvus_uri, "collection": "shared"})

    def test_milvus_lite_gets_a_small_insert_buffer(self, milvus_uri, monkeypatch):
        """milvus-lite searches its insert buffer row by row in Python (its default 128 MB: 72 ms a query at 300
        4096-d rows): the index sets it, unless the environment already does."""
        monkeypatch.delenv("MILVUS_LITE_MEMTABLE_MEMORY_LIMIT_BYTES", raising=False)
        create_index(D, {"name": "milvus", "uri": milvus_uri, "lite_buffer_kb": 64}).close()
        assert os.environ["MILVUS_LITE_MEMTABLE_MEMORY_LIMIT_BYTES"] == str(64 * 1024)
        monkeypatch.setenv("MILVUS_LITE_MEMTABLE_MEMORY_LIMIT_BYTES", "4096")
        create_index(D, {"name": "milvus", "uri": milvus_uri}).close()
        assert os.environ["MILVUS_LITE_MEMTABLE_MEMORY_LIMIT_BYTES"] == "4096"  # the user's own setting wins
        with pytest.raises(ConfigError, match="lite_buffer_kb"):
            create_index(D, {"name": "milvus", "lite_buffer_kb": 1})


def query(kf, code, frame_id, k, timestamp=None):
    """What the detector does for a query frame: admit the codes old enough, then search (which only reads)."""
    kf.admit(frame_id, timestamp)
    return kf.search(code, k)


class TestKeyframeIndex:
    @pytest.fixture()
    def codes(self):
        return unit(np.random.default_rng(5), 40)

    @pytest.mark.parametrize("conf", [{"name": "flat"}, {"name": "fp16"}, {"name": "hnsw", "m": 8},
                                      {"name": "milvus"}])
    def test_exclude_recent_frames(self, codes, conf, milvus_uri):
        kf = KeyframeIndex(D, dict(conf, uri=milvus_uri) if conf["name"] == "milvus" else conf, exclude_recent=5)
        for i in range(10):
            kf.add(i, codes[i])
        assert len(kf) == 10
        # the query is a copy of frame 8's code, so frame 8 would be the best match if it were searchable
        scores, ids = query(kf, codes[8], 10, 10)
        assert ids.dtype == np.int64 and len(scores) == len(ids)
        assert set(ids.tolist()) == set(range(0, 6))  # frames 6..10 are too recent
        _, Ib = brute_force_search(codes[8:9], codes[:6], 10)
        np.testing.assert_array_equal(ids, Ib[0][Ib[0] >= 0])
        assert np.all(np.diff(scores) <= 1e-6)  # best first

    @pytest.mark.parametrize("mapped", [False, True])
    def test_codes_give_back_admitted_and_queued_ones_by_id(self, codes, mapped):
        """``codes``: each id's code, admitted (from the index) or queued alike, in the order asked, repeats and ids
        it does not hold (zeros, not found) among them; the same after ``mapped`` (a stream's whitening) and
        ``restore``-like rebuilds keep the id lookup with the list."""
        kf = KeyframeIndex(D, exclude_recent=5)
        ids = [0, 2, 3, 7, 8, 11, 12, 15, 16, 17]  # gaps: not every frame is a keyframe
        for i in ids:
            kf.admit(i)
            kf.add(i, codes[i])
        if mapped:
            kf = kf.mapped(lambda x: x, D, lambda fids: codes[np.asarray(fids)])
        assert len(kf.frame_ids) and kf.queued_ids()  # both kinds held
        asked = np.array([17, 1, 0, 12, 12, 39, 3, 16, 11, 8, 100, 2, 7, 15, -1], np.int64)
        found, got = kf.codes(asked)
        expected = np.isin(asked, ids)
        np.testing.assert_array_equal(found, expected)
        np.testing.assert_array_equal(got[expected], codes[asked[expected]])
        assert not got[~expected].any()
        assert kf.codes(np.zeros(0, np.int64))[1].shape == (0, D)

    def test_exclusion_follows_query_frame(self, codes):
        kf = KeyframeIndex(D, exclude_recent=5)
        assert query(kf, codes[0], 0, 3)[1].size == 0  # empty index: no results
        for i in range(20):
            _, ids = query(kf, codes[i], i, 50)
            assert set(ids.tolist()) == set(range(0, max(0, i - 4)))
            kf.add(i, codes[i])

    def test_zero_exclusion_returns_self(self, codes):
        kf = KeyframeIndex(D)
        for i in range(5):
            kf.add(i, codes[i])
        scores, ids = query(kf, codes[3], 3, 1)
        assert ids.tolist() == [3] and scores[0] == pytest.approx(1.0, abs=1e-5)

    def test_exclude_recent_seconds(self, codes):
        kf = KeyframeIndex(D, exclude_recent=0, exclude_recent_s=2.0)
        times = np.arange(20) * 0.5  # 2 frames a second
        for i in range(10):
            kf.add(i, codes[i], timestamp=float(times[i]))
        _, ids = query(kf, codes[9], 10, 20, float(times[10]))
        assert set(ids.tolist()) == set(range(0, 7))  # 5.0 - t >= 2.0  ->  t <= 3.0  ->  frames 0..6
        # the frame rule applies too when both are set
        kf2 = KeyframeIndex(D, exclude_recent=6, exclude_recent_s=2.0)
        for i in range(10):
            kf2.add(i, codes[i], timestamp=float(times[i]))
        _, ids = query(kf2, codes[9], 10, 20, float(times[10]))
        assert set(ids.tolist()) == set(range(0, 5))

    def test_k_larger_than_available(self, codes):
        kf = KeyframeIndex(D, exclude_recent=2)
        for i in range(4):
            kf.add(i, codes[i])
        scores, ids = query(kf, codes[0], 4, 10)
        assert sorted(ids.tolist()) == [0, 1, 2] and np.isfinite(scores).all()

    def test_search_does_not_change_the_index(self, codes):
        kf = KeyframeIndex(D, exclude_recent=2)
        for i in range(6):
            kf.add(i, codes[i])
        assert kf.search(codes[0], 10)[1].size == 0  # nothing admitted yet: search alone admits nothing
        kf.admit(6)
        first = kf.search(codes[0], 10)
        np.testing.assert_array_equal(kf.search(codes[0], 10)[1], first[1])
        assert sorted(first[1].tolist()) == [0, 1, 2, 3, 4]


class TestSaveWithStore:
    """``KeyframeIndex.save`` / ``restore``: what a detector writes beside its keyframe store and takes back."""

    def fill(self, conf, codes, n):
        kf = KeyframeIndex(D, conf, exclude_recent=5)
        for i in range(n):
            query(kf, codes[i], i, 1)
            kf.add(i, codes[i])
        return kf

    def test_graph_index_restored_searches_as_saved(self, tmp_path, data):
        codes = data[0][:300]
        kf = self.fill({"name": "hnsw", "m": 8}, codes, 300)
        assert kf.save(tmp_path / "kf.index")
        back = KeyframeIndex(D, {"name": "hnsw", "m": 8}, exclude_recent=5)
        assert back.restore(tmp_path / "kf.index", np.arange(400)) == len(kf.frame_ids) == 295
        for q in data[1][:10]:
            for got, want in zip(back.search(q, 10), kf.search(q, 10)):
                np.testing.assert_array_equal(got, want)

    def test_exact_index_is_not_saved(self, tmp_path, data):
        kf = self.fill({"name": "flat"}, data[0], 50)
        assert not kf.save(tmp_path / "kf.index")
        assert not (tmp_path / "kf.index").exists()

    @pytest.mark.parametrize("ids, conf", [(np.arange(1, 400), {"name": "hnsw", "m": 8}),  # not the store's first
                                           (np.arange(200), {"name": "hnsw", "m": 8}),  # the store has fewer
                                           (np.arange(400), {"name": "hnsw", "m": 16})])  # another index
    def test_a_file_that_does_not_fit_is_not_taken(self, tmp_path, data, ids, conf, caplog):
        self.fill({"name": "hnsw", "m": 8}, data[0], 300).save(tmp_path / "kf.index")
        back = KeyframeIndex(D, conf, exclude_recent=5)
        assert back.restore(tmp_path / "kf.index", ids) == 0
        assert len(back) == 0 and "rebuilt" in caplog.text

    def test_a_damaged_file_is_not_taken(self, tmp_path, data, caplog):
        self.fill({"name": "hnsw", "m": 8}, data[0], 300).save(tmp_path / "kf.index")
        raw = (tmp_path / "kf.index").read_bytes()
        (tmp_path / "kf.index").write_bytes(raw[: len(raw) - 100])
        back = KeyframeIndex(D, {"name": "hnsw", "m": 8})
        assert back.restore(tmp_path / "kf.index", np.arange(400)) == 0 and "not a readable code index" in caplog.text
        assert back.restore(tmp_path / "missing.index", np.arange(400)) == 0
