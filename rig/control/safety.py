"""Limits checked every tick and before every move: pure functions, so they are easy to test.

The loop calls `check` before the sequencer may issue any command; a non-None result
means: stop the slider now, then log the fault. `check_move` is the one limit check
every path that moves the slider goes through (protocol steps, the abort return,
`rig move`, `rig home`), before the command is sent.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from rig.drivers.base import Reading
from rig.specs.config import LimitsConfig


@dataclass(frozen=True)
class TickState:
    """What one tick knows that a safety limit can be checked against: the force the tissue
    carries, the slider's position and measured speed, the load cell's age, the drive's alarm."""

    force_N: float  # what the limit applies to: the force the tissue carries (from the free-air zero)
    position_abs_mm: float  # slider coordinates (the travel window is in these)
    speed_mm_s: float | None  # from the last two fresh positions; None: not measurable this tick
    loadcell_age_s: float | None  # None: no reading yet
    alarm_code: int = 0  # 0 = drive reports no alarm
    force_over_range: bool = False  # the load cell reported a force beyond its range
    raw_force_N: float = 0.0  # the untared value the cell reported
    force_source: str = "measured"  # or "estimated": the model's force on a rig without a load cell
    preload_N: float = 0.0  # of force_N, what the probe already carried when the trial was tared


@dataclass(frozen=True)
class Fault:
    """Why a trial stops on its own: a ``kind`` a program can act on and a ``message`` the
    operator reads."""

    kind: str  # force_limit, force_range, travel, overspeed, loadcell_stale, drive_alarm, move, ...
    message: str


def check(state: TickState, limits: LimitsConfig) -> Fault | None:
    """The first limit this tick breaks, or None: a drive alarm, a load cell over its range or
    silent beyond `loadcell_stale_ms`, a force that is not a number or above `max_force_N`, a
    position outside the travel window, a speed above the limit times `overspeed_factor`. In that
    order: a stale or invalid force is a fault before its value is compared with anything."""
    if state.alarm_code:
        return Fault("drive_alarm", f"drive alarm code 0x{state.alarm_code:02X}")
    if state.force_over_range:
        return Fault("force_range", f"load cell over range: it reports {state.raw_force_N:.3f} N, beyond "
                                    "its range (loadcell.max_abs_N)")
    stale_s = limits.loadcell_stale_ms / 1000.0
    if state.loadcell_age_s is None or state.loadcell_age_s > stale_s:
        age = "no reading" if state.loadcell_age_s is None else f"{state.loadcell_age_s * 1000:.0f} ms"
        return Fault("loadcell_stale", f"load cell silent ({age}; limit {limits.loadcell_stale_ms:g} ms)")
    if not math.isfinite(state.force_N):  # NaN compares False with any limit: it would switch it off
        what = "measured" if state.force_source == "measured" else "estimated (the model's)"
        return Fault("force_invalid", f"{what} force is {state.force_N}: the force limit cannot be checked")
    if state.force_N > limits.max_force_N:
        what = "force" if state.force_source == "measured" else \
            f"estimated force x (1 + margin {limits.model_force_margin:g})"
        pre = f" ({state.preload_N:.3f} N of it preload at the start)" if state.preload_N else ""
        return Fault("force_limit", f"{what} {state.force_N:.3f} N above the limit of {limits.max_force_N:g} N"
                                    + pre)
    lo, hi = limits.travel_mm
    if not lo <= state.position_abs_mm <= hi:
        return Fault("travel", f"position {state.position_abs_mm:.3f} mm outside the travel "
                               f"window [{lo:g}, {hi:g}] mm")
    max_speed = limits.max_speed_mm_s * limits.overspeed_factor
    if state.speed_mm_s is not None and abs(state.speed_mm_s) > max_speed:
        return Fault("overspeed", f"measured speed {abs(state.speed_mm_s):.2f} mm/s above "
                                  f"{max_speed:g} mm/s")
    return None


def check_move(to_mm: float, speed_mm_s: float, limits: LimitsConfig) -> str | None:
    """Why a move to `to_mm` (slider coordinates) at `speed_mm_s` is not allowed, or None."""
    lo, hi = limits.travel_mm
    if not lo <= to_mm <= hi:
        return f"target {to_mm:.3f} mm is outside the travel window [{lo:g}, {hi:g}] mm"
    if not 0 < speed_mm_s <= limits.max_speed_mm_s:
        return f"speed {speed_mm_s:g} mm/s is not within (0, {limits.max_speed_mm_s:g}] mm/s"
    return None


class SpeedMeter:
    """Speed from fresh positions at least `span_s` apart; stale readings are skipped.

    Two readings a tick apart, or a fraction of a tick after a late one, would turn a single
    encoder step into a false overspeed (one 0.01 mm step in 0.5 ms reads as 20 mm/s).
    """

    def __init__(self, span_s: float) -> None:
        self.span_s = span_s
        self._history: deque[tuple[float, float]] = deque()

    def update(self, reading: Reading[float]) -> float | None:
        """The speed, mm/s, or None while there is no fresh pair `span_s` apart."""
        if not reading.fresh:
            return None
        h = self._history
        t = reading.t_s
        if h and t <= h[-1][0]:
            return None
        h.append((t, reading.value))
        while len(h) > 2 and t - h[1][0] >= self.span_s:  # keep the newest one old enough
            h.popleft()
        t0, x0 = h[0]
        return (reading.value - x0) / (t - t0) if t - t0 >= self.span_s else None
