"""Supervision of one move: it must start, progress, arrive by its deadline and not overshoot.

A move is planned (trapezoidal profile, `rig.motion`), so it has a deadline: the planned
time stretched by `limits.move_deadline_factor` plus `limits.move_deadline_slack_s`. A
drive that takes the command and does not move (STOP held, disabled, an alarm not yet
read) fails the start check; one that stalls fails the deadline; one that runs past its
target fails the overshoot check. Pure logic: the loop feeds it fresh measurements.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

from rig.specs.config import LimitsConfig
from rig.specs.motion import move_time


@dataclass
class MoveWatch:
    """One commanded move (from, to, speed, acceleration, when it was sent) and the limits that set
    its deadline: it must start, arrive by the deadline and not overshoot its target."""

    from_mm: float
    to_mm: float
    speed_mm_s: float
    accel_mm_s2: float
    t0_s: float
    limits: LimitsConfig
    tolerance_mm: float
    started: bool = False

    @cached_property  # checked every tick; the plan does not change
    def planned_s(self) -> float:
        return move_time(self.from_mm, self.to_mm, self.speed_mm_s, self.accel_mm_s2)

    @cached_property
    def deadline_s(self) -> float:
        lim = self.limits
        return self.t0_s + self.planned_s * lim.move_deadline_factor + lim.move_deadline_slack_s

    def arrived(self, position_mm: float, moving: bool | None) -> bool:
        return abs(position_mm - self.to_mm) <= self.tolerance_mm and moving is False

    def check(self, t_s: float, position_mm: float | None, moving: bool | None) -> str | None:
        """A fault message, or None. `position_mm`/`moving` are None when not freshly measured."""
        lim = self.limits
        if position_mm is not None:
            if abs(position_mm - self.from_mm) > self.tolerance_mm:
                self.started = True
            direction = 1.0 if self.to_mm >= self.from_mm else -1.0
            beyond = (position_mm - self.to_mm) * direction
            if beyond > lim.overshoot_mm:
                return (f"move to {self.to_mm:.3f} mm overshot: at {position_mm:.3f} mm, "
                        f"{beyond:.3f} mm past the target (limit {lim.overshoot_mm:g} mm)")
        if moving:
            self.started = True
        elapsed = t_s - self.t0_s
        far = abs(self.to_mm - self.from_mm) > self.tolerance_mm
        # Judged only on a fresh position: a link that fails for a while is not a drive that stands.
        if not self.started and far and elapsed > lim.move_start_s and position_mm is not None \
                and moving is not True:
            return (f"the drive did not start the move to {self.to_mm:.3f} mm within "
                    f"{lim.move_start_s:g} s (STOP held by another master, drive disabled, or an alarm)")
        if t_s > self.deadline_s:
            where = f" at {position_mm:.3f} mm" if position_mm is not None else ""
            return (f"move to {self.to_mm:.3f} mm not finished by its deadline "
                    f"({self.deadline_s - self.t0_s:.2f} s for a planned {self.planned_s:.2f} s){where}: "
                    "stalled or too slow")
        return None
