"""Progress lines where no bar shows: a logged run is never silent for
more than 30 s, even while one view of a view stage takes minutes."""

from __future__ import annotations

import io
import logging
import sys
import threading
from dataclasses import dataclass

import numpy as np
import pytest

from ptovs.progress import Heartbeat, Ticker
from ptovs.registry import REGISTRY, StageSpec, scene_input


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


# ------------------------------------------------------------ Ticker --


def test_ticker_line_has_rate_time_left_and_the_view_under_way():
    now = [100.0]
    tick = Ticker("extract-features trevi", 10, initial=2, every=30.0,
                  clock=lambda: now[0])  # fmt: skip
    assert tick.line() == "extract-features trevi: 2/10 views (20 %), ? s/view, ? left"
    now[0] = 190.0  # no view finished yet in this run: the first is under way
    assert tick.line().endswith("? left; 1:30 since the start")
    tick.update()  # 90 s for one view
    now[0] = 200.0
    # 7 views left at 90 s, 10 s of the next already spent: 10:20
    assert (
        tick.line()
        == "extract-features trevi: 3/10 views (30 %), 90.0 s/view, 10:20 left"
    )
    now[0] = 400.0  # a view slower than the rest: never less than 6 views' time
    assert tick.line() == (
        "extract-features trevi: 3/10 views (30 %), 90.0 s/view, 9:00 left; "
        "3:30 since the last view"
    )
    no_total = Ticker("x", None, every=30.0, clock=lambda: now[0])
    assert no_total.line() == "x: 0 views, ? s/view"


def test_ticker_is_quiet_and_threadless_when_a_bar_shows(caplog):
    with caplog.at_level(logging.INFO, logger="ptovs"):
        with Ticker("x", 3, every=0.001, enabled=False) as tick:
            assert tick._thread is None
            tick.update()
    assert not caplog.records


@dataclass(frozen=True)
class _SlowConfig:
    fail: bool = False


@dataclass(frozen=True)
class _SlowInputs:
    scene: object = scene_input()


_GATE: dict = {}


def _run_slow(inputs: _SlowInputs, config: _SlowConfig):
    """Two views; the second waits (up to 30 s) until a progress line shows
    that it is under way: a view longer than the line interval."""
    for i, view in enumerate(inputs.scene.train_views()[:2]):
        if i == 1:
            _GATE["seen"] = _GATE["ticked"].wait(30)
            if config.fail:
                raise RuntimeError("the stage failed mid-view")
        yield view.name, {"x": np.full(2, i, np.float32)}
    yield None, {"n": np.int64(2)}


class _Watch(logging.Handler):
    """Sets the gate when a line comes while the second view is under way."""

    def emit(self, record):
        if "1/2 views" in (m := record.getMessage()) and "since the last view" in m:
            _GATE["ticked"].set()


@pytest.fixture
def slow(monkeypatch, tmp_path, tiny_scene_dir):
    from ptovs import progress
    from ptovs.chain import Chain, RunContext
    from ptovs.locate import resolve_scene

    spec = StageSpec("toy-slow", 1, _SlowConfig, _SlowInputs, _run_slow, "views",
                     count=lambda inputs, config: 2)  # fmt: skip
    monkeypatch.setitem(REGISTRY, "toy-slow", spec)
    monkeypatch.setattr(progress, "EVERY_S", 0.01)
    _GATE.clear()
    _GATE["ticked"] = threading.Event()
    watch = _Watch()
    logging.getLogger("ptovs").addHandler(watch)

    def chain(*sets: str) -> Chain:
        ctx = RunContext(tmp_path / "work", {})
        return Chain(ctx, resolve_scene(ctx, None, tiny_scene_dir),
                     {"toy-slow": list(sets)})  # fmt: skip

    yield chain
    logging.getLogger("ptovs").removeHandler(watch)


def _tickers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == Ticker.THREAD]


def test_a_view_stage_logs_while_one_view_runs_and_leaves_no_thread(slow, caplog):
    from ptovs.chain import execute

    with caplog.at_level(logging.INFO, logger="ptovs"):
        execute(slow(), "toy-slow").close()
    assert _GATE["seen"]  # a line came while the second view was under way
    lines = [r.getMessage() for r in caplog.records if "since the" in r.getMessage()]
    assert lines[-1].startswith("toy-slow tiny_s0: 1/2 views (50 %), ")
    assert "s/view" in lines[-1] and lines[-1].endswith(" since the last view")
    assert not _tickers()
    with caplog.at_level(logging.INFO, logger="ptovs"):  # failed mid-view
        with pytest.raises(RuntimeError, match="mid-view"):
            execute(slow("fail=true"), "toy-slow")
    assert not _tickers()


def test_a_view_stage_under_a_terminal_bar_logs_no_progress(slow, caplog, monkeypatch):
    from ptovs.chain import execute

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    started = []
    real_start = threading.Thread.start

    def start(self):
        started.append(self.name)
        real_start(self)

    monkeypatch.setattr(threading.Thread, "start", start)
    _GATE["ticked"].set()  # the view does not wait for a line that never comes
    with caplog.at_level(logging.INFO, logger="ptovs"):
        execute(slow(), "toy-slow").close()
    assert "0/2 [" in term.getvalue()  # tqdm drew its bar there
    assert Ticker.THREAD not in started
    assert not [r for r in caplog.records if r.getMessage().startswith("toy-slow ti")]


def test_ticker_keeps_quiet_while_a_heartbeat_speaks(monkeypatch):
    from ptovs import progress

    monkeypatch.setattr(progress, "_BEAT", [float("-inf")])  # no earlier test's
    tick = Ticker("reconstruct t", 12, every=30.0)
    t0 = tick._said
    assert not tick.due(t0 + 29.0)
    assert tick.due(t0 + 30.0)  # no Heartbeat line yet
    now = [0.0]
    beat = Heartbeat("reconstruct t", 100, enabled=True, clock=lambda: now[0])
    now[0] = 30.0
    assert beat(10)  # training logs its own lines (stamped in real time)
    stamp = progress._BEAT[0]
    assert stamp >= t0
    assert not tick.due(stamp + 44.0)  # a beat within 1.5 intervals: quiet
    assert tick.due(stamp + 45.0)  # the heartbeat went silent: the ticker speaks
