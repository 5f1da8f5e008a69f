"""The driver interfaces every backend (real, simulated, mock) implements.

The loop only ever talks to these: a `Slider` that moves, stops and reports its
position and status, and a `LoadCell` that hands over its newest reading and how
old it is. Backends live one per module, like pyserial's platform modules.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class SliderStatus:
    ready: bool
    moving: bool
    in_position: bool
    alarm: bool
    alarm_code: int = 0


@dataclass(frozen=True)
class ForceReading:
    force_N: float  # as converted by the driver, before the loop's tare
    t_s: float  # loop-clock time the reading arrived
    age_s: float  # how old it was when handed over


@dataclass
class LinkStats:
    """Counters every driver keeps; the loop logs them in /rig/health."""

    transactions: int = 0
    errors: int = 0
    retries: int = 0
    lines_ok: int = 0
    lines_bad: int = 0
    out_of_range: int = 0


@runtime_checkable
class Slider(Protocol):
    stats: LinkStats

    def read_position_mm(self) -> float:
        """Feedback position (one bus transaction)."""

    def read_status(self) -> SliderStatus:
        """READY / MOVE / IN-POS / alarm (one bus transaction)."""

    def move_to(self, position_mm: float, speed_mm_s: float, accel_mm_s2: float | None = None) -> None:
        """Start one absolute move the drive executes itself; returns at once."""

    def stop(self) -> None:
        """Stop motion now (decelerate at the drive's stop rate)."""

    def reset_alarm(self) -> None: ...

    def close(self) -> None: ...


@runtime_checkable
class LoadCell(Protocol):
    stats: LinkStats

    def latest(self) -> ForceReading | None:
        """The newest reading (a polled device is asked for one), or None before the first."""

    def close(self) -> None: ...
