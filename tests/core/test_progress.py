"""Progress in a log: a generator wrapped in ``Counted`` has a total and an ETA (the calibration's read pass had
neither), the rate is the average since the start (work arriving in batches read 400000 frames/s), one line a step."""

from __future__ import annotations

import logging
import re
import time

from cae_lcd.core.progress import LOG_STEP_PERCENT, Counted, LogLines


def _lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "cae_lcd.progress"]


def test_a_counted_generator_has_a_total_and_an_eta(caplog):
    caplog.set_level(logging.INFO, "cae_lcd.progress")
    for _ in LogLines(Counted((i for i in range(40)), 40), desc="read", unit="frame", mininterval=0):
        time.sleep(0.002)
    lines = _lines(caplog)
    assert len(lines) == 100 // LOG_STEP_PERCENT, lines
    assert all(re.search(r"/40 \[\d\d:\d\d<\d\d:\d\d, ", ln) for ln in lines), lines
    assert lines[-1].startswith("read: 100% 40/40")


def test_the_rate_of_bursty_work_is_the_average(caplog):
    """Frames arrive in batches of 10 after a 50 ms wait (as from an encoder working ahead): 200 frames/s, not the
    rate within a burst."""
    caplog.set_level(logging.INFO, "cae_lcd.progress")
    bar = LogLines(total=50, desc="encode", unit="frame", mininterval=0)
    for _ in range(5):
        time.sleep(0.05)
        for _ in range(10):
            bar.update(1)
    bar.close()
    rates = [float(re.search(r", ([\d.]+)frame/s", ln).group(1)) for ln in _lines(caplog)]
    assert rates and all(50 < r < 400 for r in rates), rates
