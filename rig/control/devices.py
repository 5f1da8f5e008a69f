"""Open the slider and load cell a config names, behind the driver interfaces.

Backends: the simulated rig in-process (virtual or real time), the simulated rig on the
wire (started in a process of its own, reached through the real drivers), or real
hardware over Modbus RTU/TCP and a serial port.
"""

from __future__ import annotations

import contextlib
import re
from dataclasses import dataclass, field

from rig.clock import Clock
from rig.control.ownership import acquire, hold_with, serial_key, tcp_key, tty_exclusive
from rig.drivers.base import LoadCell, Slider
from rig.errors import DeviceError, RigError
from rig.specs.config import RigConfig


@dataclass
class Devices:
    """The slider and load cell a trial runs on, opened from the config, with what stops the
    drive if this controller dies (``backstop``), the warnings every start repeats, and the
    simulator or wire spy behind them if any. `close` releases all of them, best effort; as a
    context manager (``with open_devices(...) as dev:``) they are released however the block
    ends."""

    slider: Slider
    loadcell: LoadCell | None  # None: no load cell (loadcell.backend: none)
    rig: object | None = None  # the SimRig behind in-process devices (tests, fault injection)
    sim: object | None = None  # the SimProcess behind simulated devices on the wire
    description: str = ""
    # What stops the drive if this controller dies: the drive's communication timeout, or
    # nothing (then `warnings` says so, on every start).
    backstop: str = ""
    warnings: list[str] = field(default_factory=list)
    spy: object | None = None  # the WireSpy writing every frame and line (--spy)

    def __enter__(self) -> Devices:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for dev in (self.slider, self.loadcell):
            # closing is best effort; the devices may be gone
            with contextlib.suppress(Exception):
                if dev is not None:
                    dev.close()
        if self.sim is not None:
            self.sim.close()
        if self.spy is not None:
            self.spy.close()


# The backends a config may name, and what opens each: a slider on a bus by its Modbus transport,
# a load cell on a serial line. "sim" names the simulated rig, which provides both devices at once
# (in-process, or on the wire at speed 1); a load cell may be "none". `specs.config` lists the same
# names as the choices it accepts (tests/test_driver_contract.py holds them equal).
SLIDERS = {"modbus-rtu": "rtu", "modbus-tcp": "tcp"}
LOADCELLS = {"serial": "an ASCII load cell on a serial line"}
SIMULATED, NO_LOADCELL = "sim", "none"


def uses_wire(config: RigConfig, speed: float) -> bool:
    """Whether a trial at `speed` talks to its devices over real lines (a real rig; the simulated
    one on Modbus and serial lines at speed 1 unless `sim.wire` is none)."""
    if config.slider.backend != SIMULATED:
        return True
    return speed == 1.0 and config.sim.wire != "none"


def open_devices(config: RigConfig, clock: Clock, *, speed: float = 0.0,
                 spy_path: str | None = None, holder_note: str = "") -> Devices:
    """Devices for a run at `speed` (1 = real time; the simulated rig goes on the wire then).

    `spy_path`: write every Modbus frame and load-cell line to this file (`rig spy` reads it).
    Devices on a wire are locked to this process until `close` (`DeviceInUse` names another
    holder); `holder_note` tells a second user how to reach this one instead (a daemon's socket).
    """
    sb, lb = config.slider.backend, config.loadcell.backend
    if (sb == SIMULATED) != (lb == SIMULATED) and lb != NO_LOADCELL:
        raise RigError(f"slider backend '{sb}' and load-cell backend '{lb}': the simulated rig "
                       "provides both devices, so use 'sim' for both or for neither")
    if spy_path and not uses_wire(config, speed):
        raise RigError("--spy needs devices on a wire: a real rig, or the simulated rig at --speed 1 "
                       "with sim.wire rtu or tcp")
    if sb == SIMULATED and not uses_wire(config, speed):
        from rig.sim.inprocess import InProcessLoadCell, InProcessSlider
        from rig.sim.physics import SimRig

        sim = SimRig(config.sim)
        origin = clock.now()
        cell = InProcessLoadCell(sim, clock, origin) if lb != NO_LOADCELL else None
        if cell is not None:
            cell.max_abs_N = config.loadcell.max_abs_N
        return Devices(InProcessSlider(sim, clock, origin), cell, sim,
                       description="simulated rig, in-process", backstop="in-process: none needed")
    sim_proc = None
    cfg = config
    if sb == SIMULATED:
        from rig.sim.process import SimProcess

        sim_proc = SimProcess(config.text())
        cfg = wire_config(config, sim_proc.endpoints)
    spy = None
    try:
        if spy_path:
            spy = open_spy(spy_path, cfg)
        slider, backstop, warnings = open_slider(cfg, clock, tap=spy, holder_note=holder_note)
        try:
            loadcell = (open_loadcell(cfg, clock, tap=spy, holder_note=holder_note) if lb != NO_LOADCELL
                        else None)
        except BaseException:
            slider.close()
            raise
    except BaseException:
        if sim_proc is not None:
            sim_proc.close()
        if spy is not None:
            spy.close()
        raise
    desc = f"{slider.link.describe()}; " + (f"load cell {cfg.loadcell.port}" if loadcell is not None
                                            else "no load cell")
    if sim_proc is not None:
        desc = f"simulated rig on the wire: {desc}"
    return Devices(slider, loadcell, sim=sim_proc, description=desc, backstop=backstop, warnings=warnings,
                   spy=spy)


def open_spy(path: str, config: RigConfig):
    """A WireSpy on `path`, its header naming what each channel is connected to."""
    from rig.drivers.spy import WireSpy

    spy = WireSpy(path)
    s, lc = config.slider, config.loadcell
    if s.backend == "modbus-tcp":
        spy.describe("tcp", f"Modbus TCP {s.host}:{s.tcp_port} unit {s.device_id}; profile {s.profile}")
    else:
        spy.describe("rtu", f"Modbus RTU {s.port} {s.baudrate} 8{s.parity}{s.stopbits} unit {s.device_id}; "
                            f"profile {s.profile}")
    spy.describe("cell", f"load cell {lc.port} {lc.baudrate} baud, {lc.mode}")
    return spy


def wire_config(config: RigConfig, endpoints: dict) -> RigConfig:
    """The config with the drivers pointed at the simulated devices' wires."""
    import copy

    cfg = copy.deepcopy(config)
    s = cfg.slider
    if config.sim.wire == "tcp":
        host, port = endpoints["modbus_tcp"].rsplit(":", 1)
        s.backend, s.host, s.tcp_port = "modbus-tcp", host, int(port)
    else:
        s.backend, s.port, s.parity = "modbus-rtu", endpoints["modbus_rtu"], "N"
    if s.profile == "oriental_az":
        s.profile = "oriental_az_sim"  # the simulated drive exposes its comm-timeout parameter
    s.steps_per_mm = config.sim.slider.steps_per_mm
    s.device_id = config.sim.drive.device_id
    lc = cfg.loadcell
    if lc.backend != NO_LOADCELL:
        lc.backend, lc.port, lc.mode = "serial", endpoints["loadcell"], config.sim.loadcell.mode
    return cfg


def slider_lock_key(config: RigConfig) -> tuple[str, str]:
    """(what, key) of the slider's lock: its serial device, or its TCP host and port."""
    s = config.slider
    if s.backend == "modbus-tcp":
        return f"the slider at {s.host}:{s.tcp_port}", tcp_key(s.host, s.tcp_port)
    return f"the slider on {s.port}", serial_key(s.port)


def slider_link(config: RigConfig, timeout_s: float | None = None):
    """The `ModbusLink` the config's slider backend names (`timeout_s` overrides its timeout)."""
    from rig.drivers.modbus_slider import ModbusLink

    s = config.slider
    if s.backend not in SLIDERS:
        raise RigError(f"slider.backend '{s.backend}' is not on a bus (known: {', '.join(SLIDERS)})")
    return ModbusLink(SLIDERS[s.backend], port=s.port, baudrate=s.baudrate, parity=s.parity,
                      stopbits=s.stopbits, host=s.host, tcp_port=s.tcp_port, device_id=s.device_id,
                      timeout_s=timeout_s or s.timeout_s, retries=s.retries)


def make_slider(config: RigConfig, clock: Clock | None = None, *, tap=None, timeout_s: float | None = None,
                max_consecutive_errors: int | None = None, holder_note: str = ""):
    """The slider driver with its link open, nothing written yet (`DeviceError` if the port
    cannot be opened, `DeviceInUse` naming the process that owns the drive). `timeout_s`
    overrides the config's per-transaction timeout. Its close() releases the drive."""
    from rig.drivers.modbus_slider import ModbusSlider, open_client
    from rig.drivers.registers import PROFILES

    s = config.slider
    if s.profile not in PROFILES:
        raise RigError(f"unknown slider profile '{s.profile}' (known: {', '.join(PROFILES)})")
    try:
        regs = PROFILES[s.profile].with_overrides(s.registers)
    except ValueError as exc:
        raise RigError(f"slider.registers: {exc}") from None
    link = slider_link(config, timeout_s)
    if link.transport == "rtu" and not s.port:
        raise RigError("slider.port is empty: name the serial device of the drive")
    # The lock before the port: a second master must not put a byte on the bus or the link.
    lock = acquire(*slider_lock_key(config), note=holder_note)
    try:
        slider = ModbusSlider(link, regs, s.steps_per_mm, current_percent=s.current_percent,
                              max_consecutive_errors=max_consecutive_errors or s.max_consecutive_errors,
                              client=open_client(link, tap) if tap is not None else None,
                              **({"clock": clock.now} if clock is not None else {}))
    except BaseException:
        lock.release()
        raise
    if link.transport == "rtu":
        tty_exclusive(getattr(slider.client, "socket", None))
    return hold_with(slider, lock)


FIRST_READ_TRIES = 3  # a reply lost on a line just opened (an adapter just plugged in) is not a dead drive


def _first_position(slider) -> float:
    """The drive's position, asked up to FIRST_READ_TRIES times: the error of the last try if none
    is answered (a drive that is not there still fails at once, within a few timeouts)."""
    for _ in range(FIRST_READ_TRIES - 1):
        with contextlib.suppress(DeviceError):
            return slider.read_position_mm()
    return slider.read_position_mm()


def open_slider(config: RigConfig, clock: Clock | None = None, *, tap=None, holder_note: str = ""):
    """The slider driver, connected: STOP released and verified, the comm timeout set.

    Returns (slider, backstop description, warnings). Refuses a drive whose communication
    timeout cannot be set unless `slider.allow_no_comm_timeout` says the rig runs without it.
    """
    s = config.slider
    slider = make_slider(config, clock, tap=tap, holder_note=holder_note)
    warnings: list[str] = []
    try:
        _first_position(slider)
        slider.prepare()
        if s.comm_timeout_s > 0 and slider.set_comm_timeout(s.comm_timeout_s):
            backstop = f"drive communication timeout {s.comm_timeout_s:g} s"
        else:
            why = (f"profile '{s.profile}' does not know the drive's communication-timeout register"
                   if s.comm_timeout_s > 0 else "slider.comm_timeout_s is 0")
            if not s.allow_no_comm_timeout:
                raise RigError(f"{why}: if this controller dies mid-move, nothing stops the drive. Set "
                               "slider.registers.comm_timeout_ms to the parameter's address (drive manual), "
                               "or slider.allow_no_comm_timeout: true to run without this backstop")
            backstop = "none"
            warnings.append(f"WARNING: {why}; running without the drive's communication timeout "
                            "(allowed by slider.allow_no_comm_timeout): if this controller dies "
                            "mid-move, nothing stops the drive")
    except BaseException:
        slider.close()
        raise
    return slider, backstop, warnings


def open_loadcell(config: RigConfig, clock: Clock, *, tap=None, holder_note: str = ""):
    """The load-cell driver, reading; with a `tap`, every line each way goes to it too.
    Locked to this process until its close() (`DeviceInUse` names another holder)."""
    from rig.drivers.serial_loadcell import DEFAULT_PATTERN, LineFormat, SerialLoadCell

    lc = config.loadcell
    if not lc.port:
        raise RigError("loadcell.port is empty: name the serial device of the load cell")
    fmt = LineFormat(pattern=lc.pattern or DEFAULT_PATTERN, unit=lc.unit, counts=lc.counts,
                     gain_N_per_count=lc.gain_N_per_count, offset_counts=lc.offset_counts,
                     max_abs_N=lc.max_abs_N)
    try:
        fmt.compile()
    except (ValueError, re.error) as exc:
        raise RigError(f"loadcell.pattern: {exc}") from None
    kwargs = {"baudrate": lc.baudrate, "mode": lc.mode, "request": lc.request.encode(), "fmt": fmt,
              "clock": clock}
    lock = acquire(f"the load cell on {lc.port}", serial_key(lc.port), note=holder_note)
    try:
        if tap is not None:
            from rig.drivers.spy import SpiedSerialLoadCell

            cell = SpiedSerialLoadCell(lc.port, tap=tap, **kwargs)
        else:
            cell = SerialLoadCell(lc.port, **kwargs)
    except BaseException:
        lock.release()
        raise
    tty_exclusive(getattr(cell, "_serial", None))
    return hold_with(cell, lock)
