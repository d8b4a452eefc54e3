"""Progress where no progress bar shows: a log line at least every 30 s.

tqdm draws nothing when stderr is not a terminal (a log file, a batch job), so a
long stage would be silent for many minutes. `Heartbeat` fills that gap: when the
bar is off, every `every` seconds it logs the step, the caller's figures (loss,
PSNR, ...), the rate and the time left.

    beat = Heartbeat("reconstruct", total=2500, initial=step)
    for ...:
        beat(step, loss=f"{lo:.4f}", psnr=f"{ps:.2f}")
"""

from __future__ import annotations

import logging
import sys
import time

log = logging.getLogger("ptovs")

EVERY_S = 30.0  # seconds between lines
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
        rate = (step - self.step0) / max(now - self.t0, 1e-9)
        eta = (self.total - step) / rate if rate > 0 else float("inf")
        extra = "".join(f", {k} {v}" for k, v in fields.items())
        left = _clock(eta) if eta != float("inf") else "?"
        log.info("%s: %d/%d (%.0f %%)%s, %.2f it/s, %s left", self.desc, step,
                 self.total, 100.0 * step / max(self.total, 1), extra, rate, left)  # fmt: skip
        return True


__all__ = ["CHECKPOINT_S", "EVERY_S", "Heartbeat"]
