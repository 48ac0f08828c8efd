"""``bench.online_detect``: ``cae-lcd detect`` with the default conf and the API stream, on the bundled sample, write
the same loops (the comparison the BENCHMARKS.md table reports)."""

from bench.online_detect import compare


def test_detect_and_the_api_stream_write_the_same_loops(sample_dir, tmp_path):
    row = compare(sample_dir, tmp_path / "run")
    assert row["same"] and row["detect_loops"] == row["stream_loops"] >= 45
    assert row["precision"] == row["stream_precision"] == 1.0
    assert row["stream_r10"] >= row["stream_recall"] > 0.9  # the stream's own candidates, ranked as it ranked them
    assert row["detect_ms"] >= row["detect_calibration_ms"] > 0
    assert row["detect_whole_ms"] > row["detect_ms"] and row["sift_ms"] > 0  # the whole run: frames, edges too
    assert 0 < row["detect_edges_ms"] < row["detect_whole_ms"] - row["detect_ms"] + 1e-6  # the edges' share in it
