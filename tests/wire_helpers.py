"""Helpers for tests over real wires: a raw pseudo-terminal and a scripted Modbus RTU device."""

from __future__ import annotations

import os
import pty
import select
import threading
import time
import tty


def crc16(frame: bytes) -> bytes:
    """Modbus RTU CRC (poly 0xA001, init 0xFFFF), low byte first; written here independently."""
    crc = 0xFFFF
    for b in frame:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes([crc & 0xFF, crc >> 8])


def rtu(hexstr: str) -> bytes:
    body = bytes.fromhex(hexstr.replace(" ", ""))
    return body + crc16(body)


def raw_pty() -> tuple[int, int, str]:
    master, slave = pty.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    return master, slave, os.ttyname(slave)


def read_exactly(fd: int, n: int, timeout_s: float = 2.0) -> bytes:
    out = bytearray()
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        r, _, _ = select.select([fd], [], [], 0.05)
        if r:
            out += os.read(fd, n - len(out))
    return bytes(out)


class ScriptedDevice:
    """Answers each expected request with a canned reply and records what actually came."""

    def __init__(self, exchanges: list[tuple[bytes, bytes]]) -> None:
        self.exchanges = exchanges
        self.received: list[bytes] = []
        self.master, self.slave, self.path = raw_pty()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        for expected, reply in self.exchanges:
            got = read_exactly(self.master, len(expected))
            self.received.append(got)
            if got != expected:
                return
            os.write(self.master, reply)

    def close(self) -> None:
        self._thread.join(3.0)
        for fd in (self.master, self.slave):
            os.close(fd)
