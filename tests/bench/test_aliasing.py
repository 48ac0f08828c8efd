"""bench.aliasing: the issue-17 table shows the calibration's own share of the run beside its share with the run's
work it does ahead (``summary.json`` ``seconds``)."""

from __future__ import annotations

from bench.aliasing import aliasing_table


def test_calibration_share_own_and_with_the_runs_work():
    res = {"KITTI 90": {"frames": 200, "loops": 100, "precision": 1.0, "recall": 1.0, "ms": 15.5, "path": "inliers",
                        "wall_s": 10.0, "calibration_s": 5.0, "calibration_own_s": 1.2},
           "a run with the calibration given": {"frames": 200, "loops": 0, "precision": 1.0, "recall": None,
                                                "ms": None, "path": "none", "wall_s": 4.0, "calibration_s": 0.0,
                                                "calibration_own_s": None}}
    table = aliasing_table(res)
    assert "| KITTI 90 | 200 | 100 | 1.000 | 1.000 | 15.5 | 12 % / 50 % | inliers |" in table
    assert "| n/a (no revisit) | n/a | n/a | none |" in table
    assert "own / with the run's work" in table.splitlines()[0]
