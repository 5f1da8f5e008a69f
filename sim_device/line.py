"""The simulated devices' wires as slow as the real ones: bytes paced at the baud rate and frame,
and a USB-serial adapter's latency on the way back to the host.

A pseudo-terminal delivers bytes the moment they are written, so on its own it proves a loop
rate at no cost. Here every byte a simulated device sends or receives takes its time on the
line (start bit, 8 data bits, parity bit if any, stop bits, at the baud rate), one byte after
another; a half-duplex RS-485 line carries one direction at a time, so a request and its reply
share one `Line`. A byte from the device then waits in the USB adapter for `latency_s` before
the host can read it (an FTDI adapter holds received bytes up to its latency timer), handed on
in pieces at most once per USB frame, as the adapter does.

The pacing lives here, on the simulated devices' side of the pseudo-terminal: the rig's drivers
see only bytes arriving later, exactly as on a lab's wire.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

USB_FRAME_S = 0.001  # a full-speed USB adapter hands received bytes to the host once per 1 ms frame


@dataclass(frozen=True)
class Framing:
    """A serial frame: how long one byte occupies the line."""

    baudrate: int
    parity: str = "N"
    stopbits: int = 1
    bytesize: int = 8

    def __post_init__(self) -> None:
        if self.baudrate <= 0:
            raise ValueError(f"baudrate must be positive, got {self.baudrate}")
        if self.parity not in ("N", "E", "O"):
            raise ValueError(f"parity must be N, E or O, got {self.parity!r}")

    @property
    def bits_per_byte(self) -> int:
        """Start bit, data bits, the parity bit if any, stop bits: 10 in 8N1, 11 in 8E1/8O1/8N2."""
        return 1 + self.bytesize + (self.parity != "N") + self.stopbits

    @property
    def byte_s(self) -> float:
        return self.bits_per_byte / self.baudrate

    def bytes_s(self, n: int) -> float:
        return n * self.byte_s

    def describe(self) -> str:
        return f"{self.baudrate} {self.bytesize}{self.parity}{self.stopbits}"


class Line:
    """One serial line (or one direction of a full-duplex one): bytes leave one after another.

    `carry(n, ready_s)` books n bytes that are ready to go at `ready_s` and returns when they
    start and when the last one has arrived; a line still busy with earlier bytes delays them.
    Without a framing the line takes no time (TCP): only the latency applies.
    """

    def __init__(self, framing: Framing | None, latency_s: float = 0.0) -> None:
        self.framing = framing
        self.latency_s = max(latency_s, 0.0)
        self._free_s = 0.0
        self._lock = threading.Lock()  # the two directions of a half-duplex line book it from two threads
        self.bytes = 0
        self.busy_s = 0.0  # time the line has carried bytes (the wire's share of the run)

    @property
    def paced(self) -> bool:
        return self.framing is not None or self.latency_s > 0

    def free_at(self) -> float:
        with self._lock:
            return self._free_s

    def carry(self, n: int, ready_s: float) -> tuple[float, float]:
        took = self.framing.bytes_s(n) if self.framing is not None else 0.0
        with self._lock:
            start = max(ready_s, self._free_s)
            end = start + took
            self._free_s = end
            self.bytes += n
            self.busy_s += took
        return start, end

    def pieces(self, data: bytes, ready_s: float, *, latency: bool = True,
               trickle: bool = True) -> list[tuple[float, bytes]]:
        """When each part of `data` may be read at the far end: (due time, bytes), in order.

        No byte is due before it has crossed the line (plus the adapter's latency when
        `latency`). With `trickle` the bytes come out in pieces, once per USB frame, as they
        cross; without, all at once when the last one has (a device acts on a whole frame).
        """
        start, end = self.carry(len(data), ready_s)
        lat = self.latency_s if latency else 0.0
        if not trickle or self.framing is None or end - start <= USB_FRAME_S:
            return [(end + lat, data)]
        byte_s = self.framing.byte_s
        out: list[tuple[float, bytes]] = []
        sent = 0
        t = start + USB_FRAME_S
        # a piece a fraction of a frame before the last would only cost a wake-up: the last takes it
        while t < end - USB_FRAME_S / 4:
            done = min(int((t - start) / byte_s), len(data))
            if done > sent:
                out.append((t + lat, data[sent:done]))
                sent = done
            t += USB_FRAME_S
        if sent < len(data):
            out.append((end + lat, data[sent:]))
        return out


class PacedWriter:
    """Writes each piece at its due time, never before: one thread, pieces in due order.

    Whoever puts pieces goes on at once (a bridge keeps reading while a reply is still on the
    line); the writer sleeps until the next piece is due. A piece for a destination that is gone
    is the write function's business (it may drop it).
    """

    def __init__(self, name: str = "paced-writer") -> None:
        self._heap: list[tuple[float, int, Callable[[bytes], None], bytes]] = []
        self._seq = itertools.count()
        self._cond = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, write: Callable[[bytes], None], pieces: list[tuple[float, bytes]]) -> None:
        with self._cond:
            for due, data in pieces:
                heapq.heappush(self._heap, (due, next(self._seq), write, data))
            self._cond.notify()

    def pending(self) -> int:
        with self._cond:
            return len(self._heap)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._stop:
                    if self._heap:
                        wait = self._heap[0][0] - time.monotonic()
                        if wait <= 0:
                            break
                        self._cond.wait(wait)
                    else:
                        self._cond.wait()
                if self._stop:
                    return
                _, _, write, data = heapq.heappop(self._heap)
            write(data)

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(2.0)
