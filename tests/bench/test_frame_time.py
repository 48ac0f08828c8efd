"""The issue-18 speed benchmark's pieces (the measurement itself is ``python -m bench.frame_time``, not a test)."""

import numpy as np

from bench.frame_time import busy_neighbour, report, sift_yardstick, write_section


def _summary(median, wall_s, cal_s=None):
    s = {"ms_per_frame": {"total": {"median": median, "p90": median * 2}, "insert": {"median": 0.25, "p90": 1}},
         "wall_s": wall_s, "frames": 200, "peak_rss_bytes": 700 * 2**20, "loops": 100, "stored_bytes": 1_600_000}
    if cal_s is not None:
        s["seconds"] = {"calibration": cal_s, "frames": wall_s - cal_s}
    return s


def test_report_ratios():
    res = {"sequence": "kitti/90", "before_rev": "abc", "same_loops": True,
           "system": {"cores": 2, "cpu": "cpu", "load_avg": (1, 1, 1)},
           "quiet": {"sift_ms": 20.0, "new": _summary(10.0, 4.0, 0.5), "before": _summary(40.0, 20.0),
                     "api": {"median": 15.0, "p90": 30.0, "loops": 100},
                     "new_calibration_given": _summary(9.0, 3.6, 0.0)},
           "busy": {"sift_ms": 30.0, "new": _summary(15.0, 6.0, 1.0)}}
    text = report(res)
    assert "| this code, no neighbour added | 10.0 | 0.50x | 20.0 | 1.00x | 12 % | 0.25 | 8.0 | 700 | 100 |" in text
    assert "1.50x the run without it" in text and "median ms/frame 4.0x, wall time 5.0x" in text
    assert "identical: True" in text and "what it adds to the run: 10 %" in text


def test_write_section_replaces_its_own_part(tmp_path):
    path = tmp_path / "B.md"
    path.write_text("# head\n")
    write_section(path, "one")
    write_section(path, "two")
    text = path.read_text()
    assert text.startswith("# head\n") and "two" in text and "one" not in text and text.count("frame_time:begin") == 1


def test_yardstick_and_neighbour(sample_image):
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        assert sift_yardstick([sample_image(0), sample_image(1)]) > 0  # on one core, whatever the policy before
        assert cv2.getNumThreads() == 2  # the policy as it was
    finally:
        cv2.setNumThreads(before)
    with busy_neighbour() as proc:
        assert proc.poll() is None  # running
    assert proc.poll() is not None  # stopped


def test_report_lists_each_api_pass():
    passes = {name: {"median": m, "p90": 2 * m, "first_half": 9.0, "second_half": m + 5, "loops": 100}
              for name, m in (("back to back", 25.0), ("at the camera rate", 18.0))}
    res = {"sequence": "kitti/90", "before_rev": "abc", "same_loops": True,
           "system": {"cores": 2, "cpu": "cpu", "load_avg": (1, 1, 1)},
           "quiet": {"sift_ms": 20.0, "new": _summary(10.0, 4.0, 0.5), "api": passes,
                     "new_calibration_given": _summary(9.0, 3.6, 0.0)},
           "busy": {"sift_ms": 30.0, "new": _summary(15.0, 6.0, 1.0)}}
    text = report(res)
    assert "back to back: median 25.0 ms (first half of the frames 9.0, second half, the revisits, 30.0)" in text
    assert "at the camera rate: median 18.0 ms" in text
    passes["back to back"].update(second_half_gate=1.5, second_half_encode=6.0, second_half_features=2.0,
                                  second_half_verify=5.0)
    assert "the revisits, 30.0: gate 1.5, encode 6.0, features 2.0, verify 5.0)" in report(res)


def test_api_passes_interleaved(sample_seq, sample_image, monkeypatch):
    import bench.frame_time as ft

    monkeypatch.setattr(ft, "API_RUNS", {"back to back": ({}, False), "paced": ({}, True)})
    images = [sample_image(i) for i in range(3)]
    out = ft.api_per_frame(images, sample_seq.K, None, np.array([0.0, 0.05, 0.1]), rounds=2,
                           extra={"512 px": ({"calibration": {"features_px": None}}, False, None)})
    assert set(out) == {"back to back", "paced", "512 px"}
    assert all(a["median"] > 0 and a["loops"] == 0 and set(a) >= {"p90", "first_half", "second_half"}
               and a["second_half_encode"] > 0 for a in out.values())
