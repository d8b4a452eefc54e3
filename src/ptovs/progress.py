"""Progress where no progress bar shows: a log line at least every 30 s.

tqdm draws nothing when stderr is not a terminal (a log file, a batch job), so a
long stage would be silent for many minutes. `Heartbeat` fills that gap in loops
of many short steps: when the bar is off, every `every` seconds it logs the step,
the caller's figures (loss, PSNR, ...), the rate and the time left.

    beat = Heartbeat("reconstruct", total=2500, initial=step)
    for ...:
        beat(step, loss=f"{lo:.4f}", psnr=f"{ps:.2f}")

`Ticker` is for loops whose one step may take minutes (a view of extract-features
with a large encoder): a background thread logs the last known progress every
`every` seconds while the loop runs, even in the middle of a step.

    with Ticker("extract-features trevi", total=n, enabled=bar.disable) as tick:
        for view in ...:
            ...
            tick.update()
"""

from __future__ import annotations

import logging
import sys
import threading
import time

log = logging.getLogger("ptovs")

EVERY_S = 30.0  # seconds between lines
_BEAT = [float("-inf")]  # time.monotonic() of the last Heartbeat line, any loop's
CHECKPOINT_S = 300.0  # a training loop also checkpoints after this long without one


def _clock(seconds: float) -> str:
    s = int(max(seconds, 0))
    return (
        f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"
        if s >= 3600
        else f"{s // 60}:{s % 60:02d}"
    )


class Heartbeat:
    """Log `desc: step/total, fields, rate, ETA` every `every` seconds, unless a
    terminal shows tqdm's bar instead (`enabled`: force either way)."""

    def __init__(
        self,
        desc: str,
        total: int,
        initial: int = 0,
        every: float = EVERY_S,
        enabled: bool | None = None,
        clock=time.monotonic,
    ) -> None:
        self.desc, self.total, self.every = desc, total, every
        self.enabled = (not sys.stderr.isatty()) if enabled is None else enabled
        self.clock = clock
        self.t0 = self.last = clock()
        self.step0 = initial

    def __call__(self, step: int, **fields: object) -> bool:
        """Log a line if `every` seconds passed since the last; True if it did."""
        if not self.enabled:
            return False
        now = self.clock()
        if now - self.last < self.every and step < self.total:
            return False
        self.last = now
        _BEAT[0] = time.monotonic()  # a Ticker around this loop need not speak
        rate = (step - self.step0) / max(now - self.t0, 1e-9)
        eta = (self.total - step) / rate if rate > 0 else float("inf")
        extra = "".join(f", {k} {v}" for k, v in fields.items())
        left = _clock(eta) if eta != float("inf") else "?"
        log.info("%s: %d/%d (%.0f %%)%s, %.2f it/s, %s left", self.desc, step,
                 self.total, 100.0 * step / max(self.total, 1), extra, rate, left)  # fmt: skip
        return True


class Ticker:
    """Log `desc: done/total units (%), s/unit, time left` every `every` seconds
    from a background thread while a `with` block runs, unless a terminal shows
    tqdm's bar instead (`enabled`: force either way; pass the bar's `disable`).

    The thread only reads what `update` recorded, so a line appears even while
    one step takes longer than `every`; it says how long since the last step. It
    keeps quiet while a `Heartbeat` speaks (a stage that trains before it yields
    its first view, as reconstruct does, logs its own iterations), so the log
    stays one voice and still never pauses for a minute. The thread is a daemon
    and is stopped and joined when the block ends, by an error too, so it never
    outlives the loop."""

    THREAD = "ptovs-progress"  # the thread's name (tests look for it)

    def __init__(
        self,
        desc: str,
        total: int | None,
        initial: int = 0,
        unit: str = "view",
        every: float | None = None,
        enabled: bool | None = None,
        clock=time.monotonic,
    ) -> None:
        self.desc, self.total, self.unit = desc, total, unit
        self.every = EVERY_S if every is None else every  # read now: tests lower it
        self.enabled = (not sys.stderr.isatty()) if enabled is None else enabled
        self.clock = clock
        self.done = self.done0 = initial
        self.t0 = self.last = clock()  # start; end of the last finished step
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._said = time.monotonic()  # real time of the last line (or the start)

    def update(self, n: int = 1) -> None:
        """Record `n` more steps finished now."""
        with self._lock:
            self.done += n
            self.last = self.clock()

    def line(self) -> str:
        """The progress line as of now (what the thread logs)."""
        with self._lock:
            done, last = self.done, self.last
        now = self.clock()
        unit, ran = self.unit, done - self.done0
        head = f"{self.desc}: {done}"
        if self.total:
            head += f"/{self.total} {unit}s ({100.0 * done / self.total:.0f} %)"
        else:
            head += f" {unit}s"
        per = (last - self.t0) / ran if ran > 0 else None
        parts = [head, f"? s/{unit}" if per is None else f"{per:.1f} s/{unit}"]
        if self.total:
            left_n = max(self.total - done, 0)
            if per is None:
                parts.append("? left")
            else:  # the step under way has had (now - last) of its share already
                left = max(left_n * per - (now - last), (left_n - 1) * per, 0.0)
                parts.append(f"{_clock(left)} left")
        text = ", ".join(parts)
        if (self.total is None or done < self.total) and now - last >= self.every:
            # true whether the stage is inside a view or before its first one
            since = f"the last {unit}" if ran > 0 else "the start"
            text += f"; {_clock(now - last)} since {since}"
        return text

    def due(self, now: float) -> bool:
        """Whether a line is due at `now` (time.monotonic()): `every` since this
        ticker's last, and 1.5 `every` since any Heartbeat's (its lines come every
        `every` and a step late; half that again covers the step)."""
        return now - self._said >= self.every and now - _BEAT[0] >= 1.5 * self.every

    def _run(self) -> None:
        # wake twice per interval: a line is at most every / 2 late
        while not self._stop.wait(self.every / 2):
            now = time.monotonic()
            if self.due(now):
                self._said = now
                log.info("%s", self.line())

    def __enter__(self) -> Ticker:
        if self.enabled:
            self._thread = threading.Thread(
                target=self._run, name=self.THREAD, daemon=True
            )
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the thread and wait for it (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None


__all__ = ["CHECKPOINT_S", "EVERY_S", "Heartbeat", "Ticker"]
