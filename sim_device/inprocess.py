"""The simulated devices as in-process objects behind the driver interfaces.

They share `SimRig` physics with the devices on the wire and advance it to the loop
clock's time on every call, so virtual time (`--speed 0`) and real time both work.
Faults can be switched at run time: `slider.alarm_code`, `slider.ignore_moves` (a drive
that takes the move command but does not move), `slider.unreadable` (position reads
fail), `loadcell.silent`, `loadcell.force_scale` (a cell that reads too high).
"""

from __future__ import annotations

from rig.drivers.base import ForceReading, LinkStats, Reading, SliderStatus
from rig.sim.physics import SimRig

from rig.clock import Clock


class InProcessSlider:
    def __init__(self, rig: SimRig, clock: Clock, origin_s: float = 0.0) -> None:
        self.rig = rig
        self.clock = clock
        self.origin_s = origin_s  # clock time at which the simulation started
        self.stats = LinkStats()
        self.alarm_code = 0  # set non-zero to inject a drive alarm (the drive stops itself)
        self.ignore_moves = False  # acknowledge move commands but never start them
        self.unreadable = False  # position reads fail (the last good value comes back stale)
        self._last_position: Reading[float] | None = None

    def _sync(self) -> None:
        self.rig.advance(self.clock.now() - self.origin_s)
        self.stats.transactions += 1
        if self.alarm_code and self.rig.slider.moving:
            self.rig.slider.stop()

    def position(self) -> Reading[float]:
        self._sync()
        if self.unreadable and self._last_position is not None:
            self.stats.errors += 1
            return Reading(self._last_position.value, self._last_position.t_s, False)
        self._last_position = Reading(self.rig.feedback_position_mm(), self.clock.now())
        return self._last_position

    def read_position_mm(self) -> float:
        return self.position().value

    def status(self) -> Reading[SliderStatus]:
        self._sync()
        m = self.rig.slider
        return Reading(SliderStatus(ready=not m.moving and not self.alarm_code, moving=m.moving,
                                    in_position=not m.moving and abs(m.position_mm - m.target_mm) < 1e-6,
                                    alarm=bool(self.alarm_code), alarm_code=self.alarm_code),
                       self.clock.now())

    def read_status(self) -> SliderStatus:
        return self.status().value

    def move_to(self, position_mm: float, speed_mm_s: float, accel_mm_s2: float | None = None) -> None:
        self._sync()
        if not self.alarm_code and not self.ignore_moves:
            self.rig.slider.move_to(position_mm, speed_mm_s, accel_mm_s2)

    def stop(self) -> bool:
        self._sync()
        self.rig.slider.stop()
        return True

    def reset_alarm(self) -> None:
        self._sync()
        self.alarm_code = 0

    def close(self) -> None:
        self.rig.slider.stop()


class InProcessLoadCell:
    """Converts once per request, at the requesting tick (a polled device with no latency)."""

    def __init__(self, rig: SimRig, clock: Clock, origin_s: float = 0.0) -> None:
        self.rig = rig
        self.clock = clock
        self.origin_s = origin_s
        self.stats = LinkStats()
        self.silent = False  # set to inject a sensor that stops answering
        self.force_scale = 1.0  # > 1 injects a cell that reads too high (over range)
        self.max_abs_N = 500.0  # the cell's range, as loadcell.max_abs_N
        self._last: ForceReading | None = None

    def latest(self) -> ForceReading | None:
        now = self.clock.now()
        if self.silent:
            if self._last is None:
                return None
            return ForceReading(self._last.force_N, self._last.t_s, now - self._last.t_s)
        self.rig.advance(now - self.origin_s)
        force = self.rig.read_force_N() * self.force_scale
        over = abs(force) > self.max_abs_N
        self._last = ForceReading(force, now, 0.0, over_range=over)
        if over:
            self.stats.out_of_range += 1
        else:
            self.stats.lines_ok += 1
        return self._last

    def close(self) -> None:
        pass
