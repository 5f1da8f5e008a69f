"""Setting up the probe by hand: home, move to a position, read the position.

Same limits as a trial: the target and speed go through the same check as every trial
move before anything is sent, and force, travel, speed, the drive alarm and the move's
deadline are watched while it runs (the slider stops on any of them). A move that ends
anywhere but at its target is an error, never "moved".
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

from rig.clock import RealClock
from rig.control.devices import Devices, open_devices
from rig.control.movewatch import MoveWatch
from rig.control.safety import SpeedMeter, TickState, check, check_move
from rig.errors import DeviceError, LimitError
from rig.specs.config import RigConfig


def _open(config: RigConfig) -> Devices:
    return open_devices(config, RealClock(), speed=1.0)


def position(config: RigConfig) -> dict:
    """`rig position`: the slider's position, status and alarm, and the force, read from the devices
    (nothing moves)."""
    with _open(config) as dev:
        pos = dev.slider.read_position_mm()
        status = dev.slider.read_status()
        cell = dev.loadcell
        reading = cell.latest() if cell is not None else None
        deadline = time.monotonic() + 0.5
        while cell is not None and reading is None and time.monotonic() < deadline:
            time.sleep(0.01)
            reading = cell.latest()
        return {"position_mm": pos, "moving": status.moving, "ready": status.ready,
                "alarm_code": status.alarm_code,
                "force_N": reading.force_N if reading else None, "devices": dev.description}


def move(config: RigConfig, to_mm: float, speed_mm_s: float, *, home: bool = False,
         out=sys.stderr) -> dict:
    """Move (or home) under the same limit check and deadline as a trial's moves."""
    _check_target(config, to_mm, speed_mm_s, home)
    with _open(config) as dev:
        for w in dev.warnings:
            print(w, file=out, flush=True)
        return move_on(dev, config, to_mm, speed_mm_s, home=home, out=out)


def _check_target(config: RigConfig, to_mm: float, speed_mm_s: float, home: bool) -> tuple[float, float]:
    target, speed = (0.0, config.slider.home_speed_mm_s) if home else (to_mm, speed_mm_s)
    why = check_move(target, speed, config.limits)
    if why is not None:
        what = "home (slider.home_speed_mm_s, home at 0 mm)" if home else "--to-mm/--speed-mm-s"
        raise LimitError(f"{what}: {why}")
    return target, speed


def move_on(dev: Devices, config: RigConfig, to_mm: float, speed_mm_s: float, *, home: bool = False,
            out=None, interrupted: Callable[[], str | None] | None = None) -> dict:
    """The move of `move` on devices already open (the daemon's): watched as a trial's moves are.
    `interrupted`, asked every 10 ms, names a reason to stop (a stop from another client): the
    slider then stops where it is and the move ends in an error saying why."""
    lim = config.limits
    target, speed = _check_target(config, to_mm, speed_mm_s, home)
    slider = dev.slider
    tol = config.slider.position_tolerance_mm
    commanded = stop_sent = False
    shown = out is not None and out.isatty()
    try:
        first = slider.position()
        if not first.fresh:
            raise DeviceError("cannot read the slider's position: not moving")
        start = first.value
        if dev.loadcell is None:
            raise DeviceError("rig move needs a load cell to watch the force (loadcell.backend is none)")
        reading = dev.loadcell.latest()
        tare = reading.force_N if reading else 0.0
        commanded = True  # from here the drive may be moving (even if the write's reply is lost)
        if home:
            slider.home()
        else:
            slider.move_to(to_mm, speed_mm_s, config.slider.accel_mm_s2)
        t0 = time.monotonic()
        watch = MoveWatch(start, target, speed, config.slider.accel_mm_s2, 0.0, lim, tol)
        speedometer = SpeedMeter(0.02)
        speedometer.update(first)
        while True:
            time.sleep(0.01)
            now = time.monotonic() - t0
            pr = slider.position()
            sr = slider.status()
            r = dev.loadcell.latest()
            pos, moving = pr.value, (sr.value.moving if sr.fresh else None)
            speed_now = speedometer.update(pr)
            force = (r.force_N - tare) if r else 0.0
            fault = check(TickState(force, pos, speed_now, r.age_s if r else None,
                                    sr.value.alarm_code if sr.value.alarm else 0,
                                    bool(r and r.over_range), r.force_N if r else 0.0), lim)
            why = fault.message if fault else watch.check(now, pos if pr.fresh else None, moving)
            if why is None and interrupted is not None:
                why = interrupted()
            if why is not None:
                stop_sent = True
                stopped = slider.stop()
                raise DeviceError(f"stopped: {why}" + ("" if stopped else
                                                       "; the drive did not acknowledge STOP"))
            if shown:
                out.write(f"\r  position {pos:8.3f} mm   force {force:7.3f} N")
                out.flush()
            if pr.fresh and watch.arrived(pos, moving):
                break
        if shown:
            out.write("\n")
        return {"from_mm": start, "position_mm": pos, "alarm_code": sr.value.alarm_code,
                "seconds": round(now, 3)}
    except (KeyboardInterrupt, Exception) as exc:
        # Whatever ended the watch (Ctrl-C, a lost bus, a bug), the drive must not go on moving.
        if commanded and not stop_sent:
            _stop_after(slider, exc)
        raise


def _stop_after(slider, exc: BaseException) -> None:
    """STOP before the error goes up; if it is not acknowledged, the error says so."""
    try:
        stopped = slider.stop()
    except Exception as stop_exc:  # noqa: BLE001 - the original error is what the operator needs
        stopped, why = False, str(stop_exc)
    else:
        why = getattr(slider, "last_error", "")
    if not stopped and isinstance(exc, Exception) and exc.args:
        exc.args = (f"{exc.args[0]}; STOP not acknowledged by the drive ({why})", *exc.args[1:])


def reset_alarm(config: RigConfig) -> dict:
    """Clear the drive's alarm (its cause must be gone); the alarm code before and after."""
    with _open(config) as dev:
        before = dev.slider.status().value.alarm_code
        dev.slider.reset_alarm()
        after = dev.slider.status().value.alarm_code
    if after:
        raise DeviceError(f"the drive still reports alarm 0x{after:02X} after the reset: its cause is "
                          "still there")
    return {"alarm_before": before, "alarm_after": after}
