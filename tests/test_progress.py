"""Progress lines where no bar shows: a logged run is never silent for
more than 30 s."""

from __future__ import annotations

import logging

from ptovs.progress import Heartbeat


def test_heartbeat_logs_every_30_s_with_rate_and_time_left(caplog):
    now = [0.0]
    beat = Heartbeat(
        "reconstruct", 1000, initial=100, enabled=True, clock=lambda: now[0]
    )
    with caplog.at_level(logging.INFO, logger="ptovs"):
        assert not beat(150)  # too soon
        now[0] = 30.0
        assert beat(400, loss="0.0123", psnr="21.50")
        now[0] = 45.0
        assert not beat(500)
        now[0] = 60.0
        assert beat(700)
        now[0] = 61.0
        assert beat(1000)  # the last step always shows
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3
    # 300 steps in 30 s: 10 it/s, 600 left: 1:00
    assert (
        lines[0]
        == "reconstruct: 400/1000 (40 %), loss 0.0123, psnr 21.50, 10.00 it/s, 1:00 left"
    )
    assert (
        lines[2].startswith("reconstruct: 1000/1000 (100 %)")
        and "0:00 left" in lines[2]
    )


def test_heartbeat_is_quiet_when_a_bar_shows(caplog):
    beat = Heartbeat("x", 10, enabled=False, clock=lambda: 1e9)
    with caplog.at_level(logging.INFO, logger="ptovs"):
        assert not beat(10)
    assert not caplog.records
