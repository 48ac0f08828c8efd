"""retrieval.decision: the hard-negative null, when a score may decide alone, fused evidence and the trajectory's
"too recent" rule, on real frames (the bundled sample shrunk to 160x120 as a plain folder: no intrinsics)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from retrieval.decision import SPAN, UNSUPPORTED, Decision, Horizon, Stops, TailModel, gamma_log10_sf


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """``(folder, calibration)`` of the bundled sample at 160x120, default conf."""
    from bench.camera import shrunk_sample
    from retrieval.detect import calibrate_sequence
    from retrieval.sequences import open_sequence

    root = tmp_path_factory.mktemp("s160")
    seq = shrunk_sample(root / "seq", (160, 120))
    return seq, calibrate_sequence(open_sequence(seq), {}, progress=False)


#: a run on the map's speed only (``calibration.speeds: [1.0]``): the sample's weak three-frame revisit (80-82 on
#: 29-31) reaches ``accept_at`` on one line; tested on three, each line pays log10(3) and it needs a fourth frame
MAP_SPEED = (1.0,)


def _decision(cal, single: bool | None = None, speeds: tuple[float, ...] | None = None) -> Decision:
    if speeds is not None:
        cal = copy.copy(cal)
        cal.fused = {**cal.fused, "speeds": list(speeds)}
    dec = cal.decision(50)
    if single is not None:
        dec.single = single
    return dec


class _NoSource:
    """No stored codes (the horizon then rests on the frame floor)."""

    def pairs(self, queries: np.ndarray, refs: np.ndarray) -> np.ndarray:
        return np.full(len(refs), np.nan, np.float32)


class TestHardNegatives:
    def test_hard_null_above_random_null(self, small):
        _, cal = small
        hard, rand = cal.samples["retrieved_inliers"], cal.samples["random_inliers"]
        assert len(cal.samples["hard_inliers"]) > len(hard) > len(rand) >= 10
        # the pair null holds both what retrieval returns among pairs known not to be loops and random far-side
        # pairs (at 160x120 both sit mostly at 0 and the 7 of a minimal model; a random one may verify higher)
        null = cal.samples["hard_inliers"]
        assert null.max() >= max(hard.max(), rand.max()) and len(null) >= 500

    def test_both_distributions_saved_and_printed(self, small, tmp_path):
        from retrieval.calibrate import Calibration

        _, cal = small
        cal.save(tmp_path / "c.h5")
        back = Calibration.load(tmp_path / "c.h5")
        for name in ("random_inliers", "hard_inliers", "positive_inliers", "hard_fused", "positive_fused"):
            assert np.array_equal(back.samples[name], cal.samples[name])
        assert any("random far-side pairs" in n and "null pairs, hard and random" in n for n in cal.notes)

    def test_measured_tail_claims_only_its_sample(self):
        from retrieval.decision import EmpiricalTail

        x = np.r_[np.zeros(600), np.arange(1, 11)]
        tail = EmpiricalTail(x)
        assert tail.log10_sf(0) == 0.0  # at the median: no evidence
        assert 10 ** tail.log10_sf(10) == pytest.approx(2 / 611)  # the largest sample: (1 + 1) / (n + 1)
        assert tail.evidence(10_000) == pytest.approx(math.log10(611)) == tail.max_evidence  # no tail past it

    def test_measured_sequence_tail_no_wider_than_its_sample(self):
        from retrieval.decision import MeasuredTail

        tail = MeasuredTail(np.r_[np.zeros(149), 7.1])  # one look-alike sequence far above the rest
        assert 10 ** tail.log10_sf(7.1) == pytest.approx(1 / 151)  # it raises the bar up to itself
        assert tail.log10_sf(7.2) == -math.inf  # and no further: beyond it the Gamma model speaks

    def test_empirical_calibration_bounded(self, small):
        _, cal = small
        assert cal.inlier_null["empirical"] and cal.inlier_confidence(10_000) < cal.accept_at  # a pair never alone
        assert cal.thresholds()["inliers"] is None

    def test_tail_never_lighter_than_its_samples(self):
        x = np.r_[np.zeros(60), np.arange(1, 11)]
        tail = TailModel.fit(x)
        assert 10 ** tail.log10_sf(x.max()) >= 1 / (2 * len(x)) - 1e-12
        assert tail.log10_sf(0) == 0.0 and tail.evidence(5) > 0


class TestSeparation:
    def test_geometry_does_not_separate_at_160x120(self, small):
        _, cal = small
        assert cal.fused["single"] == 0.0

    def test_non_separating_pair_cannot_accept_alone(self, small):
        _, cal = small
        dec = _decision(cal)
        dec.pair_tail = TailModel(0.0, 5.0)  # a modelled tail (a calibration made by hand): one pair could claim much
        huge = np.array([10_000])
        assert dec.confidences(100, np.array([10]), huge, _NoSource())[0] == UNSUPPORTED < dec.accept_at
        dec.single = True  # where it separates, the same pair decides alone
        assert dec.confidences(100, np.array([10]), huge, _NoSource())[0] >= dec.accept_at


class TestFusedEvidence:
    def _inliers(self, seq, pairs):
        from cae_lcd.core.images import read_image
        from verify.features import create_extractor
        from verify.verifier import create_verifier

        ex, ver = create_extractor({"name": "sift"}), create_verifier({"name": "ratio"}, None)
        img = (lambda i: read_image(seq / "image_0" / f"{i:06d}.png"))
        return [ver.verify(ex.extract(img(q)), [ex.extract(img(r))], None, 0, 0, True)[0].inliers for q, r in pairs]

    def test_weak_consistent_sequence_accepted(self, small):
        seq, cal = small
        dec = _decision(cal, speeds=MAP_SPEED)
        pairs = [(80 + j, 29 + j) for j in range(3)]  # a true revisit of the sample (loops.txt), frame after frame
        inl = self._inliers(seq, pairs)
        alone = [cal.inlier_confidence(x) for x in inl]
        assert max(alone) < cal.accept_at  # weak: no single pair would pass on its own
        for (q, r), x in zip(pairs[:-1], inl[:-1]):
            dec.commit(q, np.array([r]), np.array([x]))
        q, r = pairs[-1]
        assert dec.confidences(q, np.array([r]), np.array([inl[-1]]), _NoSource())[0] >= cal.accept_at

    def test_one_strong_pair_among_look_alikes_refused(self, small):
        _, cal = small
        dec = _decision(cal)
        hard = cal.samples["hard_inliers"]
        for j, q in enumerate(range(95, 99)):  # look-alikes: the hardest negatives, offsets that do not agree
            dec.commit(q, np.array([10 + 7 * j]), np.array([int(hard.max())]))
        strong = 10_000  # as strong as a pair can be: the measured null caps what one pair claims
        assert dec.confidences(99, np.array([40]), np.array([strong]), _NoSource())[0] < cal.accept_at

    def test_gamma_tail(self):
        assert gamma_log10_sf(1, 3.0) == pytest.approx(-3.0)
        assert gamma_log10_sf(3, 3.0) > -3.0  # three chances to reach a sum are more likely than one


class TestTooRecent:
    def test_floor_without_codes(self):
        assert Horizon(0.5, 50)(100, _NoSource()) == 51

    def test_revisit_of_a_long_look_alike_stretch_gives_no_loop(self, small, tmp_path):
        """A robot that stands still for 60 frames (the same real view, sensor noise only), so frames 50 back
        look exactly like the current one: the stretch it is in is one place, not a loop."""
        from cae_lcd.core.images import read_image
        from retrieval.detector import LoopDetector

        seq, cal = small
        frames = [read_image(seq / "image_0" / f"{i:06d}.png") for i in range(10)]
        rng = np.random.default_rng(0)
        hold = frames[-1].astype(np.int16)
        frames += [np.clip(hold + rng.integers(-2, 3, hold.shape), 0, 255).astype(np.uint8) for _ in range(60)]
        loops = {}
        floor_only = copy.deepcopy(cal)
        floor_only.fused.pop("stretch_cos")
        floor_only.fused.pop("still_cos")  # a stop is matched only to a stop as long: it would refuse this too
        for rule, calib in (("trajectory", cal), ("frame count only", floor_only)):
            loops[rule] = []
            with LoopDetector({"calibration": {"online": False}}, calibration=calib) as det:  # as given, no prior check
                for i, image in enumerate(frames):
                    if (res := det.process(image, i)).loop is not None:
                        loops[rule].append((i, res.loop.frame_id))
                        break
        assert loops["trajectory"] == []
        assert loops["frame count only"]  # the frame floor alone calls the stretch a loop: the test can fail


@pytest.fixture(scope="module")
def table(nordland_codes):
    """The real Nordland frames' unit raw codes as a ``CodeTable`` (frame ids as in the sequence)."""
    from retrieval.temporal import CodeTable

    table = CodeTable(4096)
    for fid, code in nordland_codes.items():
        table.add(fid, code / np.linalg.norm(code))
    return table


class TestStops:
    """A stop is one place, matched to a stop: on Nordland's real station stops (summer 206-241, winter 705-745, where
    the winter train waits 5 frames longer)."""

    @staticmethod
    def _stops():
        from cae.weights import load_encoder

        return Stops(load_encoder().still_cos)  # the shipped weights' own

    def test_stop_lengths(self, table):
        lengths = self._stops().lengths(np.array([206, 207, 240, 241, 242, 744]), table)
        assert lengths.tolist() == [0, 1, 34, 35, 0, 39]  # summer: arrives at 206, still 207-241; winter: 706-745

    def test_moving_frames_are_read_once_the_newest_kept(self, table, monkeypatch):
        """A frame found moving is remembered (its stop is asked for by its own decision, the frames after it and a
        replay), the newest ``MOVING_KEPT`` of them: the same lengths, each moving frame's codes read once."""
        import retrieval.decision as decision

        monkeypatch.setattr(decision, "MOVING_KEPT", 2)
        stops, asked = self._stops(), []
        pairs = table.pairs
        monkeypatch.setattr(table, "pairs", lambda q, r: asked.append(q.tolist()) or pairs(q, r))
        frames = np.array([206, 242, 255, 206, 242])  # three moving frames, two asked again
        assert stops.lengths(frames, table).tolist() == [0, 0, 0, 0, 0]
        assert asked == [[206], [242], [255], [206], [242]]  # 206 forgotten (two kept), then 242 too
        assert stops.lengths(np.array([255]), table).tolist() == [0] and len(asked) == 6
        assert stops.lengths(np.array([242]), table).tolist() == [0] and len(asked) == 6  # kept: not read again
        assert stops.lengths(np.array([241]), table).tolist() == [35]  # a stop's frames as before

    def test_a_still_query_matches_a_stop_as_long(self, table):
        stops = self._stops()
        assert stops.admissible(730, np.array([240, 250]), table).tolist() == [True, False]  # a stop, not a passage
        assert not stops.admissible(744, np.array([240, 242]), table).any()  # waited longer than the reference did
        assert stops.admissible(755, np.array([240, 250]), table).all()  # a moving query: not affected

    def test_a_query_that_just_left_a_stop_reads_it_on_its_line(self, table):
        """Winter 746 has just left a 40-frame stop: its score-path window reads that stop, so on its line the frame
        before (745, still 39 frames) must meet a stop as long; summer 229 stood 23 frames, 246 had moved on."""
        stops = self._stops()
        assert stops.admissible(746, np.array([229, 246]), table).all()  # the query itself moves
        assert not stops.line_admissible(746, np.array([229, 246]), 2, table).any()
        assert stops.line_admissible(755, np.array([255]), 2, table).all()  # moving on both lines: not affected

    def test_decision_refuses_only_the_inadmissible(self, table):
        dec = Decision(None, TailModel(0.0, 1.0), 1.0, 1.0, False, stops=self._stops())
        fallback = np.array([10.0])
        assert dec.confidences(730, np.array([240]), np.array([-1]), table, fallback)[0] == 10.0
        assert dec.confidences(744, np.array([240]), np.array([-1]), table, fallback)[0] == -math.inf

    def test_code_terms_computed_before_decide_the_same(self, table):
        """The detector reads a frame's code terms (``Decision.code_terms``) before its candidates are verified, beside
        the worker extracting its features: the confidences from them are those computed in one go, and they are the
        terms read (another frame's would decide otherwise)."""
        dec = Decision(None, TailModel(0.0, 1.0), 1.0, 1.0, False, stops=self._stops())
        refs, unverified, fallback = np.array([240, 250, 242]), np.full(3, -1), np.full(3, 10.0)
        for q in (730, 744, 755):
            terms = dec.code_terms(q, refs, table)
            assert np.array_equal(dec.confidences(q, refs, unverified, table, fallback, terms),
                                  dec.confidences(q, refs, unverified, table, fallback))
        other = dec.confidences(730, refs, unverified, table, fallback, dec.code_terms(744, refs, table))
        assert not np.array_equal(other, dec.confidences(730, refs, unverified, table, fallback))

    def test_code_terms_of_many_frames_are_each_frames_own(self, table):
        """A replay reads the code terms of its recorded frames together (``Decision.code_terms_many``: the score
        path's windows in calls of ``PAIR_CHUNK // span`` pairs): each frame's are those it reads alone, on Nordland's
        real winter frames against summer keyframes at three line speeds, over more than one call."""
        from retrieval.decision import EmpiricalTail, MeasuredTail, ScoreSpans
        from retrieval.temporal import PAIR_CHUNK, create_filter

        spans = ScoreSpans(create_filter({}).score, 10, EmpiricalTail(np.linspace(0.0, 0.5, 999)),
                           [MeasuredTail(np.zeros(0))] * 3, 1e4, (0.87, 1.0, 1.15))
        dec = Decision(None, TailModel(0.0, 1.0), 1e4, 1.0, False, stops=self._stops(), spans=spans)
        queries = np.arange(700, 760, dtype=np.int64)
        refs = [np.arange(q - 506, q - 494, dtype=np.int64) for q in queries]  # 12 summer keyframes around its place
        assert sum(map(len, refs)) > PAIR_CHUNK // spans.span  # more than one call
        many = dec.code_terms_many(queries, refs, table)
        for q, r, terms in zip(queries.tolist(), refs, many):
            alone = dec.code_terms(q, r, table)
            assert np.array_equal(terms.windows, alone.windows) and np.array_equal(terms.allowed_w, alone.allowed_w)
        assert np.isfinite(np.concatenate([t.windows for t in many])).any()  # windows that decide

    def test_a_line_at_another_speed_through_a_stop_does_not_agree(self, table):
        """A stop has no speed: a line at 0.87x through Nordland's winter station stop (706-745) reads the stop's
        frames at offsets the stop's length sets (random weights, lines at 0.87x, 1x and 1.15x: 744-746 matched 239-241
        and 749 243, 5-7 frames off). Its window does not agree where a still frame lies on either side; the window of
        a moving query and keyframe does, and so does a line at the map's speed (the stops' own rule decides there)."""
        from retrieval.decision import EmpiricalTail, MeasuredTail, ScoreSpans
        from retrieval.temporal import create_filter

        def spans(stops):
            return ScoreSpans(create_filter({}).score, 10, EmpiricalTail(np.linspace(0.0, 0.5, 999)),
                              [MeasuredTail(np.zeros(0))] * 3, 1e4, (0.87, 1.0, 1.15), stops)

        q, r = np.array([744, 700]), np.array([239, 200])  # in both stops; moving, before them
        ruled = spans(self._stops())
        assert ruled.windows(q, r, table, 0.87)[:, 0].tolist()[0] == -math.inf
        assert np.isfinite(ruled.windows(q, r, table, 0.87)[1, 0])
        assert np.isfinite(ruled.windows(q, r, table, 1.0)[:, 0]).all()
        assert np.isfinite(spans(None).windows(q, r, table, 0.87)[:, 0]).all()

    def test_a_stop_carries_the_loop_of_its_arrival(self, table):
        """Winter 730 stands still in the station after 729 closed a loop to summer 230: the loop is carried to its
        candidate in the summer stop nearest after 230 (the query has not moved), with 729's confidence; to nothing
        else, and only from the frame before."""
        dec = Decision(None, TailModel(0.0, 1.0), 1.0, 1.0, False, stops=self._stops())
        refs = np.array([231, 235, 250, 229])
        dec.note_loop(729, 230, 9.0)
        inside, confidence = dec.stop_carry(730, refs, table)
        assert inside.tolist() == [True, False, False, False] and confidence == 9.0
        assert dec.stop_carry(730, refs[1:], table)[0].tolist() == [True, False, False]  # 231 not a candidate
        assert not dec.stop_carry(731, refs, table)[0].any()  # 730 was not recorded as a loop: nothing to carry
        dec.note_loop(754, 250, 9.0)
        assert not dec.stop_carry(755, np.array([251, 252]), table)[0].any()  # a moving query: its own evidence
        dec.note_loop(729, None)
        assert not dec.stop_carry(730, refs, table)[0].any()
        assert not dec.fresh().stop_carry(730, refs, table)[0].any()


    def test_a_stop_that_begins_a_frame_later_carries_too(self, table):
        """Winter 705 arrives (a loop to summer 205) and is still from 706; the summer train was still only from 207
        (``STOP_EDGE``: the first still frame of a slowing camera is one frame uncertain): 706 carries the loop, to
        206 where the summer train was coming to its stop, or to 209, three frames into it; not to 250, past it."""
        dec = Decision(None, TailModel(0.0, 1.0), 1.0, 1.0, False, stops=self._stops())
        dec.note_loop(705, 205, 9.0)
        assert dec.stop_carry(706, np.array([206, 250]), table)[0].tolist() == [True, False]
        assert dec.stop_carry(706, np.array([209, 250]), table)[0].tolist() == [True, False]

    def test_a_carried_stop_ends_where_the_reference_moved_on(self, table):
        """Carried frame by frame from the arrival 705 -> 205, the winter stop reaches 741 -> 241 (the summer stop's
        last frame) and ends there: at 742 the summer train has moved on, and ``STOP_EDGE``'s one frame was the
        arrival's, not each step's (else the chain would walk into the summer passage a frame at a time)."""
        dec = Decision(None, TailModel(0.0, 1.0), 1.0, 1.0, False, stops=self._stops())
        dec.note_loop(705, 205, 9.0)
        for q in range(706, 742):
            refs = np.array([q - 500, q - 499])
            inside, _ = dec.stop_carry(q, refs, table)
            assert inside.tolist() == [True, False]
            dec.note_loop(q, q - 500, 9.0)
        assert not dec.stop_carry(742, np.array([242, 243]), table)[0].any()

class TestStopCarryThroughTheDetector:
    """``Decision.carry_to``: the keyframe a stop would carry the frame before's loop to stays among the frame's
    hypotheses whatever its rank (a reference stop's frames all look alike: their order among the top k is noise)."""

    def test_carry_to_names_the_keyframe_after_the_frame_befores(self):
        dec = Decision(None, TailModel(0.0, 1.0), 1.0, 1.0, False)
        assert dec.carry_to(725).tolist() == []  # no loop yet
        dec.note_loop(724, 224, 9.0)
        assert dec.carry_to(725).tolist() == [225] and dec.carry_to(726).tolist() == []  # only the next frame
        dec.note_loop(725, None)
        assert dec.carry_to(726).tolist() == []

    def test_a_winter_stop_is_carried_to_its_end(self, tmp_path):
        """Nordland summer 100-299 and winter 600-799 (``detect --lookahead``, the score path): the winter train waits
        706-745 in the station the summer train waited in (207-241). Its loop, carried frame by frame, ran out at 722
        when summer's next stop frame fell out of the top 10 (measured); kept, it reaches 741, every loop true."""
        from bench.aliasing import plain_folder
        from cae_lcd.evaluation.ground_truth import read_loop_pairs
        from retrieval.detect import main as detect
        from retrieval.run_folder import RunFolder
        from tests.conftest import NORDLAND

        if not (NORDLAND / "images").is_dir():
            pytest.skip(f"shared Nordland data not found at {NORDLAND}")
        frames = [*range(100, 300), *range(600, 800)]
        folder = plain_folder(tmp_path / "seq", [NORDLAND / "images" / f"{i:06d}.png" for i in frames])
        detect(folder, tmp_path / "run", {"calibration": {"online": False}}, progress=False)
        loops = [(frames[int(q)], frames[int(r)]) for q, r in RunFolder(tmp_path / "run").read_loops()[:, :2]]
        truth = set(map(tuple, read_loop_pairs(NORDLAND / "loops.txt").tolist()))
        assert [pair for pair in loops if pair not in truth] == []
        assert set(range(723, 742)) <= {q for q, _ in loops}


class TestScoreSpans:
    """The score path fuses consecutive windows on one line (``ScoreSpans``), each window's evidence read from the
    measured null (issue 27: no p-value below ``1 / (n + 1)`` of its sample)."""

    @staticmethod
    def _spans(values: dict[int, float], n: int = 9999):
        from retrieval.decision import EmpiricalTail, MeasuredTail, ScoreSpans

        def score(q, r, source, speed=1.0):  # the filter's window score, by the window's query
            return np.array([values.get(int(x), 0.0) for x in q], np.float64)

        null = EmpiricalTail(np.linspace(-0.1, 0.1, n))  # n null window scores: at most log10(n + 1) = 4 decades each
        return ScoreSpans(score, 10, null, [MeasuredTail(np.zeros(0))] * 3, 1e4)

    def test_weak_consistent_windows_accept_what_one_cannot(self):
        accept_at = -math.log10(0.05)
        one = self._spans({300: 0.35})  # the earlier windows (290, 280) at the null median: they do not agree
        assert one.confidences(np.array([300]), np.array([100]), None)[0] < accept_at
        three = self._spans({300: 0.35, 290: 0.35, 280: 0.35})  # the same evidence, three windows in a row
        assert three.confidences(np.array([300]), np.array([100]), None)[0] >= accept_at

    def test_a_contrary_window_vetoes_the_longer_spans(self):
        spans = self._spans({300: 0.9, 290: -0.2, 280: 0.9})
        fused = spans.fused(spans.windows(np.array([300]), np.array([100]), None))
        assert fused[0, 0] > 0 and (fused[0, 1:] == 0).all()

    def test_windows_at_a_speed_each_equal_one_speed_a_call(self, nordland_codes):
        """Every speed's windows scored in one call (a speed a pair, ``_by_speed``) are those of one call per speed,
        bit for bit, the stops included (a line at another speed than the map's through a still frame does not
        agree): on real Nordland codes, frames 150-259, where the summer train waits at a station (206-241)."""
        from retrieval.decision import EmpiricalTail, MeasuredTail, ScoreSpans
        from retrieval.temporal import CodeTable, SequenceFilter

        table = CodeTable(4096)
        for fid in range(150, 260):
            code = nordland_codes[fid]
            table.add(fid, code / np.linalg.norm(code))
        spans = ScoreSpans(SequenceFilter({"length": 10}).score, 10, EmpiricalTail(np.zeros(9)),
                           [MeasuredTail(np.zeros(0))] * 3, 1.0, (0.87, 1.0, 1.15), Stops(0.99))
        q = np.arange(215, 260)
        r = q - 40
        speeds = np.array([0.87, 1.0, 1.15])
        one_each = np.concatenate([spans.windows(q, r, table, v) for v in speeds])
        together = spans.windows(np.tile(q, 3), np.tile(r, 3), table, np.repeat(speeds, len(q)))
        np.testing.assert_array_equal(together, one_each)
        assert np.isneginf(one_each).any() and np.isfinite(one_each).any()  # lines through the stop, and not

    def test_no_window_before_the_first_frame(self):
        spans = self._spans({300: 0.35, 290: 0.35, 280: 0.35})
        win = spans.windows(np.array([300]), np.array([15]), None)  # the third window's pair would be (280, -5)
        assert not np.isnan(win[0, :2]).any() and np.isnan(win[0, 2])

    def test_windows_on_a_faster_line_fuse_at_its_speed(self):
        """A revisit twice as fast as the map: its windows lie on the line through ``(300, 100)`` at 2x (the earlier
        windows end at keyframes 80 and 60, each scored on lines at twice the filter's velocities); at the map's speed
        only the query's own window reads (keyframes 90 and 80 do not), and one window cannot accept."""
        from retrieval.decision import EmpiricalTail, MeasuredTail, ScoreSpans

        on_line = {(300, 100, 2.0), (290, 80, 2.0), (280, 60, 2.0)}

        def score(q, r, source, speed=1.0):  # 0.35 on the 2x line's windows, scored at 2x; the null's median else
            speeds = np.broadcast_to(np.asarray(speed, np.float64), np.shape(q))  # one speed, or one a pair
            return np.array([0.35 if (int(a), int(b), float(v)) in on_line else 0.0 for a, b, v in zip(q, r, speeds)],
                            np.float64)

        def spans(speeds):
            return ScoreSpans(score, 10, EmpiricalTail(np.linspace(-0.1, 0.1, 9999)), [MeasuredTail(np.zeros(0))] * 3,
                              1e4 * len(speeds), speeds)

        accept_at, q, r = -math.log10(0.05), np.array([300]), np.array([100])
        assert spans((1.0,)).confidences(q, r, None)[0] < accept_at
        both = spans((1.0, 2.0))
        assert both.confidences(q, r, None)[0] >= accept_at
        value, frames, speed = both.best_run(300, 100, None)
        assert value >= accept_at and frames == 30 and speed == 2.0
        assert np.isfinite(both.fused_best(q, r, None)).all() and both.fused_best(q, r, None)[0, 2] > 0

    def test_a_member_beaten_by_a_line_more_than_a_frame_off_is_not_on_the_run(self):
        """A member's own window on the run's line (99 -> 0) against the lines nearby: 1.25 decades where a line 5
        frames off reads 1.71 is within ``LOCALISE`` (localised) but not on the line (measured with KITTI 90 at 64x32
        and the encoder's input low-passed, an experiment: frame 99, the first pass's last, certified on frame 0); the
        same beaten by the line one frame off (the confirmation's slack) is."""
        from retrieval.decision import EmpiricalTail, ScoreSpans

        def spans(values):
            def score(q, r, source, speed=1.0):  # the window score by its (query, reference)
                return np.array([values.get((int(a), int(b)), 0.0) for a, b in zip(q, r)], np.float64)
            return ScoreSpans(score, 10, EmpiricalTail(np.linspace(-0.1, 0.1, 9999)), [], 1e4)

        def at(decades):  # the window score that reads ``decades`` against the null (uniform on [-0.1, 0.1])
            return 0.1 - 0.2 * 10 ** -decades

        q, r = np.array([99]), np.array([0])
        far = spans({(99, 0): at(1.25), (99, 5): at(1.71)})
        assert far.localised(q, r, None)[0] and not far.on_line(q, r, None)[0]
        assert spans({(99, 0): at(1.25), (99, 1): at(1.71)}).on_line(q, r, None)[0]
        assert not spans({(99, 0): 0.0, (99, 1): at(1.71)}).on_line(q, r, None)[0]  # beaten by more than LOCALISE

    def test_a_line_beaten_in_raw_score_by_a_line_nearby_is_not_localised(self):
        """A revisit 1.15x as fast as the map on the map's line (KITTI 90 at 64x32, measured: query 171 on the line
        through 79, its own window 0.32 there and 0.91 two frames on, the truth 4 frames on): both windows lie above
        every null sample, so their evidence is equal (saturated), but the raw scores say the query is not at 79. A
        line nearby within ``LOCAL_SPREAD`` null spreads (the null's 90th percentile above its median: 0.08 here) is
        no reason to refuse."""
        from retrieval.decision import LOCAL_SPREAD, EmpiricalTail, ScoreSpans

        def spans(values):
            def score(q, r, source, speed=1.0):
                return np.array([values.get((int(a), int(b)), 0.0) for a, b in zip(q, r)], np.float64)
            return ScoreSpans(score, 10, EmpiricalTail(np.linspace(-0.1, 0.1, 9999)), [], 1e4)

        q, r = np.array([171]), np.array([79])
        drifted = spans({(171, 79): 0.32, (171, 81): 0.91})
        assert drifted.spread == pytest.approx(0.08, abs=1e-3)
        assert not drifted.localised(q, r, None)[0] and not drifted.on_line(q, r, None)[0]
        near = 0.32 + LOCAL_SPREAD * 0.08 - 0.01
        assert spans({(171, 79): 0.32, (171, 81): near}).localised(q, r, None)[0]

    @staticmethod
    def _nordland(nordland_codes):
        """``(calibration, null rows, code table, filter)``: the score path calibrated on the real Nordland frames of
        the fixture (a summer and a winter stretch, raw codes)."""
        from cae.weights import load_encoder
        from retrieval.calibrate import Calibration, camera_moved, _null_scores, _score_path
        from retrieval.temporal import CodeTable, create_filter

        ids = np.array(sorted(nordland_codes), np.int64)
        codes = np.stack([nordland_codes[int(i)] for i in ids])
        table = CodeTable(codes.shape[1])
        for fid, code in zip(ids, codes):
            table.add(int(fid), code / np.linalg.norm(code))
        filt = create_filter({"name": "sequence"})
        null = _null_scores(ids, table, filt, 50, camera_moved(codes, load_encoder().still_cos), 25)
        cal = Calibration(tests={"score": 1e6}, expected_false_loops=0.1)
        _score_path(cal, null, filt, table)
        return cal, null, table, filt

    def test_no_p_value_below_its_sample(self, nordland_codes):
        """On real Nordland null window scores: one window, however high its score, claims at most
        ``log10(n + 1)`` decades, and ``m`` windows at most what ``m`` such windows give under the Gamma tail."""
        from retrieval.decision import EmpiricalTail

        cal, null, table, filt = self._nordland(nordland_codes)
        n = len(cal.samples["score_null"])
        assert n == len(null) > 500 and EmpiricalTail(null[:, 2]).max_evidence == pytest.approx(math.log10(n + 1))
        tests = cal.tests["score"]
        assert cal.score_confidence(10.0) == pytest.approx(math.log10(n + 1) - math.log10(tests))  # far past the max
        assert cal.thresholds()["score"] is None  # one window cannot certify the run's tests: it never decides alone
        spans = cal.score_spans(filt)
        top = spans.span_confidences(np.array([250]), np.array([180]), _HighSource())[0]
        for m, value in enumerate(top, 1):
            assert value <= -math.log10(tests) - gamma_log10_sf(m, m * math.log10(n + 1)) + 1e-9

    def test_a_line_a_few_frames_off_is_not_localised(self, nordland_codes):
        """Winter 755 is summer 255 (Nordland, 500 frames on): the line 3 frames off still reads the revisit in its
        earlier windows, but the query's own window says it is not there."""
        cal, _, table, filt = self._nordland(nordland_codes)
        spans = cal.score_spans(filt)
        assert spans.localised(np.array([755, 755]), np.array([255, 252]), table).tolist() == [True, False]

    def test_calibrated_on_real_frames_at_64x32(self, tmp_path_factory):
        from bench.camera import shrunk_sample
        from retrieval.calibrate import Calibration
        from retrieval.detect import calibrate_sequence
        from retrieval.sequences import open_sequence
        from retrieval.temporal import create_filter

        seq = open_sequence(shrunk_sample(tmp_path_factory.mktemp("s64") / "seq", (64, 32)))
        cal = calibrate_sequence(seq, {}, progress=False)
        assert cal.path == "score" and cal.spans["span"] == SPAN and cal.spans["window"] == 10
        assert cal.samples["score_fused"].shape == (len(cal.samples["score_null"]), SPAN)
        assert any("consecutive windows" in n for n in cal.notes)
        assert any(n.startswith("accept: score") for n in cal.notes)  # what a loop needs, said
        path = tmp_path_factory.mktemp("c") / "c.h5"
        cal.save(path)
        back = Calibration.load(path)
        assert back.spans == cal.spans and back.identity() == cal.identity()
        assert np.array_equal(back.samples["score_fused"], cal.samples["score_fused"], equal_nan=True)
        dec = back.decision(50, create_filter({}))
        assert dec.spans is not None and dec.spans.tests == cal.tests["score"]
        assert dec.reach == SPAN * 10 and dec.confirms  # an accepted run of windows certifies its frames


class _HighSource:
    """Every pair of frames identical (cosine 1): each window far above any null."""

    def pairs(self, queries: np.ndarray, refs: np.ndarray) -> np.ndarray:
        return np.ones(len(refs), np.float32)


class TestConfirmations:
    """A run accepted at frame t certifies its earlier members (delayed loops), once; a refused run certifies
    nothing. On the sample's true revisit at 160x120 (80 + j -> 29 + j, weak pairs: none passes alone)."""

    @staticmethod
    def _run(cal, inl, pairs):
        from retrieval.decision import Confirmations

        dec, conf = _decision(cal, speeds=MAP_SPEED), Confirmations()
        for (q, r), x in zip(pairs, inl):
            conf.add(q, {r: (0.0, f"c{q}")}, False)
            dec.commit(q, np.array([r]), np.array([x]))
        return dec, conf

    def test_accepted_run_reports_its_earlier_members_once(self, small):
        seq, cal = small
        pairs = [(80 + j, 29 + j) for j in range(3)]
        inl = TestFusedEvidence()._inliers(seq, pairs)
        dec, conf = self._run(cal, inl[:-1], pairs[:-1])
        q, r = pairs[-1]
        assert dec.confidences(q, np.array([r]), np.array([inl[-1]]), _NoSource())[0] >= cal.accept_at
        assert conf.confirm(dec, q, r, inl[-1]) == [(80, "c80"), (81, "c81")]
        read = []
        for name in ("run_members", "window_members"):
            setattr(dec, name, lambda *a, name=name: read.append(name) or [])
        assert conf.confirm(dec, q, r, inl[-1]) == []  # reported once
        assert not read  # every frame it could certify is a loop already: no member is read

    def test_refused_run_reports_nothing(self, small):
        seq, cal = small
        pairs = [(80 + j, 29 + j) for j in range(3)]
        inl = TestFusedEvidence()._inliers(seq, pairs)
        dec, conf = self._run(cal, inl[:-1], pairs[:-1])
        dec.tests *= 1e6  # the same run, a million times more hypotheses tested: no longer accepted
        q, r = pairs[-1]
        assert dec.confidences(q, np.array([r]), np.array([inl[-1]]), _NoSource())[0] < dec.accept_at
        assert conf.confirm(dec, q, r, inl[-1]) == []

    def test_a_revisits_first_frame_is_kept_for_its_run(self, small):
        """The first frame of a revisit has evidence of its own but no run yet (KITTI 90's frame 100 on frame 0): its
        confidence is ``UNSUPPORTED``, not a veto, so the run its next frames complete reports it; decided as the
        detector decides (each frame's confidences stored, ``max(value, VETO)``)."""
        from retrieval.decision import Confirmations

        seq, cal = small
        pairs = [(80 + j, 29 + j) for j in range(3)]
        inl = TestFusedEvidence()._inliers(seq, pairs)
        dec, conf = _decision(cal, single=False, speeds=MAP_SPEED), Confirmations()
        first = dec.confidences(80, np.array([29]), np.array([inl[0]]), _NoSource())[0]
        assert first == UNSUPPORTED < cal.accept_at  # not a loop alone, not vetoed
        for (q, r), x in zip(pairs[:-1], inl[:-1]):
            value = dec.confidences(q, np.array([r]), np.array([x]), _NoSource())[0]
            conf.add(q, {r: (max(value, Confirmations.VETO), f"c{q}")}, False)
            dec.commit(q, np.array([r]), np.array([x]))
        q, r = pairs[-1]
        assert dec.confidences(q, np.array([r]), np.array([inl[-1]]), _NoSource())[0] >= cal.accept_at
        assert [f for f, _ in conf.confirm(dec, q, r, inl[-1])] == [80, 81]

    def test_vetoed_or_already_looped_member_not_reported(self, small):
        from retrieval.decision import Confirmations

        seq, cal = small
        pairs = [(80 + j, 29 + j) for j in range(3)]
        inl = TestFusedEvidence()._inliers(seq, pairs)
        dec, conf = _decision(cal), Confirmations()
        conf.add(80, {29: (Confirmations.VETO, "c80")}, False)  # too recent then: its pair was not admissible
        conf.add(81, {30: (5.0, "c81")}, True)  # a loop already
        for (q, r), x in zip(pairs[:-1], inl[:-1]):
            dec.commit(q, np.array([r]), np.array([x]))
        assert conf.confirm(dec, 82, 31, inl[-1]) == []

    def test_score_path_member_one_frame_off_its_line(self):
        """Nordland's winter frames 806-817 wait in a station the summer train waited in too: the run accepted at
        818 -> 318 has members 808 -> 308 and 809 -> 309 on its line, refused then by the stop rule; an admissible
        keyframe one frame off the line (309 -> 310) is reported, two off (308 -> 310) is not; on the inlier path
        (verified pairs) only the member itself counts."""
        from retrieval.decision import Confirmations

        class Line:  # the score path's accepted run (``Decision.window_members`` on its line)
            pair_tail = None

            def window_members(self, query_id, ref, source):
                return [(808, 308), (809, 309)]

        class Verified:  # the inlier path's (``Decision.run_members``), its windows not deciding beside it
            pair_tail = object()

            def run_members(self, query_id, ref, inliers, source):
                return [(808, 308), (809, 309)]

            def window_members(self, query_id, ref, source):
                return []

        for decision, want in ((Line(), [(809, "c809")]), (Verified(), [])):
            conf = Confirmations()
            conf.add(808, {308: (Confirmations.VETO, "v808"), 310: (-3.0, "c808")}, False)
            conf.add(809, {309: (Confirmations.VETO, "v809"), 310: (-3.6, "c809")}, False)
            assert conf.confirm(decision, 818, 318, -1) == want

    def test_stream_reports_delayed_loops_and_detect_replays_them(self, small, tmp_path):
        """Through the API on real frames: the revisit's first frame, too weak alone, is reported once the run
        through it is accepted (on the later frame's result); the stored run replays to the same delayed loops."""
        from cae_lcd.core.images import read_image
        from cae_lcd.evaluation.ground_truth import read_loop_pairs
        from retrieval.detector import LoopDetector

        seq, cal = small
        truth = {tuple(p) for p in read_loop_pairs(seq / "loops.txt").tolist()}
        looped, confirmed = set(), {}
        with LoopDetector({"calibration": {"online": False}}, calibration=cal, database=tmp_path / "k.h5") as det:
            for i in range(100):
                res = det.process(read_image(seq / "image_0" / f"{i:06d}.png"), i)
                looped |= {i} if res.loop is not None else set()
                for q, cand in res.confirmed:
                    assert q < i and q not in looped and q not in confirmed  # not a loop yet, reported once
                    confirmed[q] = (cand.frame_id, cand.confidence)
                    assert cand.confidence == res.loop.confidence  # the accepting run's
            replayed = det.confirmed_loops(det.db.results())
        assert confirmed and all((q, r) in truth for q, (r, _) in confirmed.items())  # measured: 51 -> 1, at 52
        assert replayed.keys() == confirmed.keys()
        for q, (r, c) in replayed.items():
            assert r == confirmed[q][0] and c == pytest.approx(confirmed[q][1], abs=1e-4)  # stored as float32

    def test_a_run_does_not_certify_the_frame_before_its_revisit(self, kitti_sequences, tmp_path):
        """KITTI 90 at 64x32 (the score path; ``detect --lookahead``): two passes joined, the second (100-199)
        beginning where the first began. A run accepted on the line one frame off the revisit's (offset 99) reads the
        revisit's windows; its earliest member would be frame 99 on frame 0, the first pass's last frame, which is not
        that place. Its own window is beaten on a line nearby (``ScoreSpans.on_line``): not certified (it was, as a
        delayed loop, with the shipped weights, before members had to be localised: precision 0.990)."""
        from bench.aliasing import plain_folder
        from cae_lcd.evaluation.ground_truth import load_ground_truth
        from cae_lcd.evaluation.metrics import precision_recall
        from retrieval.detect import main as detect
        from retrieval.run_folder import RunFolder

        frames = sorted((kitti_sequences / "90" / "image_0").glob("*.png"))
        detect(plain_folder(tmp_path / "k90_64", frames, (64, 32)), tmp_path / "run",
               {"calibration": {"online": False}}, progress=False)
        loops = RunFolder(tmp_path / "run").read_loops()[:, :2].astype(np.int64)
        pr = precision_recall(loops, load_ground_truth(kitti_sequences / "90" / "loops.txt").pairs)
        assert 99 not in loops[:, 0].tolist()
        assert pr.precision == 1.0 and pr.recall >= 0.95

    def test_detect_writes_delayed_loops(self, small, tmp_path):
        """``detect`` on the same frames: the delayed loop is a row of loops.csv (the accepting run's confidence, at
        least the acceptance level), marked accepted in candidates.csv, counted in the summary."""
        from cae_lcd.evaluation.ground_truth import read_loop_pairs
        from retrieval.detect import main as detect
        from retrieval.run_folder import RunFolder

        seq, _ = small
        summary = detect(seq, tmp_path / "run", {}, progress=False)
        run = RunFolder(tmp_path / "run")
        loops = {int(r[0]): (int(r[1]), float(r[6])) for r in run.read_loops()}
        assert summary["confirmed"] >= 1 and 51 in loops  # measured: 51 -> 1, confirmed at frame 52
        assert loops[51][0] == 1 and loops[51][1] >= summary["calibration"]["accept_at_confidence"]
        truth = {tuple(p) for p in read_loop_pairs(seq / "loops.txt").tolist()}
        assert all((q, r) in truth for q, (r, _) in loops.items())  # precision 1.000


class TestBothPaths:
    """On a stream's inlier path the score path's fused windows decide beside it (``Decision``'s ``both``): a frame
    whose candidates do not verify (keypoints of night noise) is still found from its code and its sequence."""

    @staticmethod
    def _decision(both: bool) -> Decision:
        from retrieval.decision import EmpiricalTail, MeasuredTail, ScoreSpans

        windows = {(300, 100): 0.35, (290, 90): 0.35, (280, 80): 0.35}  # three agreeing windows on one line

        def score(q, r, source, speed=1.0):
            return np.array([windows.get((int(a), int(b)), 0.0) for a, b in zip(q, r)], np.float64)

        spans = ScoreSpans(score, 10, EmpiricalTail(np.linspace(-0.1, 0.1, 9999)), [MeasuredTail(np.zeros(0))] * 3,
                           1e4)
        pairs = EmpiricalTail(np.arange(100) % 10)  # hard negatives of 0-9 inliers
        return Decision(pairs, MeasuredTail(np.zeros(0)), 1e4, -math.log10(0.05), False, floor=12, spans=spans,
                        both=both)

    def test_unverified_windows_decide_beside_the_inlier_path(self):
        accept_at = -math.log10(0.05)
        assert self._decision(True).confidences(300, np.array([100]), np.array([-1]), None)[0] >= accept_at
        assert self._decision(False).confidences(300, np.array([100]), np.array([-1]), None)[0] == -math.inf
        assert self._decision(True).reach == SPAN * 10  # an accepted run of windows certifies its frames

    def test_where_geometry_accepts_a_candidate_it_says_which(self):
        """KITTI 90's narrower-lens revisit (measured with the thumbnail and random weights): its last frame's window
        line through keyframe 100, the joint of the two passes, outscored keyframe 99, verified with 64 inliers; the
        windows decide only a frame the inlier path does not."""
        dec = self._decision(True)
        dec.tests, dec.single = 1.0, True  # one verified pair may decide alone here
        accept_at = -math.log10(0.05)
        verified = dec.confidences(300, np.array([99, 100]), np.array([64, -1]), None)
        assert verified[0] >= accept_at and verified[1] == -math.inf
        unverified = dec.confidences(300, np.array([99, 100]), np.array([5, -1]), None)
        assert unverified[0] == -math.inf and unverified[1] >= accept_at

    def test_a_calibration_fitted_on_a_stream_lets_both_decide(self, small):
        _, cal = small
        assert not cal.decision(50).both  # calibrated before its run: the score path's nulls drawn in sample
        from retrieval.temporal import create_filter

        held = copy.copy(cal)
        held.score_null = {**cal.score_null, "held_out": 0.25}  # a stream's fit: drawn out of sample
        assert held.decision(50, create_filter({})).both


class TestRunsAtTheStreamsSpeed:
    """A revisit three times as fast as the map: frame ``q - d`` of the run sits at keyframe ``r - 3 d``, its offset
    drifting 2 frames a frame (``TOL`` holds one frame back only). Four frames of 20 inliers each (the sample's
    hardest negative at 160x120 holds 18)."""

    PAIRS = [(90 + j, 10 + 3 * j) for j in range(4)]

    def _last(self, cal, speeds):
        dec = _decision(cal, single=False, speeds=speeds)
        for q, r in self.PAIRS[:-1]:
            dec.commit(q, np.array([r]), np.array([20]))
        q, r = self.PAIRS[-1]
        return dec, dec.confidences(q, np.array([r]), np.array([20]), _NoSource())[0]

    def test_fused_on_the_line_of_its_speed(self, small):
        _, cal = small
        assert self._last(cal, MAP_SPEED)[1] < cal.accept_at  # measured: 0.29 (two frames on one offset)
        dec, value = self._last(cal, (1.0, 2.0, 3.0))
        assert value >= cal.accept_at  # measured: 2.00, the line's choice counted (tests x 3)
        assert dec.run_members(*self.PAIRS[-1], 20) == self.PAIRS[:-1]  # members on that line

    def test_every_line_is_counted_in_the_tests(self, small):
        _, cal = small
        one, three = _decision(cal, speeds=MAP_SPEED), _decision(cal, speeds=(1.0, 2.0, 3.0))
        assert three.tests == pytest.approx(3 * one.tests)
