"""The keyframe store's write-ahead log: records round-trip, a torn or damaged tail is never used."""

import numpy as np

from retrieval.wal import MAGIC, FrameLog, encode_record, read_records


def _records(path, n=3):
    log = FrameLog(path)
    for i in range(n):
        log.append({"frame_id": i, "source": "ab"}, {"code": np.arange(4, dtype=np.float16) + i,
                                                     "empty": np.zeros((0, 128), np.uint8)})
    log.close()


def test_round_trip(tmp_path):
    _records(tmp_path / "x.log")
    got = list(read_records(tmp_path / "x.log"))
    assert [m["frame_id"] for m, _ in got] == [0, 1, 2]
    np.testing.assert_array_equal(got[2][1]["code"], np.arange(4, dtype=np.float16) + 2)
    assert got[0][1]["code"].dtype == np.float16 and got[0][1]["empty"].shape == (0, 128)


def test_torn_tail_ignored(tmp_path):
    path = tmp_path / "x.log"
    _records(path)
    whole = path.read_bytes()
    extra = encode_record({"frame_id": 3}, {"code": np.ones(4, np.float16)})
    for cut in (1, 10, len(extra) - 1):  # a kill in the middle of the last write
        path.write_bytes(whole + extra[:cut])
        assert [m["frame_id"] for m, _ in read_records(path)] == [0, 1, 2]


def test_damaged_record_stops_the_replay(tmp_path):
    path = tmp_path / "x.log"
    _records(path)
    data = bytearray(path.read_bytes())
    second = data.index(MAGIC, 1)
    data[second + 40] ^= 0xFF  # a bit flip in the second record's payload
    path.write_bytes(bytes(data))
    assert [m["frame_id"] for m, _ in read_records(path)] == [0]


def test_missing_log_is_empty(tmp_path):
    assert list(read_records(tmp_path / "none.log")) == []
    log = FrameLog(tmp_path / "e.log")
    log.close(remove=True)
    assert not (tmp_path / "e.log").exists()
