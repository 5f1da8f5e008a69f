"""Slider driver: Modbus RTU (serial) or Modbus TCP, register map from `rig.drivers.registers`.

Bus budget per loop tick: one FC03 read of the feedback position; status and alarm
together in one FC03 read when the loop asks (about 10 Hz); a move is one FC16 write of
the direct-data block that the drive then executes itself. Every call is bounded by
`timeout_s` x (1 + `retries`). One failed read is ridden through (the last good
value is returned, marked stale, and the error counted); `max_consecutive_errors` in a
row raise `DeviceError`, which the loop turns into a fault.

STOP on the input command is level-sensitive, as on the real drive: while it is set the
drive ignores every move. `prepare()` (on connect) releases a STOP that another process
left set and reads the register back, asking again after a lost reply (connect is not on
the loop's clock); every write must be acknowledged, and a write that is not raises
`DeviceError` (a STOP is retried first: it must not be lost).

The client is owned by one thread (pymodbus does not allow parallel calls on a client).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass

from pymodbus import FramerType
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException
from rig.drivers.base import LinkStats, Reading, SliderStatus
from rig.drivers.registers import RegisterMap, from_words, to_words
from rig.drivers.rtu_client import FramedSerialClient

from rig.errors import DeviceError

# pymodbus logs every timeout at ERROR level; we count and report them ourselves.
logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


@dataclass(frozen=True)
class ModbusLink:
    """Where the drive is and how to talk to it."""

    transport: str  # "rtu" or "tcp"
    port: str = ""  # RTU: serial device or pyserial URL
    baudrate: int = 115200
    parity: str = "N"
    stopbits: int = 1
    host: str = "127.0.0.1"  # TCP
    tcp_port: int = 502
    device_id: int = 1
    timeout_s: float = 0.02
    retries: int = 0

    def describe(self) -> str:
        if self.transport == "tcp":
            return f"Modbus TCP {self.host}:{self.tcp_port} unit {self.device_id}"
        return f"Modbus RTU {self.port} {self.baudrate} 8{self.parity}{self.stopbits} unit {self.device_id}"


def open_client(link: ModbusLink, tap=None) -> FramedSerialClient | ModbusTcpClient:
    """A connected client; with a `tap` (rig.drivers.spy), every frame each way goes to it too.
    RTU replies are read by their length (`rig.drivers.rtu_client`), not by polling the port."""
    serial_cls, tcp_cls = FramedSerialClient, ModbusTcpClient
    if tap is not None:
        from rig.drivers.spy import SpiedSerialClient, SpiedTcpClient

        serial_cls, tcp_cls = SpiedSerialClient, SpiedTcpClient
    if link.transport == "tcp":
        client = tcp_cls(link.host, port=link.tcp_port, timeout=link.timeout_s,
                         retries=link.retries, reconnect_delay=0)
    elif link.transport == "rtu":
        client = serial_cls(link.port, framer=FramerType.RTU, baudrate=link.baudrate,
                            bytesize=8, parity=link.parity, stopbits=link.stopbits,
                            timeout=link.timeout_s, retries=link.retries, reconnect_delay=0)
    else:
        raise DeviceError(f"unknown Modbus transport '{link.transport}' (rtu or tcp)")
    if tap is not None:
        client.tap = tap
    try:
        ok = client.connect()
    except Exception as exc:  # noqa: BLE001 - pyserial/socket errors vary by platform
        raise DeviceError(f"cannot open {link.describe()}: {exc}") from None
    if not ok:
        raise DeviceError(f"cannot open {link.describe()}: no connection")
    _no_delay(client)
    return client


def _matches(reply, args: tuple, kwargs: dict) -> bool:
    """A read reply carries as many registers as asked for; a write reply echoes address and count."""
    if "count" in kwargs:
        return len(getattr(reply, "registers", ())) == kwargs["count"]
    if len(args) == 2 and isinstance(args[1], list):
        address, values = args
        same_count = getattr(reply, "count", len(values)) == len(values)
        return getattr(reply, "address", address) == address and same_count
    return True


def _no_delay(client) -> object:
    """TCP_NODELAY on the client's socket (pymodbus makes a new one on every reconnect).

    Without it, a request after a lost reply waits for the delayed ACK of the last one
    (Nagle): about 40 ms, i.e. two more failed ticks.
    """
    sock = getattr(client, "socket", None)
    if isinstance(sock, socket.socket):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


# Connect-time requests (release, read-back, the drive's communication timeout) are idempotent
# and not on the loop's clock: a lost reply is asked again, up to this many times in all.
SETUP_ATTEMPTS = 3


class ModbusSlider:
    def __init__(self, link: ModbusLink, registers: RegisterMap, steps_per_mm: float, *,
                 current_percent: float = 100.0, stop_decel_mm_s2: float = 2000.0,
                 max_consecutive_errors: int = 5, client=None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.link = link
        self.regs = registers
        self.steps_per_mm = steps_per_mm
        self.current_percent = current_percent
        self.stop_decel_mm_s2 = stop_decel_mm_s2
        self.max_consecutive_errors = max_consecutive_errors
        self.stats = LinkStats()
        self.client = client or open_client(link)
        self.clock = clock
        self._consecutive = 0
        self._position: Reading[float] | None = None
        self._status: Reading[SliderStatus] = Reading(
            SliderStatus(ready=False, moving=False, in_position=False, alarm=False), 0.0, False)
        self._stop_latched = False
        self.last_error = ""
        self._sock = getattr(self.client, "socket", None)

    # ------------------------------------------------------------ bus calls
    def _call(self, what: str, fn, *args, **kwargs):
        self.stats.transactions += 1
        if self.link.transport == "tcp" and getattr(self.client, "socket", None) is not self._sock:
            self._sock = _no_delay(self.client)
        try:
            reply = fn(*args, device_id=self.link.device_id, **kwargs)
        except ModbusException as exc:
            return self._failed(what, str(exc).strip() or type(exc).__name__)
        except OSError as exc:
            return self._failed(what, f"link error: {exc}")
        if reply is None or reply.isError():
            return self._failed(what, f"exception reply {getattr(reply, 'exception_code', '?')}")
        if not _matches(reply, args, kwargs):
            # RTU has no transaction id: this is the late answer to an earlier request.
            return self._failed(what, "the reply does not match the request (a late reply to an earlier one)")
        self._consecutive = 0
        return reply

    def _failed(self, what: str, why: str) -> None:
        self.stats.errors += 1
        self._consecutive += 1
        self.last_error = f"{what}: {why}"
        if self.link.transport == "rtu":
            self._drain()
        if self._consecutive >= self.max_consecutive_errors:
            raise DeviceError(f"slider ({self.link.describe()}): {self._consecutive} failed "
                              f"transactions in a row; last: {self.last_error}")
        return None

    def _drain(self) -> None:
        """After a failed RTU transaction: let a late reply arrive, then drop it, so the next
        request is not answered by it. Costs one timeout, only after a failure."""
        sock = getattr(self.client, "socket", None)
        if sock is None:
            return
        with contextlib.suppress(Exception):
            time.sleep(self.link.timeout_s)
            sock.reset_input_buffer()

    def _write(self, what: str, address: int, values: list[int]) -> bool:
        return self._call(what, self.client.write_registers, address, values) is not None

    def _write_checked(self, what: str, address: int, values: list[int], attempts: int = 1) -> None:
        if self._again(what, self.client.write_registers, address, values, attempts=attempts) is None:
            raise DeviceError(f"slider ({self.link.describe()}): {what} not acknowledged "
                              f"({self.last_error})")

    def _again(self, what: str, fn, *args, attempts: int, **kwargs):
        """`_call` up to `attempts` times, for idempotent requests outside the loop's tick.

        On connect the loop's budget (one timeout, no retry) would turn one lost reply, which
        the loop itself rides through, into a trial that never starts; each failure is still
        counted, and `max_consecutive_errors` still bounds the whole."""
        for _ in range(max(attempts, 1)):
            reply = self._call(what, fn, *args, **kwargs)
            if reply is not None:
                return reply
        return None

    # ------------------------------------------------------------ interface
    def prepare(self) -> None:
        """On connect: release any STOP/ZHOME level left set (by us or another master), verified.

        Each request is tried up to `SETUP_ATTEMPTS` times: both are idempotent."""
        self._write_checked("release input command", self.regs.input_command, [0, 0],
                            attempts=SETUP_ATTEMPTS)
        reply = self._again("read input command", self.client.read_holding_registers,
                            self.regs.input_command, count=2, attempts=SETUP_ATTEMPTS)
        if reply is None:
            raise DeviceError(f"slider ({self.link.describe()}): cannot read back the input command "
                              f"register ({self.last_error})")
        if reply.registers[1] & (1 << self.regs.bit_stop):
            raise DeviceError(f"slider ({self.link.describe()}): STOP stays set on the input command "
                              f"after release (0x{reply.registers[1]:04X}): is a STOP input wired on?")
        self._stop_latched = False

    def position(self) -> Reading[float]:
        reply = self._call("read position", self.client.read_holding_registers,
                           self.regs.feedback_position, count=2)
        if reply is not None:
            self._position = Reading(from_words(*reply.registers[:2]) / self.steps_per_mm, self.clock())
            return self._position
        if self._position is None:
            raise DeviceError(f"slider ({self.link.describe()}): no position read yet "
                              f"({self.last_error})")
        return Reading(self._position.value, self._position.t_s, False)

    def read_position_mm(self) -> float:
        return self.position().value

    def status(self) -> Reading[SliderStatus]:
        address, count = self.regs.status_block
        reply = self._call("read status", self.client.read_holding_registers, address, count=count)
        if reply is None:
            return Reading(self._status.value, self._status.t_s, False)
        words = reply.registers
        bits = words[1]
        code = from_words(words[2], words[3]) if count == 4 else self.read_alarm_code()
        r = self.regs
        self._status = Reading(SliderStatus(
            ready=bool(bits >> r.bit_ready & 1), moving=bool(bits >> r.bit_move & 1),
            in_position=bool(bits >> r.bit_in_pos & 1),
            alarm=bool(bits >> r.bit_alarm & 1) or code != 0, alarm_code=code), self.clock())
        return self._status

    def read_status(self) -> SliderStatus:
        return self.status().value

    def read_alarm_code(self) -> int:
        reply = self._call("read alarm", self.client.read_holding_registers, self.regs.alarm, count=2)
        return from_words(*reply.registers[:2]) if reply is not None else self._status.value.alarm_code

    def move_to(self, position_mm: float, speed_mm_s: float, accel_mm_s2: float | None = None) -> None:
        """One FC16 write of the direct-data block with trigger 1 (apply and start)."""
        if self._stop_latched:  # STOP is level-sensitive: release it before the next move
            self._write_checked("release stop", self.regs.input_command, [0, 0])
            self._stop_latched = False
        spm = self.steps_per_mm
        accel = accel_mm_s2 or 50.0
        block = [0, 0,  # operation data No. 0
                 *to_words(self.regs.type_absolute),
                 *to_words(round(position_mm * spm)),
                 *to_words(max(round(abs(speed_mm_s) * spm), 1)),
                 *to_words(max(round(accel * spm), 1)),  # 1 = 0.001 kHz/s = 1 step/s^2
                 *to_words(max(round(accel * spm), 1)),
                 *to_words(round(self.current_percent * 10)),  # 1 = 0.1 %
                 *to_words(1)]  # trigger: apply all and start
        # An absolute move is idempotent: a write whose reply was lost is sent once more.
        if not self._write("move", self.regs.direct_data, block):
            self._write_checked("move (again)", self.regs.direct_data, block)

    def stop(self, attempts: int = 3) -> bool:
        """STOP bit on the input command, retried at once if not acknowledged; released by the
        next move. False if no attempt was acknowledged (the caller keeps trying; the drive's
        communication timeout is the backstop)."""
        self._stop_latched = True
        for _ in range(attempts):
            try:
                if self._write("stop", self.regs.input_command, [0, 1 << self.regs.bit_stop]):
                    return True
            except DeviceError:
                # too many failures in a row: still try the remaining attempts
                self._consecutive = 0
        return False

    def home(self) -> None:
        """The drive's return-to-home operation (ZHOME)."""
        self._write_checked("release", self.regs.input_command, [0, 0])
        self._write_checked("home", self.regs.input_command, [0, 1 << self.regs.bit_zhome])
        self._stop_latched = True  # the ZHOME level must be released before the next move

    def reset_alarm(self) -> None:
        self._write_checked("alarm reset", self.regs.alarm_reset, [0, 1])
        self._write_checked("alarm reset", self.regs.alarm_reset, [0, 0])

    def set_comm_timeout(self, timeout_s: float) -> bool:
        """Write the drive's communication timeout and read it back; False if the profile has no
        register for it. `DeviceError` if the drive does not take it."""
        address = self.regs.comm_timeout_ms
        if address is None:
            return False
        want = round(timeout_s * 1000)
        self._write_checked("comm timeout", address, to_words(want), attempts=SETUP_ATTEMPTS)
        reply = self._again("read comm timeout", self.client.read_holding_registers, address, count=2,
                            attempts=SETUP_ATTEMPTS)
        got = from_words(*reply.registers[:2]) if reply is not None else None
        if got != want:
            raise DeviceError(f"slider ({self.link.describe()}): communication timeout written as "
                              f"{want} ms but reads back {got} (register 0x{address:04X})")
        return True

    def close(self) -> None:
        # closing a dead link must not raise
        with contextlib.suppress(Exception):
            self.client.close()
