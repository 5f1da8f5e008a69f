"""The simulated devices as in-process objects behind the driver interfaces.

They share `SimRig` physics with the devices on the wire and advance it to the loop
clock's time on every call, so virtual time (`--speed 0`) and real time both work.
Faults can be switched at run time: `rig.alarm_code`, `loadcell.silent`.
"""

from __future__ import annotations

from drivers.base import ForceReading, LinkStats, SliderStatus
from rig.clock import Clock
from sim_device.physics import SimRig


class InProcessSlider:
    def __init__(self, rig: SimRig, clock: Clock, origin_s: float = 0.0) -> None:
        self.rig = rig
        self.clock = clock
        self.origin_s = origin_s  # clock time at which the simulation started
        self.stats = LinkStats()
        self.alarm_code = 0  # set non-zero to inject a drive alarm (the drive stops itself)

    def _sync(self) -> None:
        self.rig.advance(self.clock.now() - self.origin_s)
        self.stats.transactions += 1
        if self.alarm_code and self.rig.slider.moving:
            self.rig.slider.stop()

    def read_position_mm(self) -> float:
        self._sync()
        return self.rig.feedback_position_mm()

    def read_status(self) -> SliderStatus:
        self._sync()
        m = self.rig.slider
        return SliderStatus(ready=not m.moving and not self.alarm_code, moving=m.moving,
                            in_position=not m.moving and abs(m.position_mm - m.target_mm) < 1e-6,
                            alarm=bool(self.alarm_code), alarm_code=self.alarm_code)

    def move_to(self, position_mm: float, speed_mm_s: float, accel_mm_s2: float | None = None) -> None:
        self._sync()
        if not self.alarm_code:
            self.rig.slider.move_to(position_mm, speed_mm_s, accel_mm_s2)

    def stop(self) -> None:
        self._sync()
        self.rig.slider.stop()

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
        self._last: ForceReading | None = None

    def latest(self) -> ForceReading | None:
        now = self.clock.now()
        if self.silent:
            if self._last is None:
                return None
            return ForceReading(self._last.force_N, self._last.t_s, now - self._last.t_s)
        self.rig.advance(now - self.origin_s)
        self._last = ForceReading(self.rig.read_force_N(), now, 0.0)
        self.stats.lines_ok += 1
        return self._last

    def close(self) -> None:
        pass
