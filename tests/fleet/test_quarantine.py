"""Damage stays with one robot (issue 29): a robot whose files cannot be read at start-up is quarantined (one log
line, its requests 503 with the reason, an admin reset releases it) and the others start and are served. The audit's
damages: camera.json holding ``{``, keyframes.h5 with a damaged header or cut in half, robots/R1 replaced by a file."""

from __future__ import annotations

import logging
import shutil

import pytest

from cae_lcd.fleet.client import FleetClient, FleetError
from cae_lcd.fleet.server import create_app

ADMIN = "quarantine-admin"


def damage_camera(folder):
    (folder / "camera.json").write_text("{")


def damage_header(folder):
    db = folder / "keyframes.h5"
    data = bytearray(db.read_bytes())
    data[:64] = b"\0" * 64
    db.write_bytes(bytes(data))


def cut_in_half(folder):
    db = folder / "keyframes.h5"
    db.write_bytes(db.read_bytes()[:db.stat().st_size // 2])


def replace_by_a_file(folder):
    shutil.rmtree(folder)
    folder.write_text("not a folder")


@pytest.mark.parametrize("damage", [damage_camera, damage_header, cut_in_half, replace_by_a_file])
def test_a_damaged_robot_is_quarantined_and_the_others_are_served(tmp_path, cae_descriptor, sample_poses, jpeg,
                                                                 damage, caplog):
    from fastapi.testclient import TestClient

    state = tmp_path / "state"
    app = create_app(state, ADMIN, descriptor=cae_descriptor)
    http, admin = TestClient(app), FleetClient("", ADMIN, client=TestClient(app))
    tokens = {name: admin.register(name) for name in ("R1", "R2")}
    for name in ("R2", "R1"):  # R2 first: the anchor, whose map every reply below expresses
        robot = FleetClient("", tokens[name], client=http)
        for i in range(4):
            robot.submit_keyframe(name, i, 0.1 * i, sample_poses[i], jpeg(i))
    app.state.service.close()
    damage(state / "robots" / "R1")

    with caplog.at_level(logging.ERROR, "cae_lcd.fleet.recognition"):
        app = create_app(state, ADMIN, descriptor=cae_descriptor)  # starts
    try:
        http = TestClient(app)
        admin = FleetClient("", ADMIN, client=http)
        r1, r2 = (FleetClient("", tokens[n], client=http) for n in ("R1", "R2"))
        lines = [r.getMessage() for r in caplog.records if "quarantined" in r.getMessage()]
        assert len(lines) == 1 and lines[0].startswith("robot R1 quarantined") and "\n" not in lines[0]
        with pytest.raises(FleetError, match="503: robot 'R1' is quarantined"):
            r1.submit_keyframe("R1", 4, 0.4, sample_poses[4], jpeg(4))
        with pytest.raises(FleetError, match="503"):
            r1.poses("R1")
        assert r2.submit_keyframe("R2", 4, 0.4, sample_poses[4], jpeg(4))  # the others are served
        assert sorted(r2.poses("R2", wait=True)) == [0, 1, 2, 3, 4]
        assert admin.reset("R1") == 0  # from its stored keyframes: recognition starts again, its poses stay
        assert r1.submit_keyframe("R1", 4, 0.4, sample_poses[4], jpeg(4))
        assert r1.loops("R1") == [] and isinstance(r1.poses("R1", wait=True), dict)  # served again
        assert list((state / "robots" / ".reset").iterdir())  # the damaged files kept aside for inspection
    finally:
        app.state.service.close()
