"""Time for the loop: the real monotonic clock, or virtual time for fast simulated runs."""

from __future__ import annotations

import time
from typing import Protocol


def slots_behind(lateness: float, period: float) -> int:
    """The loop's catch-up rule: the slots a tick starting `lateness` after its own skips (every
    whole period it fell behind, none within one). The trial loop and `rig probe`, which replays
    measured bus times through it, both use it."""
    return int(lateness / period) if lateness > period else 0


class Clock(Protocol):
    """The time a trial's loop runs on: `RealClock` at speed 1, `VirtualClock` otherwise (the
    simulated rig at `--speed 0` jumps to each deadline; at N it runs N times real time)."""

    def now(self) -> float:
        """Seconds on this clock (arbitrary origin, monotonic)."""

    def sleep_until(self, t_s: float) -> None: ...

    def wall_ns(self, t_s: float) -> int:
        """Wall-clock nanoseconds corresponding to clock time `t_s` (for log timestamps)."""


class RealClock:
    """`time.monotonic`, with a short busy-wait before each deadline.

    `time.sleep` on Linux wakes 50-100 us late and occasionally much later; sleeping
    until `spin_s` before the deadline and spinning the rest keeps period errors well
    under a millisecond for the price of a few percent of one core.
    """

    def __init__(self, spin_s: float = 0.0003) -> None:
        self.spin_s = spin_s
        self._wall0 = time.time_ns()
        self._mono0 = time.monotonic()

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t_s: float) -> None:
        remaining = t_s - time.monotonic()
        if remaining > self.spin_s:
            time.sleep(remaining - self.spin_s)
        while time.monotonic() < t_s:
            pass

    def wall_ns(self, t_s: float) -> int:
        return self._wall0 + int((t_s - self._mono0) * 1e9)


class VirtualClock:
    """Virtual time: `speed=0` jumps straight to each deadline; `speed=N` runs N times real time."""

    def __init__(self, speed: float = 0.0, start_s: float = 0.0) -> None:
        if speed < 0:
            raise ValueError("speed must be >= 0")
        self.speed = speed
        self._t = start_s
        self._wall0 = time.time_ns()
        self._real0 = time.monotonic()
        self._virt0 = start_s

    def now(self) -> float:
        return self._t

    def sleep_until(self, t_s: float) -> None:
        if t_s <= self._t:
            return
        if self.speed > 0:
            real_deadline = self._real0 + (t_s - self._virt0) / self.speed
            delay = real_deadline - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        self._t = t_s

    def wall_ns(self, t_s: float) -> int:
        return self._wall0 + int((t_s - self._virt0) * 1e9)
