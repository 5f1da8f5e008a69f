"""Load-cell driver: ASCII lines over a serial port (or any pyserial URL).

Streamed (the device pushes lines) or polled (the driver sends a request each time
the loop asks; the reply arrives before the next tick). A reader thread parses every
line; the loop only ever takes the newest reading and its age, so it never blocks on
the port. Garbage, partial and out-of-range lines are counted and skipped; a port that
disappears is reopened, and the readings' age tells the loop the sensor is silent.
A line beyond the cell's range (`max_abs_N`) is not skipped: it is kept, flagged
`over_range`, until the loop has taken it (a good line right after it does not hide it), so
the loop stops on an overload at once.
"""

from __future__ import annotations

import contextlib
import re
import threading
import time
from dataclasses import dataclass

import serial
from rig.drivers.base import ForceReading, LinkStats

# Force per unit, to newtons.
UNITS_N = {"N": 1.0, "kN": 1000.0, "mN": 0.001, "lbf": 4.4482216152605, "lbF": 4.4482216152605,
           "kgf": 9.80665, "g": 0.00980665, "gf": 0.00980665, "kg": 9.80665}

DEFAULT_PATTERN = r"^\s*(?P<value>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(?P<unit>[A-Za-z]+)?\s*$"


@dataclass(frozen=True)
class LineFormat:
    """How to turn one line into newtons."""

    pattern: str = DEFAULT_PATTERN  # needs a group 'value'; an optional group 'unit'
    unit: str = "N"  # assumed when the line carries none
    counts: bool = False  # raw counts: force = gain * (value - offset)
    gain_N_per_count: float = 1.0
    offset_counts: float = 0.0
    max_abs_N: float = 500.0  # beyond the cell's range: a bad line, not a force

    def compile(self) -> re.Pattern[str]:
        rx = re.compile(self.pattern)
        if "value" not in rx.groupindex:
            raise ValueError("the load-cell pattern needs a named group 'value'")
        return rx


class LineRejected(ValueError):
    def __init__(self, reason: str, out_of_range: bool = False, force_N: float | None = None) -> None:
        super().__init__(reason)
        self.out_of_range = out_of_range
        self.force_N = force_N  # the value an over-range line carried


def parse_line(raw: bytes, fmt: LineFormat, rx: re.Pattern[str] | None = None) -> float:
    """One line (without its terminator) to newtons, or `LineRejected` saying why."""
    try:
        text = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        raise LineRejected("not ASCII") from None
    if not text:
        raise LineRejected("empty line")
    m = (rx or fmt.compile()).match(text)
    if m is None:
        raise LineRejected(f"does not match the line pattern: {text[:40]!r}")
    try:
        value = float(m.group("value"))
    except (TypeError, ValueError):
        raise LineRejected(f"no number in {text[:40]!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise LineRejected("not a finite number")
    if fmt.counts:
        force = fmt.gain_N_per_count * (value - fmt.offset_counts)
    else:
        unit = (m.groupdict().get("unit") or fmt.unit)
        if unit not in UNITS_N:
            raise LineRejected(f"unknown unit {unit!r}")
        force = value * UNITS_N[unit]
    if abs(force) > fmt.max_abs_N:
        raise LineRejected(f"{force:g} N is beyond the cell's range", out_of_range=True, force_N=force)
    return force


class SerialLoadCell:
    def __init__(self, port: str, *, baudrate: int = 115200, mode: str = "stream",
                 request: bytes = b"?\r\n", fmt: LineFormat | None = None, clock=None,
                 reopen_s: float = 0.5) -> None:
        if mode not in ("stream", "poll"):
            raise ValueError(f"load-cell mode must be 'stream' or 'poll', not {mode!r}")
        self.port = port
        self.baudrate = baudrate
        self.mode = mode
        self.request = request
        self.fmt = fmt or LineFormat()
        self._rx = self.fmt.compile()
        self.clock = clock
        self.reopen_s = reopen_s
        self.stats = LinkStats()
        self.last_rejected = ""
        self._latest: ForceReading | None = None
        self._over_range: ForceReading | None = None  # kept until the loop has seen it
        self._latest_lock = threading.Lock()  # the reader and the loop, for a few bytecodes
        self._stop = threading.Event()
        self._serial = self._open()
        self._write_lock = threading.Lock()
        self.thread = threading.Thread(target=self._read_loop, name=f"loadcell {port}", daemon=True)
        self.thread.start()

    def _now(self) -> float:
        return self.clock.now() if self.clock is not None else time.monotonic()

    def _connect(self) -> serial.SerialBase:
        # exclusive: flock on the device (POSIX), so a second reader is refused, not interleaved
        return serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.05, exclusive=True)

    def _open(self) -> serial.SerialBase:
        from rig.errors import DeviceError

        try:
            return self._connect()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"load cell: cannot open {self.port}: {exc}") from None

    # ------------------------------------------------------------ loop side
    def latest(self) -> ForceReading | None:
        if self.mode == "poll":
            self._send_request()
        with self._latest_lock:
            r, self._over_range = self._over_range or self._latest, None
        if r is None:
            return None
        return ForceReading(r.force_N, r.t_s, self._now() - r.t_s, r.over_range)

    def _send_request(self) -> None:
        with self._write_lock:
            try:
                self._serial.write(self.request)
                self.stats.transactions += 1
            except (serial.SerialException, OSError):
                self.stats.errors += 1

    def close(self) -> None:
        self._stop.set()
        self.thread.join(2.0)
        # the port may already be gone
        with contextlib.suppress(Exception):
            self._serial.close()

    # ------------------------------------------------------------ reader thread
    def _read_loop(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            try:
                chunk = self._serial.read(max(1, self._serial.in_waiting or 1))
            except (serial.SerialException, OSError, TypeError):
                self.stats.errors += 1
                self._reopen()
                buf.clear()
                continue
            if not chunk:
                continue
            buf += chunk
            while True:
                i = min((k for k in (buf.find(b"\n"), buf.find(b"\r")) if k >= 0), default=-1)
                if i < 0:
                    if len(buf) > 256:  # a line that never ends is garbage
                        self._reject("line too long")
                        buf.clear()
                    break
                line = bytes(buf[:i])
                del buf[: i + 1]
                if not line.strip():
                    continue  # the other half of a CRLF
                self._take(line)

    def _take(self, line: bytes) -> None:
        try:
            force = parse_line(line, self.fmt, self._rx)
        except LineRejected as exc:
            if exc.out_of_range:
                self.stats.out_of_range += 1
                self.last_rejected = str(exc)
                over = ForceReading(exc.force_N, self._now(), 0.0, over_range=True)
                with self._latest_lock:
                    self._latest = self._over_range = over
                return
            self._reject(str(exc))
            return
        self.stats.lines_ok += 1
        reading = ForceReading(force, self._now(), 0.0)
        with self._latest_lock:
            self._latest = reading

    def _reject(self, why: str) -> None:
        self.stats.lines_bad += 1
        self.last_rejected = why

    def _reopen(self) -> None:
        with contextlib.suppress(Exception):
            self._serial.close()
        while not self._stop.wait(self.reopen_s):
            try:
                self._serial = self._connect()
                return
            except (serial.SerialException, OSError, ValueError):
                self.stats.errors += 1
