"""retrieval.temporal: the sequence filter on a hand-built similarity sequence."""

from __future__ import annotations

import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from retrieval.temporal import BayesFilter, CodeTable, NoFilter, SequenceFilter, create_filter


class MatrixSource:
    """A SimilaritySource over a hand-built (n, n) similarity matrix; every earlier frame is searchable."""

    def __init__(self, sims: np.ndarray) -> None:
        self.sims = sims

    def pairs(self, queries: np.ndarray, refs: np.ndarray) -> np.ndarray:
        return self.sims[np.asarray(queries), np.asarray(refs)].astype(np.float32)

    def searchable(self, refs: np.ndarray) -> np.ndarray:
        return np.ones(len(refs), bool)


def revisit_matrix(n: int = 60, start: int = 40, offset: int = 40, true_sim: float = 0.3, spike_at=(50, 5),
                   spike: float = 0.6, seed: int = 0) -> np.ndarray:
    """Noise, plus a revisit (query start+i matches map frame start-offset+i) and one look-alike spike."""
    rng = np.random.default_rng(seed)
    sims = rng.normal(0, 0.05, (n, n))
    for q in range(start, n):
        sims[q, q - offset] = true_sim
    sims[spike_at] = spike
    return sims


class TestSequenceFilter:
    def test_a_sequence_beats_a_single_look_alike(self):
        sims = revisit_matrix()
        src, filt = MatrixSource(sims), SequenceFilter({"length": 5})
        for q in range(40, 51):
            ids, scores = filt.update(q, np.array([q - 40, 5]), src)
            filt.commit(q, ids[:10])
        # at query 50 the single-frame spike (0.6 to frame 5) loses to the 11-frame revisit line (0.3 each)
        assert ids[0] == 10
        assert scores[0] == pytest.approx(0.3, abs=0.06)
        assert scores[list(ids).index(5)] < 0.2

    def test_hypotheses_are_carried_when_retrieval_misses(self):
        sims = revisit_matrix(spike=0.0)
        src, filt = MatrixSource(sims), SequenceFilter({"length": 5})
        for q in range(40, 46):
            ids, _ = filt.update(q, np.array([q - 40]), src)
            filt.commit(q, ids[:10])
        ids, scores = filt.update(46, np.array([30]), src)  # single-frame retrieval returns a wrong frame
        assert ids[0] == 6 and 6 not in (30,)

    def test_missing_terms_count_zero(self):
        sims = np.full((20, 20), 0.5)
        filt = SequenceFilter({"length": 10})
        # ref 2: only refs 2, 1, 0 exist -> 3 of 10 terms
        assert filt.score(np.array([15]), np.array([2]), MatrixSource(sims))[0] == pytest.approx(0.15)

    def test_a_speed_for_each_pair_scores_as_one_speed_a_call(self):
        """The score path scores every speed's lines in one call (``ScoreSpans._by_speed``): a speed a pair gives the
        same scores, bit for bit, as one call per speed."""
        sims = revisit_matrix(n=120, start=60, offset=50)
        src, filt = MatrixSource(sims), SequenceFilter({"length": 7, "velocities": [1.0, 1.1]})
        q, r = np.arange(60, 120), np.arange(60, 120) - 50
        speeds = (0.87, 1.0, 1.15, 2.0)
        one_each = np.concatenate([filt.score(q, r, src, v) for v in speeds])
        together = filt.score(np.tile(q, len(speeds)), np.tile(r, len(speeds)), src, np.repeat(speeds, len(q)))
        np.testing.assert_array_equal(together, one_each)

    def test_reverse_velocity(self):
        n = 40
        sims = np.zeros((n, n))
        for i in range(10):
            sims[30 + i, 20 - i] = 0.4  # the map traversed backwards
        src = MatrixSource(sims)
        fwd = SequenceFilter({"length": 8}).score(np.array([39]), np.array([11]), src)[0]
        both = SequenceFilter({"length": 8, "velocities": [1.0, -1.0]}).score(np.array([39]), np.array([11]), src)[0]
        assert fwd < 0.1 and both == pytest.approx(0.4)

    def test_empty(self):
        ids, scores = SequenceFilter().update(0, np.zeros(0, np.int64), MatrixSource(np.zeros((1, 1))))
        assert ids.shape == (0,) and scores.shape == (0,)

    def test_conf_checked(self):
        with pytest.raises(ConfigError, match="velocities"):
            SequenceFilter({"velocities": []})
        with pytest.raises(ConfigError, match="length"):
            SequenceFilter({"length": 0})


class TestNoFilter:
    def test_single_frame_scores(self):
        sims = revisit_matrix()
        ids, scores = NoFilter().update(50, np.array([10, 5]), MatrixSource(sims))
        assert list(ids) == [5, 10] and scores[0] == pytest.approx(0.6)


class TestCreateFilter:
    def test_by_name(self):
        assert isinstance(create_filter({"name": "none"}), NoFilter)
        with pytest.raises(ConfigError, match="unknown temporal filter"):
            create_filter({"name": "bayes2"})


class TestBayesFilter:
    def run(self, sims, queries, filt=None):
        filt = filt or BayesFilter()
        src = MatrixSource(sims)
        out = []
        for q in queries:
            ids, post = filt.update(q, np.arange(0, max(q - 10, 0)), src)
            out.append((q, ids, post))
        return out

    def test_a_consistent_revisit_wins_a_spike_does_not(self):
        sims = revisit_matrix(n=60, start=40, offset=40, true_sim=0.35, spike_at=(30, 8), spike=0.9)
        filt, src = BayesFilter(), MatrixSource(sims)
        for q in range(20, 60):
            ids, post = filt.update(q, np.arange(0, q - 10), src)
            if q == 30:  # one look-alike frame: near the top, but far from a loop, and "no loop" keeps weight
                assert abs(ids[0] - 8) <= 2 and post[0] < 0.5 and filt._no_loop > 0.2
            if q < 40:  # never above MILD's P0 = 0.7 before the revisit
                assert post[0] < 0.5
            if q >= 43:  # a few frames along the revisit: its place passes P0, "no loop" has faded
                assert abs(ids[0] - (q - 40)) <= 1 and post[0] > 0.7 and filt._no_loop < 0.05

    def test_score_sums_the_neighbourhood(self):
        sims = revisit_matrix(n=60, start=40, offset=40, true_sim=0.35)
        own, summed = BayesFilter({"score_window": 0, "max_hypotheses": 1000}), BayesFilter({"max_hypotheses": 1000})
        for q in range(20, 50):
            ids0, post0 = own.update(q, np.arange(0, q - 10), MatrixSource(sims))
            ids2, post2 = summed.update(q, np.arange(0, q - 10), MatrixSource(sims))
        by_id = dict(zip(ids0.tolist(), post0.tolist()))
        expected = sum(by_id.get(i, 0.0) for i in range(ids2[0] - 2, ids2[0] + 3))
        assert post2[0] == pytest.approx(expected, rel=1e-5) and post2[0] > post0[0]

    def test_posteriors_are_probabilities(self):
        sims, filt = revisit_matrix(), BayesFilter({"max_hypotheses": 1000, "score_window": 0})
        for q in range(20, 60):
            ids, post = filt.update(q, np.arange(0, q - 10), MatrixSource(sims))
            assert np.all(post >= 0) and post.sum() + filt._no_loop == pytest.approx(1.0, abs=1e-5)

    def test_no_candidates(self):
        ids, post = BayesFilter().update(5, np.zeros(0, np.int64), MatrixSource(np.zeros((6, 6))))
        assert ids.shape == (0,) and post.shape == (0,)

    def test_same_interface(self):
        assert isinstance(create_filter({"name": "bayes"}), BayesFilter)
        with pytest.raises(ConfigError, match="stay"):
            BayesFilter({"stay": 1.5})


class TestCodeTable:
    def test_pairs_and_missing(self):
        table = CodeTable(2)
        table.add(3, np.array([1.0, 0.0], np.float32))
        table.add(5, np.array([0.6, 0.8], np.float32))
        sims = table.pairs(np.array([5, 5]), np.array([3, 4]))
        assert sims[0] == pytest.approx(0.6) and np.isnan(sims[1])
        table.remove_last(5)
        assert 5 not in table and 3 in table

    @pytest.mark.parametrize("step", [3, 1])
    def test_bisection_finds_the_rows_one_lookup_each_finds(self, sample_frames, step):
        """The fast paths (ids added in increasing order, rows found by bisection, or by subtraction where the ids
        have no gap: ``step`` 1) against brute force (each pair's two codes looked up and multiplied): the same
        similarities, NaN where a frame is not stored, after a removal and with ids added out of order (the lookup
        path); empty in, empty out."""
        from cae_lcd.core.images import read_image
        from retrieval.descriptors import create_descriptor

        descriptor = create_descriptor({"name": "cae"})
        codes = {step * i + 1: descriptor(read_image(p)) for i, p in enumerate(sample_frames[:8])}
        codes = {f: c / np.linalg.norm(c) for f, c in codes.items()}
        rng = np.random.default_rng(0)
        for order in (sorted(codes), sorted(codes, reverse=True)):
            table = CodeTable(len(codes[1]))
            for f in order:
                table.add(f, codes[f])
            table.remove_last(order[-1])
            kept = set(order[:-1])
            q, r = rng.integers(-2, 26, 200), rng.integers(-2, 26, 200)
            want = np.array([np.dot(codes[a], codes[b]) if a in kept and b in kept else np.nan
                             for a, b in zip(q.tolist(), r.tolist())], np.float32)
            np.testing.assert_allclose(table.pairs(q, r), want, rtol=1e-5, atol=1e-6)
            assert table._ascending == (order[0] < order[1])
            assert table.pairs(np.zeros(0, np.int64), np.zeros(0, np.int64)).shape == (0,)

    def test_a_fixed_table_reads_the_similarities_a_growing_one_computes(self, sample_frames):
        """``CodeTable.fixed`` (a calibration's: every pair from the Gram matrix) against a table filled frame by
        frame (each pair's two codes multiplied): the same similarities up to float32 rounding, NaN where a frame is
        not stored; adding to it drops the matrix and computes again."""
        from cae_lcd.core.images import read_image
        from retrieval.descriptors import create_descriptor

        descriptor = create_descriptor({"name": "cae"})
        ids = np.arange(0, 24, 3)
        codes = np.stack([descriptor(read_image(p)) for p in sample_frames[:len(ids)]])
        codes /= np.linalg.norm(codes, axis=1, keepdims=True)
        fixed, grown = CodeTable.fixed(ids, codes), CodeTable(codes.shape[1])
        for f, c in zip(ids.tolist(), codes):
            grown.add(f, c)
        rng = np.random.default_rng(1)
        q, r = rng.integers(-1, 25, 300), rng.integers(-1, 25, 300)
        assert fixed._gram is not None and np.isnan(fixed.pairs(q, r)).sum() > 100
        np.testing.assert_allclose(fixed.pairs(q, r), grown.pairs(q, r), rtol=1e-5, atol=1e-6)
        fixed.add(30, codes[0])
        assert fixed._gram is None and fixed.pairs(np.array([30]), np.array([0]))[0] == pytest.approx(1.0, abs=1e-5)

    def test_a_memoised_table_gives_each_pair_as_computed_alone(self, sample_frames, monkeypatch):
        """``memo`` (a refit's replay table): every similarity bit for bit what an unmemoised table computes, NaN where
        a frame is not stored, in calls of a few pairs and of many (repeated pairs: the distinct ones computed once),
        each distinct pair's codes multiplied once in the table's life; adding a frame drops the memo."""
        from cae_lcd.core.images import read_image
        from retrieval.descriptors import create_descriptor

        descriptor = create_descriptor({"name": "cae"})
        ids = np.arange(0, 24, 3)
        codes = np.stack([descriptor(read_image(p)) for p in sample_frames[:len(ids)]])
        codes /= np.linalg.norm(codes, axis=1, keepdims=True)
        memo, plain = CodeTable(codes.shape[1], memo=True), CodeTable(codes.shape[1])
        for f, c in zip(ids.tolist(), codes):
            memo.add(f, c)
            plain.add(f, c)
        computed = []
        products = memo._products
        monkeypatch.setattr(memo, "_products", lambda a, b: computed.append(len(a)) or products(a, b))
        rng = np.random.default_rng(2)
        asked = np.r_[ids, [1, 25]]  # stored frames, and two that are not
        for n in (3, 500, 7, 500):  # a few (each computed as it comes), many (the distinct ones)
            q, r = rng.choice(asked, n), rng.choice(asked, n)
            got, want = memo.pairs(q, r), plain.pairs(q, r)
            assert np.array_equal(got, want, equal_nan=True) and np.isnan(got).any()
        assert sum(computed) <= 3 + len(ids) ** 2 and max(computed) > 1  # 1010 pairs asked, 64 distinct at most
        memo.add(30, codes[0])
        assert memo._memo is None and memo.pairs(np.array([30]), np.array([0]))[0] == plain.pairs(
            np.array([0]), np.array([0]))[0]

    def test_float16_rows_give_the_same_similarities_at_half_the_memory(self, sample_frames):
        """Codes rounded to float16 (what ``CodePlaces.entry`` searches and stores) kept as float16: the same
        similarities as float32 rows, bit for bit, in half the bytes."""
        from cae_lcd.core.images import read_image
        from retrieval.descriptors import create_descriptor
        from retrieval.detector import resolve_conf
        from retrieval.places import create_places

        descriptor = create_descriptor({"name": "cae"})
        places = create_places(descriptor, None, resolve_conf())
        codes = [places.entry(descriptor(read_image(p))) for p in sample_frames[:6]]
        tables = {dt: CodeTable(len(codes[0]), dtype=dt) for dt in (np.float32, np.float16)}
        for t in tables.values():
            for i, c in enumerate(codes):
                t.add(i, c)
        q, r = np.array([5, 5, 4, 1]), np.array([0, 1, 2, 3])
        np.testing.assert_array_equal(tables[np.float16].pairs(q, r), tables[np.float32].pairs(q, r))
        assert tables[np.float16]._codes.nbytes * 2 == tables[np.float32]._codes.nbytes
        sq8 = create_places(descriptor, None, resolve_conf({"index": {"name": "sq8"}}))
        assert sq8.source._codes.dtype == np.float16  # a memory whose index cannot give them back keeps them so
