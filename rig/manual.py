"""Setting up the probe by hand: home, move to a position, read the position.

Same limits as a trial: travel window and speed are checked before the move, and force
and the drive alarm are watched while it runs (the slider stops on any of them).
"""

from __future__ import annotations

import sys
import time

from rig.clock import RealClock
from rig.config import RigConfig
from rig.devices import Devices, open_devices
from rig.errors import DeviceError, LimitError
from rig.safety import TickState, check


def _open(config: RigConfig) -> Devices:
    return open_devices(config, RealClock(), speed=1.0)


def position(config: RigConfig) -> dict:
    dev = _open(config)
    try:
        pos = dev.slider.read_position_mm()
        status = dev.slider.read_status()
        reading = dev.loadcell.latest()
        deadline = time.monotonic() + 0.5
        while reading is None and time.monotonic() < deadline:
            time.sleep(0.01)
            reading = dev.loadcell.latest()
        return {"position_mm": pos, "moving": status.moving, "ready": status.ready,
                "alarm_code": status.alarm_code,
                "force_N": reading.force_N if reading else None, "devices": dev.description}
    finally:
        dev.close()


def move(config: RigConfig, to_mm: float, speed_mm_s: float, *, home: bool = False,
         timeout_s: float = 120.0, out=sys.stderr) -> dict:
    lim = config.limits
    if not home:
        lo, hi = lim.travel_mm
        if not lo <= to_mm <= hi:
            raise LimitError(f"--to-mm {to_mm:g} is outside the travel window [{lo:g}, {hi:g}] mm")
        if not 0 < speed_mm_s <= lim.max_speed_mm_s:
            raise LimitError(f"--speed-mm-s {speed_mm_s:g} must be in (0, {lim.max_speed_mm_s:g}] mm/s")
    dev = _open(config)
    slider = dev.slider
    try:
        start = slider.read_position_mm()
        reading = dev.loadcell.latest()
        tare = reading.force_N if reading else 0.0
        if home:
            slider.home()
        else:
            slider.move_to(to_mm, speed_mm_s, config.slider.accel_mm_s2)
        t0 = time.monotonic()
        prev, prev_t = start, t0
        status = slider.read_status()
        while True:
            time.sleep(0.01)
            now = time.monotonic()
            pos = slider.read_position_mm()
            status = slider.read_status()
            r = dev.loadcell.latest()
            force = (r.force_N - tare) if r else 0.0
            fault = check(TickState(force, pos, (pos - prev) / (now - prev_t), r.age_s if r else None,
                                    status.alarm_code if status.alarm else 0), lim)
            prev, prev_t = pos, now
            if fault is not None:
                slider.stop()
                raise DeviceError(f"stopped: {fault.message}")
            if out.isatty():
                out.write(f"\r  position {pos:8.3f} mm   force {force:7.3f} N")
                out.flush()
            if not status.moving and now - t0 > 0.05:
                break
            if now - t0 > timeout_s:
                slider.stop()
                raise DeviceError(f"move did not finish within {timeout_s:g} s")
        if out.isatty():
            out.write("\n")
        return {"from_mm": start, "position_mm": slider.read_position_mm(), "alarm_code": status.alarm_code}
    except KeyboardInterrupt:
        slider.stop()
        raise
    finally:
        dev.close()
