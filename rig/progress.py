"""How far a long piece of work is: the units done, their rate and the time left, on stderr.

One line rewritten in place at a terminal; each tenth on a line of its own in a log. Shared by
the batch of curves (`rig analyze --each`) and the simulated map's writer (`rig sim-map`)."""

from __future__ import annotations

import math
import sys
import time

__all__ = ["Progress"]


class Progress:
    """`what` done of `total`, the rate and the time left, on one line of stderr (a terminal,
    every `every_s`) or every tenth (a log). Nothing is said until `after_s` has passed: work done
    within a moment needs no progress, and a page that shows the command's output stays as it is."""

    def __init__(self, total: int, stream=None, every_s: float = 0.5, what: str = "curves",
                 after_s: float = 0.0) -> None:
        self.total, self.done, self.t0 = total, 0, time.monotonic()
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last, self._decile, self.every_s = 0.0, 0, every_s
        self.what, self.after_s, self._open = what, after_s, False

    def add(self, n: int) -> None:
        self.done += n
        now = time.monotonic()
        decile = 10 * self.done // max(self.total, 1)
        if now - self.t0 < self.after_s:
            self._decile = decile  # a tenth done within the quiet moment is not said late
            return
        if self.tty and (now - self._last >= self.every_s or self.done == self.total):
            self._last = now
            self._open = self.done < self.total
            print(f"\r{self.line(now)}\x1b[K", end="" if self._open else "\n", file=self.stream, flush=True)
        elif not self.tty and decile > self._decile:
            self._decile = decile
            print(self.line(now), file=self.stream, flush=True)

    def close(self) -> None:
        """End a terminal's line left open by work that stopped before its total."""
        if self._open:
            self._open = False
            print(file=self.stream, flush=True)

    def line(self, now: float) -> str:
        dt = max(now - self.t0, 1e-9)
        rate = self.done / dt
        left = (self.total - self.done) / rate if rate > 0 else math.inf
        eta = "" if self.done >= self.total else f", about {_duration(left)} left"
        return f"  {self.done}/{self.total} {self.what}, {rate:.3g}/s{eta}"


def _duration(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"
