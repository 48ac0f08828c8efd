"""cae_lcd.fleet.recognition with robots that calibrate online (the default), on real KITTI frames: KITTI 90 as two
robots (A the first pass, frames 0-99; B the second, 100-199, which drives A's road again about 0.7 m beside it;
``sequences/90/loops.txt`` holds the true pairs), and KITTI 00 vs 07 as two robots that never meet.

``search.exclude_recent`` is 20 here (a warm-up of 40 keyframes, 2 exclusion windows): at the default 50 a robot of
100 keyframes is calibrated only at its last one, and nothing could be accepted on these sets.
"""

from __future__ import annotations

import numpy as np
import pytest

from cae_lcd.fleet.recognition import FleetRecognizer, certified_match

#: the default (online calibration), a shorter window; room for the edges of B's whole pass (a catch-up accepts the
#: overlap with 30 at once: the default cap)
ONLINE = {"detector": {"search": {"exclude_recent": 20}}, "max_edges_per_pair": 200}
WARM_UP = 40  #: keyframes of a robot's warm-up at that window (``retrieval.online``: 2 windows, at least 40)


@pytest.fixture(scope="module")
def kitti_frame(kitti_sequences, kitti_poses):
    """``kitti_frame(seq, i)`` -> (image, pose (4, 4), K)."""
    import cv2

    from cae_lcd.fleet.sim3 import Sim3
    from retrieval.sequences import read_kitti_calib

    poses = {s: kitti_poses(s) for s in ("00", "07", "90")}
    calib = {s: read_kitti_calib(kitti_sequences / s / "calib.txt") for s in ("00", "07", "90")}
    return lambda seq, i: (cv2.imread(str(kitti_sequences / seq / "image_0" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED),
                           Sim3.from_pose(poses[seq][i]).matrix(), calib[seq])


@pytest.fixture(scope="module")
def truth(kitti_sequences):
    """KITTI 90's true pairs, unordered (``loops.txt``, the 200-frame indexing: the keyframe ids here)."""
    rows = np.loadtxt(kitti_sequences / "90" / "loops.txt", dtype=np.int64).reshape(-1, 2)
    return {frozenset(map(int, r)) for r in rows}


def feed(rec, kitti_frame, frames):
    """Streams ``(robot, seq, i)`` (keyframe id ``i``); returns ``[(robot, i, Recognition, deciding)]``, ``deciding``:
    whether the robot's detector decided with a calibration after that keyframe (its identity, else None)."""
    out = []
    for robot, seq, i in frames:
        image, pose, K = kitti_frame(seq, i)
        found = rec.process(robot, i, float(i), pose, image, K)
        cal = rec.robots[robot].detector.deciding_calibration
        out.append((robot, i, found, None if cal is None else cal.identity()))
    return out


def searched(rec, robot, ids):
    """``{keyframe: (the other robots' top keyframes, scores)}``: the fleet memory searched with ``robot``'s stored
    keyframes ``ids`` (their raw codes made into the memory's entries)."""
    det = rec.robots[robot].detector
    codes = {fid: code for fid, code, _, _ in det.db.search_entries(features=False) if fid in ids}
    return {fid: rec.places.search(robot, rec.places.entry(code), 3) for fid, code in codes.items()}


@pytest.fixture(scope="module")
def split90(tmp_path_factory, kitti_frame, cae_descriptor):
    """A after frames 0-99, then B after 100-189; the recognizer closed and opened again (a restart, the accepted
    overlaps and edges resumed) and B after 190-199."""
    state = tmp_path_factory.mktemp("fleet_online")
    rec = FleetRecognizer(state, ONLINE, descriptor=cae_descriptor)
    run = feed(rec, kitti_frame, [("A", "90", i) for i in range(100)] + [("B", "90", i) for i in range(100, 190)])
    before = {"search": searched(rec, "B", set(range(100, 190))),
              "rule": rec._cross_rule(rec.robots["B"], rec.robots["A"]),
              "identity": {n: rec.robots[n].detector.deciding_calibration.identity() for n in ("A", "B")},
              "certified": {n: certified_match(rec.robots[n].detector.deciding_calibration, 20) for n in ("A", "B")},
              "exported": {n: rec.export(n) for n in ("A", "B")}}  # what another Ray worker adopts
    rec.close()
    rec = FleetRecognizer(state, ONLINE, descriptor=cae_descriptor)
    rec.resume([o for *_, f, _ in run for o in f.overlaps], [e for *_, f, _ in run for e in f.edges])
    after = {"search": searched(rec, "B", set(range(100, 190))),
             "identity": {n: rec.robots[n].detector.deciding_calibration.identity() for n in ("A", "B")}}
    after["run"] = feed(rec, kitti_frame, [("B", "90", i) for i in range(190, 200)])
    rec.close()
    return run, before, after


def test_a_robots_warm_up_accepts_nothing(split90):
    """In each robot's warm-up (its first 40 keyframes, the last one fitting) its detector decides nothing, and no
    edge or overlap comes, though B's second pass drives A's road from its first keyframe."""
    run, _, _ = split90
    for robot, start in (("A", 0), ("B", 100)):
        mine = [(i, found, deciding) for r, i, found, deciding in run if r == robot]
        warm = [(i, found, deciding) for i, found, deciding in mine if i < start + WARM_UP - 1]
        assert len(warm) == WARM_UP - 1 and all(deciding is None for *_, deciding in warm)
        assert not [e for _, found, _ in warm for e in found.edges] and not [o for _, f, _ in warm for o in f.overlaps]
        assert all(deciding is not None for i, _, deciding in mine if i >= start + WARM_UP)


def test_each_robot_decides_with_the_calibration_of_its_own_stream(split90):
    """After its warm-up each robot's detector decides with a calibration fitted on its own stream (refitted as it
    grows); the cross-robot rule is the stricter of the two robots' certified matches, not a fixed 50 inliers."""
    run, before, _ = split90
    a_fits = {deciding for r, _, _, deciding in run if r == "A" and deciding is not None}
    assert len(a_fits) >= 2  # fitted at the end of the warm-up, refitted at 80 keyframes
    assert before["identity"]["A"] != before["identity"]["B"]
    (ia, ra), (ib, rb) = before["certified"]["A"], before["certified"]["B"]
    assert before["rule"] == (max(ia, ib), max(ra, rb, 3))
    assert 12 <= before["rule"][0] < 50  # above every hard negative of both streams (KITTI 90 at 384 px: 30-40)


def test_the_fleet_memory_keeps_one_code_space_across_refits(split90, truth):
    """A's entries from its warm-up (keyframes 0-39, its detector then searching the weights' whitening) and from
    after its fits (40-99, its detector in its stream's whitening) are in the memory's one space: B's keyframes
    find their true place in A's among the top 3 of the memory, on both sides."""
    _, before, _ = split90
    hits = {fid: any(frozenset((fid, int(k))) in truth for k in found["A"][0]) for fid, found in
            before["search"].items() if "A" in found}
    early = [ok for fid, ok in hits.items() if fid < 100 + WARM_UP]
    late = [ok for fid, ok in hits.items() if fid >= 100 + WARM_UP]
    assert len(early) + len(late) == 90 and np.mean(early) >= 0.9 and np.mean(late) >= 0.9


def test_a_cross_robot_overlap_is_accepted_on_the_calibrated_rule(split90, truth):
    """The overlap is accepted once, no earlier than B's first certified keyframe (its catch-up matches the keyframes
    of its warm-up then); every overlap edge is a true pair."""
    run, before, after = split90
    overlaps = [(i, o) for _, i, found, _ in run for o in found.overlaps]
    assert len(overlaps) == 1 and {overlaps[0][1].robot_a, overlaps[0][1].robot_b} == {"A", "B"}
    assert overlaps[0][0] >= 100 + WARM_UP - 1
    edges = [e for _, _, found, _ in run + after["run"] for e in found.edges]
    assert len(edges) >= 5 and {e.kind for e in edges} == {"overlap"}
    assert all(frozenset((e.keyframe_a, e.keyframe_b)) in truth for e in edges)


def test_a_restart_resumes_the_calibrations_and_the_memory(split90, truth):
    """Opened again, each robot decides at once with the calibration it had (no second warm-up), the memory is
    rebuilt with the same entries (the same search results), and B's next keyframes add overlap edges (no second
    overlap record)."""
    _, before, after = split90
    assert after["identity"] == before["identity"]
    assert sorted(after["search"]) == sorted(before["search"])
    for fid, found in before["search"].items():
        again = after["search"][fid]
        assert sorted(again) == sorted(found)
        for robot in found:
            np.testing.assert_array_equal(again[robot][0], found[robot][0])
            np.testing.assert_allclose(again[robot][1], found[robot][1], atol=1e-6)
    resumed = after["run"]
    assert all(deciding == before["identity"]["B"] for *_, deciding in resumed)
    edges = [e for _, _, found, _ in resumed for e in found.edges]
    assert edges and all(e.kind == "overlap" and frozenset((e.keyframe_a, e.keyframe_b)) in truth for e in edges)
    assert not [o for _, _, found, _ in resumed for o in found.overlaps]


def test_an_adopting_recognizer_holds_the_robots_rule_and_entries(split90, tmp_path, cae_descriptor):
    """As another Ray worker: a recognizer owning neither robot adopts their exported keyframes; it holds the pair's
    calibrated rule as their owner had it, and their entries in the memory's one space (the same search results)."""
    _, before, _ = split90
    rec = FleetRecognizer(tmp_path, ONLINE, descriptor=cae_descriptor, owns=lambda name: False)
    for name, shared in before["exported"].items():
        rec.adopt(name, shared)
    rule = rec._cross_rule(rec.robots["B"], rec.robots["A"])
    found = {k: rec.places.search("B", kf.entry, 3) for k, kf in before["exported"]["B"]}
    rec.close()
    assert rule == before["rule"]
    for fid, hits in before["search"].items():
        np.testing.assert_array_equal(found[fid]["A"][0], hits["A"][0])


def test_robots_that_never_meet_have_no_overlap_once_calibrated(tmp_path, kitti_frame, cae_descriptor):
    """KITTI 00 (A) and 07 (B), interleaved, 100 keyframes each: both calibrated for their last 60, the calibrated
    cross-robot rule in force, and no overlap accepted by it (no run of certified matches), no overlap edge."""
    rec = FleetRecognizer(tmp_path, ONLINE, descriptor=cae_descriptor)
    run = feed(rec, kitti_frame, [(r, s, i) for i in range(100) for r, s in (("A", "00"), ("B", "07"))])
    rule, accepted = rec._cross_rule(rec.robots["A"], rec.robots["B"]), rec.tracker.accepted("A", "B")
    rec.close()
    assert rule is not None and all(deciding is not None for _, i, _, deciding in run if i >= WARM_UP)
    assert not accepted  # no run of certified matches (an edge would also need a similarity from 3D points)
    assert not [e for *_, found, _ in run for e in found.edges if e.kind == "overlap"]
    assert not [o for *_, found, _ in run for o in found.overlaps]


def meet_in_warm_up(rec, kitti_frame):
    """A: KITTI 90 frames 0-39 (ids 0-39) then 07 frames 0-79 (ids 40-119); B: 90 frames 100-139 (ids 100-139, A's
    road again) then 07 frames 80-159 (ids 140-219); interleaved, all with 90's intrinsics (a robot keeps its
    first). They meet only in their first 40 keyframes, where neither is certified yet. Returns every keyframe's
    ``Recognition``."""
    a = [("A", "90", i) for i in range(40)] + [("A", "07", i) for i in range(80)]
    b = [("B", "90", i) for i in range(100, 140)] + [("B", "07", i) for i in range(80, 160)]
    ids = {"A": iter(range(120)), "B": iter(range(100, 220))}
    found = []
    for robot, seq, i in [f for pair in zip(a, b) for f in pair]:
        image, pose, _ = kitti_frame(seq, i)
        found.append(rec.process(robot, next(ids[robot]), float(i), pose, image, kitti_frame("90", 0)[2]))
    rec.close()
    return found


def test_robots_that_met_in_their_warm_ups_are_caught_up(tmp_path, kitti_frame, cae_descriptor, truth):
    """Two robots whose only common road is in their warm-ups (a fleet leaving one depot): when the second is first
    certified, its earlier keyframes are matched against the first's (``cross.catch_up``) and the overlap is
    accepted, every overlap edge a true pair of the common road; without the catch-up nothing is ever found."""
    found = meet_in_warm_up(FleetRecognizer(tmp_path / "on", ONLINE, descriptor=cae_descriptor), kitti_frame)
    overlaps = [o for f in found for o in f.overlaps]
    edges = [e for f in found for e in f.edges if e.kind == "overlap"]
    assert len(overlaps) == 1 and len(edges) >= 5
    assert all({e.robot_a, e.robot_b} == {"A", "B"} for e in edges)
    pairs = [(e.keyframe_a, e.keyframe_b) if e.robot_a == "A" else (e.keyframe_b, e.keyframe_a) for e in edges]
    assert all(a < 40 and 100 <= b < 140 and frozenset((a, b)) in truth for a, b in pairs)
    off = {**ONLINE, "cross": {"catch_up": 0}}
    found = meet_in_warm_up(FleetRecognizer(tmp_path / "off", off, descriptor=cae_descriptor), kitti_frame)
    assert not [o for f in found for o in f.overlaps] and not [e for f in found for e in f.edges if e.kind == "overlap"]


def test_delayed_loops_become_loop_edges_once(tmp_path, kitti_frame, cae_descriptor, truth, monkeypatch):
    """One robot on KITTI 90 frames 0-79 then 100-119 (its second pass from the start): the run that accepts the
    revisit certifies its earlier frames (``FrameResult.confirmed``); each is offered once as a loop edge (made where
    its similarity can be estimated: here the revisit's first frames have too few 3D points, their nearest stored
    neighbour being frame 79), every edge a true pair."""
    rec = FleetRecognizer(tmp_path, ONLINE, descriptor=cae_descriptor)
    feed(rec, kitti_frame, [("A", "90", i) for i in range(80)])
    det, confirmed, offered = rec.robots["A"].detector, [], []
    real, add = det.process, FleetRecognizer._add_edge
    det.process = lambda *a, **kw: (lambda res: confirmed.extend(res.confirmed) or res)(real(*a, **kw))
    monkeypatch.setattr(FleetRecognizer, "_add_edge", lambda self, out, kind, a, b, check:
                        offered.append((kind, a[1], b[1])) or add(self, out, kind, a, b, check))
    run = feed(rec, kitti_frame, [("A", "90", i) for i in range(100, 120)])
    rec.close()
    loops = [(e.keyframe_a, e.keyframe_b) for _, i, found, _ in run for e in found.edges if e.kind == "loop"]
    delayed = {(c.frame_id, q) for q, c in confirmed}
    assert confirmed and delayed <= {(a, b) for kind, a, b in offered if kind == "loop"}  # each offered
    assert len([o for o in offered if o[0] == "loop"]) == len({o for o in offered if o[0] == "loop"})  # once
    assert loops and len(loops) == len(set(loops)) and all(frozenset(pair) in truth for pair in loops)