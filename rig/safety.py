"""Limits checked every tick: pure functions of one tick's state, so they are easy to test.

The loop calls `check` before the sequencer may issue any command; a non-None result
means: stop the slider now, then log the fault.
"""

from __future__ import annotations

from dataclasses import dataclass

from rig.config import LimitsConfig


@dataclass(frozen=True)
class TickState:
    force_N: float
    position_abs_mm: float  # slider coordinates (the travel window is in these)
    speed_mm_s: float  # measured from the last two positions
    loadcell_age_s: float | None  # None: no reading yet
    alarm_code: int = 0  # 0 = drive reports no alarm


@dataclass(frozen=True)
class Fault:
    kind: str  # force_limit, travel, overspeed, loadcell_stale, drive_alarm, ...
    message: str


def check(state: TickState, limits: LimitsConfig) -> Fault | None:
    if state.alarm_code:
        return Fault("drive_alarm", f"drive alarm code 0x{state.alarm_code:02X}")
    stale_s = limits.loadcell_stale_ms / 1000.0
    if state.loadcell_age_s is None or state.loadcell_age_s > stale_s:
        age = "no reading" if state.loadcell_age_s is None else f"{state.loadcell_age_s * 1000:.0f} ms"
        return Fault("loadcell_stale", f"load cell silent ({age}; limit {limits.loadcell_stale_ms:g} ms)")
    if state.force_N > limits.max_force_N:
        return Fault("force_limit",
                     f"force {state.force_N:.3f} N above the limit of {limits.max_force_N:g} N")
    lo, hi = limits.travel_mm
    if not lo <= state.position_abs_mm <= hi:
        return Fault("travel", f"position {state.position_abs_mm:.3f} mm outside the travel "
                               f"window [{lo:g}, {hi:g}] mm")
    max_speed = limits.max_speed_mm_s * limits.overspeed_factor
    if abs(state.speed_mm_s) > max_speed:
        return Fault("overspeed", f"measured speed {abs(state.speed_mm_s):.2f} mm/s above "
                                  f"{max_speed:g} mm/s")
    return None
