"""``cae-lcd fleet-demo``: a short run of the real demo (a server thread and two robot threads on loopback, KITTI 00
frames) must merge robot B with the targets' accuracy; the negative run (00 against 07) must find no overlap."""

from __future__ import annotations

import json

import pytest

from cae_lcd.cli.fleet_demo import DEFAULT_KITTI
from cae_lcd.cli.main import build_parser, main
from cae_lcd.core.cli import api_defaults
from cae_lcd.fleet.demo import run_demo


class TestFleetDemoCommand:
    def test_cli_defaults_equal_api_defaults(self):
        args = build_parser().parse_args(["fleet-demo", "--out", "X"])
        d = api_defaults(run_demo)
        assert (args.frames, args.negative, args.hostile) == (d["frames"], d["negative"], d["hostile"])
        assert (DEFAULT_KITTI / "poses" / "00.txt").exists()

    def test_a_short_run_merges_robot_b_within_the_targets_and_a_hostile_robot_moves_nothing(self, tmp_path):
        assert main(["fleet-demo", "--out", str(tmp_path), "--frames", "40", "--hostile"]) == 0
        s = json.loads((tmp_path / "fleet_demo.json").read_text())
        assert s["format_version"] == 1 and s["mode"] == "overlap" and s["merged"]
        assert s["rotation_error_deg"] < 2.0 and s["scale_error_pct"] < 5.0 and s["translation_error_pct"] < 2.0
        assert len(s["overlaps"]) == 1 and s["overlap_edges"] > 0
        assert (tmp_path / "trajectories.png").stat().st_size > 10_000
        h = s["hostile"]  # a third robot streaming random poses, noise and replayed frames at the same time
        assert h["keyframes"] == 10 and h["moved_m"]["A"] < 0.1 and h["moved_m"]["B"] < 0.1
        assert h["errors_with_H"]["rotation_error_deg"] < 2.0 and h["errors_with_H"]["translation_error_pct"] < 2.0

    def test_robots_that_never_meet_give_no_overlap(self, tmp_path):
        assert main(["fleet-demo", "--out", str(tmp_path), "--frames", "30", "--negative"]) == 0
        s = json.loads((tmp_path / "fleet_demo.json").read_text())
        assert s["mode"] == "negative" and s["false_overlaps"] == 0 and not s["merged"]

    def test_a_missing_dataset_fails_with_one_line(self, tmp_path, capsys):
        assert main(["fleet-demo", "--out", str(tmp_path), "--kitti", str(tmp_path / "none")]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and err.strip().startswith("error: ")


@pytest.mark.parametrize("frames", [0, -2])
def test_too_few_frames_are_refused(tmp_path, capsys, frames):
    assert main(["fleet-demo", "--out", str(tmp_path), "--frames", str(frames)]) == 2
    assert "--frames" in capsys.readouterr().err
