"""A one-line progress display for a running trial, on a thread of its own.

It reads `Trial.snapshot` (replaced, never mutated, by the loop) every `every_s`: a
terminal or pipe that blocks can stall this thread, never the loop.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable
from typing import TextIO

from rig.control.states import TrialState
from rig.control.trial import Snapshot


class ProgressBar:
    def __init__(self, total_s: float, snapshot: Callable[[], Snapshot], stream: TextIO | None = None,
                 every_s: float = 0.2) -> None:
        self.total_s = max(total_s, 1e-9)
        self.snapshot = snapshot
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.every_s = every_s if self.tty else 5.0
        self._shown = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="progress", daemon=True)

    def start(self) -> ProgressBar:
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            snap = self.snapshot()
            if snap.state in (TrialState.RUNNING, TrialState.STOPPING):
                self.show(snap)

    def show(self, snap: Snapshot) -> None:
        done = min(snap.t_s / max(snap.t_s + snap.time_left_s, 1e-9), 1.0)
        width = 24
        bar = "#" * int(done * width) + "." * (width - int(done * width))
        line = (f"[{bar}] {done * 100:3.0f}%  t={snap.t_s:6.1f} s  step {snap.step + 1}/"
                f"{snap.steps_total} {snap.step_kind:<8} x={snap.position_mm:7.3f} mm  "
                f"F={snap.force_N:7.3f} N  k={snap.stiffness_N_per_m:7.1f} N/m")
        try:
            self.stream.write("\r" + line if self.tty else line + "\n")
            self.stream.flush()
        except (OSError, ValueError):  # a closed or broken terminal: stop showing, never fail the trial
            self._stop.set()
            return
        self._shown = True

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(1.0)
        if self._shown and self.tty:
            try:
                self.stream.write("\n")
                self.stream.flush()
            except (OSError, ValueError):
                pass
