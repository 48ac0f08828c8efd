"""bench.same_frames: every frame's result as text, the same for the same code (what a speed-up is compared on)."""

from __future__ import annotations

import json


def test_the_same_code_writes_the_same_frames(tmp_path):
    from bench.same_frames import main
    from tests.conftest import SAMPLE_DIR

    conf = {"search": {"exclude_recent": 4}}  # candidates from the fifth frame on
    first = main(SAMPLE_DIR, tmp_path / "a.json", frames=12, conf=conf)
    main(SAMPLE_DIR, tmp_path / "b.json", frames=12, conf=conf)
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()
    assert json.loads((tmp_path / "a.json").read_text()) == first and len(first) == 12
    assert [r["frame"] for r in first] == list(range(12)) and all(r["candidates"] for r in first[6:])
    assert isinstance(first[6]["candidates"][0][3], str)  # floats written by repr: every digit
