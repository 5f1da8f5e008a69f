"""The wire spy: every Modbus frame and load-cell line, each way, with its time (pyserial's
`spy://` for this rig).

The drivers hand bytes to a tap (`record(channel, direction, data)`) as they cross the
port: the Modbus clients at their send/recv, the load cell's port at its write/read.
`WireSpy` is the tap that writes a file: the caller's side (the loop thread among them)
only puts the bytes on a bounded queue, never waits on the disk; a writer thread cuts
them into frames and lines and writes them. When the queue is full a record is dropped
and counted, and the file says how many.

File format (text; `rig spy FILE` decodes it):
    # rig spy 1
    # started 2026-11-22T11:30:00+00:00
    # channel rtu Modbus RTU /dev/ttyUSB0 115200 8E1 unit 1; profile oriental_az
    0.012345 rtu > 01 03 00 CC 00 02 04 34
    0.014502 rtu < 01 03 04 FF FF CF C7 ...
    0.015001 cell < 2B 30 2E 31 32 33 34 20 4E 0D 0A
    # dropped 0
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Protocol

from pymodbus.client import ModbusTcpClient
from rig.drivers.rtu_client import FramedSerialClient
from rig.drivers.serial_loadcell import SerialLoadCell
from rig.drivers.wireframes import FROM_DEVICE, TO_DEVICE, Assembler, WireRecord

SPY_MAGIC = "# rig spy 1"


class WireTap(Protocol):
    def record(self, channel: str, direction: str, data: bytes) -> None:
        """Bytes that just crossed a port; must not block."""


def format_record(r: WireRecord) -> str:
    line = f"{r.t_s:.6f} {r.channel} {r.direction} {r.data.hex(' ').upper()}"
    return line + " partial" if r.partial else line


class WireSpy:
    """A tap that writes a spy file from its own thread."""

    def __init__(self, path: str | Path, *, max_queue: int = 50000, flush_s: float = 0.5,
                 clock=time.monotonic) -> None:
        from rig.errors import RigError

        self.path = Path(path)
        try:
            self._fh = open(self.path, "w", encoding="ascii")  # noqa: SIM115 - closed by the writer thread
        except OSError as exc:
            raise RigError(f"cannot write the spy file {self.path}: {exc.strerror or exc}") from None
        self._clock = clock
        self.t0 = clock()
        self.dropped = 0
        self.written = 0
        self._q: queue.Queue = queue.Queue(max_queue)
        self._flush_s = flush_s
        self._assemblers: dict[str, Assembler] = {}
        self._fh.write(f"{SPY_MAGIC}\n# started {datetime.now(UTC).isoformat(timespec='seconds')}\n")
        self._thread = threading.Thread(target=self._run, name="wire-spy", daemon=True)
        self._closed = False
        self._thread.start()

    # ------------------------------------------------------------ caller side
    def record(self, channel: str, direction: str, data: bytes) -> None:
        try:
            self._q.put_nowait((self._clock() - self.t0, channel, direction, bytes(data)))
        except queue.Full:
            self.dropped += 1

    def describe(self, channel: str, text: str) -> None:
        """What a channel is connected to, for the file's header."""
        with contextlib.suppress(queue.Full):
            self._q.put_nowait(("channel", channel, text))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._q.put(None)
        self._thread.join(10.0)

    # ------------------------------------------------------------ writer thread
    def _run(self) -> None:
        last_flush = time.monotonic()
        try:
            while True:
                try:
                    item = self._q.get(timeout=self._flush_s)
                except queue.Empty:
                    item = ()
                if item is None:
                    break
                if len(item) == 3:
                    self._fh.write(f"# channel {item[1]} {item[2]}\n")
                elif item:
                    t_s, channel, direction, data = item
                    asm = self._assemblers.setdefault(channel, Assembler(channel))
                    self._write(asm.feed(t_s, direction, data))
                if time.monotonic() - last_flush >= self._flush_s:
                    self._fh.flush()
                    last_flush = time.monotonic()
            for asm in self._assemblers.values():
                self._write(asm.flush())
            self._fh.write(f"# dropped {self.dropped}\n")
        except OSError:
            pass  # a full disk ends the spy, never the trial
        finally:
            with contextlib.suppress(OSError):
                self._fh.close()

    def _write(self, records: list[WireRecord]) -> None:
        for r in records:
            self._fh.write(format_record(r) + "\n")
            self.written += 1


class MemoryTap:
    """A tap that keeps what it sees (`rig probe` reads the load cell's lines from it)."""

    def __init__(self, clock=time.monotonic) -> None:
        self._clock = clock
        self.chunks: list[tuple[float, str, str, bytes]] = []

    def record(self, channel: str, direction: str, data: bytes) -> None:
        self.chunks.append((self._clock(), channel, direction, bytes(data)))

    def records(self, channel: str) -> list[WireRecord]:
        asm = Assembler(channel)
        out: list[WireRecord] = []
        for t, ch, d, data in list(self.chunks):
            if ch == channel:
                out += asm.feed(t, d, data)
        return out + asm.flush()


class Tee:
    """Several taps as one."""

    def __init__(self, *taps: WireTap | None) -> None:
        self.taps = [t for t in taps if t is not None]

    def record(self, channel: str, direction: str, data: bytes) -> None:
        for t in self.taps:
            t.record(channel, direction, data)


# ------------------------------------------------------------------ where the bytes are seen

class _SpiedClient:
    """Modbus client whose every request and reply bytes go to a tap (RTU and TCP alike)."""

    tap: WireTap
    channel: str

    def send(self, request: bytes, addr: tuple | None = None) -> int:
        if request:
            self.tap.record(self.channel, TO_DEVICE, request)
        return super().send(request, addr)

    def recv(self, size: int | None) -> bytes:
        data = super().recv(size)
        if data:
            self.tap.record(self.channel, FROM_DEVICE, data)
        return data


class SpiedSerialClient(_SpiedClient, FramedSerialClient):
    channel = "rtu"

    def send(self, request: bytes, addr: tuple | None = None) -> int:
        # A reply that came after its timeout waits in the port; the client throws it away
        # before the next request. Read it here first so the spy shows it arrived late.
        if request and self.socket is not None:
            with contextlib.suppress(OSError, ValueError, TypeError):
                waiting = self.socket.in_waiting
                if waiting:
                    late = self.socket.read(waiting)
                    if late:
                        self.tap.record(self.channel, FROM_DEVICE, late)
        return super().send(request, addr)


class SpiedTcpClient(_SpiedClient, ModbusTcpClient):
    channel = "tcp"


class SpyPort:
    """A pyserial port whose writes and reads also go to a tap (pyserial's spy:// idea)."""

    def __init__(self, port, tap: WireTap, channel: str = "cell") -> None:
        self._port = port
        self._tap = tap
        self._channel = channel

    def write(self, data: bytes) -> int | None:
        n = self._port.write(data)
        self._tap.record(self._channel, TO_DEVICE, data)
        return n

    def read(self, size: int = 1) -> bytes:
        data = self._port.read(size)
        if data:
            self._tap.record(self._channel, FROM_DEVICE, data)
        return data

    def __getattr__(self, name: str):
        return getattr(self._port, name)


class SpiedSerialLoadCell(SerialLoadCell):
    """The load-cell driver unchanged, its port (also after a reopen) behind a `SpyPort`."""

    def __init__(self, port: str, *, tap: WireTap, **kwargs) -> None:
        self._tap = tap
        super().__init__(port, **kwargs)

    def _connect(self):
        return SpyPort(super()._connect(), self._tap, "cell")
