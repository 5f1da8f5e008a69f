"""A one-line progress display for a running trial (stderr; plain lines when not a terminal)."""

from __future__ import annotations

import sys
import time
from typing import TextIO

from rig.loop import Snapshot


class ProgressBar:
    def __init__(self, total_s: float, stream: TextIO | None = None, every_s: float = 0.2) -> None:
        self.total_s = max(total_s, 1e-9)
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.every_s = every_s if self.tty else 5.0
        self._last = -1e9
        self._shown = False

    def __call__(self, snap: Snapshot) -> None:
        now = time.monotonic()
        if now - self._last < self.every_s:
            return
        self._last = now
        done = min(snap.t_s / max(snap.t_s + snap.time_left_s, 1e-9), 1.0)
        width = 24
        bar = "#" * int(done * width) + "." * (width - int(done * width))
        line = (f"[{bar}] {done * 100:3.0f}%  t={snap.t_s:6.1f} s  step {snap.step + 1}/"
                f"{snap.steps_total} {snap.step_kind:<8} x={snap.position_mm:7.3f} mm  "
                f"F={snap.force_N:7.3f} N  k={snap.stiffness_N_per_m:7.1f} N/m")
        if self.tty:
            self.stream.write("\r" + line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
        self._shown = True

    def close(self) -> None:
        if self._shown and self.tty:
            self.stream.write("\n")
            self.stream.flush()
