"""The simulated wire is as slow as a lab's: bytes paced at the baud rate and frame, plus the
USB adapter's latency, measured over the real pseudo-terminals.

Lower bounds are tight: a reply must never come before the wire allows (latency + every byte of
request and reply at bits/baud). Upper bounds are loose, so they hold on a loaded 2-core machine
(tried with two CPU-bound processes beside the test): the quickest reply within SLACK_BEST_S of
the model (the drive's own time), the median within SLACK_MEDIAN_S. The timed exchanges run as
the rig runs them: the devices in a `rig sim` process of their own (real-time scheduling where
allowed), the master in a thread at the loop's real-time priority. Without that a loaded machine
puts the test's threads behind the CPU hogs for tens of milliseconds, which is the scheduler's
time, not the wire's.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import select
import socket
import statistics
import time
import tty

import pytest
from rig.sim.line import USB_FRAME_S, Framing, Line, PacedWriter
from rig.sim.params import SimParams
from rig.sim.process import SimProcess
from rig.sim.server import WireSim, wire_note

from rig.realtime import Realtime
from tests.wire_helpers import crc16

SLACK_BEST_S = 0.003
SLACK_MEDIAN_S = 0.010
POSITION_READ = bytes([0x01, 0x03, 0x00, 0xCC, 0x00, 0x02])  # FC03 feedback position x2: 8 + 9 bytes




def rtu(pdu: bytes) -> bytes:
    return pdu + crc16(pdu)


def direct_data_write() -> bytes:
    """FC16 of 16 registers (the loop's move): a 41-byte request, an 8-byte reply; trigger 0, so
    nothing moves."""
    words = [0, 1, 0, 0, 0, 1000, 0, 1000, 0, 1000, 0, 1000, 0, 1000, 0, 0]
    body = b"".join(w.to_bytes(2, "big") for w in words)
    return rtu(bytes([0x01, 0x10, 0x00, 0x58, 0x00, 0x10, len(body)]) + body)


def open_raw(path: str) -> int:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    return fd


@contextlib.contextmanager
def sim_process(sim_yaml: str):
    """The simulated devices in a `rig sim` process, configured by the `sim:` block given."""
    proc = SimProcess("sim:\n" + "".join(f"  {line}\n" for line in sim_yaml.strip().splitlines()))
    try:
        yield proc.endpoints
    finally:
        proc.close()


@contextlib.contextmanager
def loop_priority():
    """This thread at the control loop's real-time priority, where allowed (the loop's default)."""
    rt = Realtime("auto", 50)
    rt.enter()
    try:
        yield
    finally:
        rt.leave()


def round_trips(fd: int, request: bytes, reply_len: int, n: int, gap_s: float = 0.002) -> list[float]:
    """Seconds from just before the request is written to the moment its whole reply is read."""
    out = []
    for _ in range(n):
        buf = b""
        t0 = time.monotonic()
        os.write(fd, request)
        while len(buf) < reply_len:
            ready, _, _ = select.select([fd], [], [], 1.0)
            assert ready, f"no reply after {len(buf)} bytes"
            buf += os.read(fd, 256)
        out.append(time.monotonic() - t0)
        assert len(buf) == reply_len and buf[-2:] == crc16(buf[:-2])
        time.sleep(gap_s)
    return out


def sim_params(baudrate: int, parity: str, latency_ms: float = 1.0) -> SimParams:
    p = SimParams()
    p.drive.baudrate, p.drive.parity, p.usb_latency_ms = baudrate, parity, latency_ms
    return p


# ------------------------------------------------------------------ the line model

@pytest.mark.parametrize("parity,stopbits,bits", [("N", 1, 10), ("E", 1, 11), ("O", 1, 11), ("N", 2, 11)])
def test_bits_per_byte_follow_the_frame(parity: str, stopbits: int, bits: int) -> None:
    f = Framing(115200, parity, stopbits)
    assert f.bits_per_byte == bits
    assert f.bytes_s(17) == pytest.approx(17 * bits / 115200)


def test_no_piece_is_due_before_its_bytes_have_crossed_the_line() -> None:
    f = Framing(19200, "E")
    line = Line(f, 0.001)
    data = bytes(range(40))
    pieces = line.pieces(data, 10.0)
    assert b"".join(d for _, d in pieces) == data
    assert len(pieces) > 1  # 40 bytes at 19200 8E1 take 23 ms: handed on once per USB frame
    sent = 0
    for due, chunk in pieces:
        sent += len(chunk)
        assert due >= 10.0 + f.bytes_s(sent) + 0.001 - 1e-12
    assert pieces[-1][0] == pytest.approx(10.0 + f.bytes_s(40) + 0.001)
    # once per USB frame; the last piece comes as soon as the last byte is in
    assert all(b[0] - a[0] >= USB_FRAME_S - 1e-12 for a, b in itertools.pairwise(pieces[:-1]))
    # half duplex: what comes next waits for the line
    (due, _), = line.pieces(b"x" * 8, 10.0, latency=False, trickle=False)
    assert due == pytest.approx(10.0 + f.bytes_s(48))


def test_the_writer_never_writes_early() -> None:
    got: list[tuple[float, bytes]] = []
    w = PacedWriter()
    try:
        now = time.monotonic()
        w.put(lambda d: got.append((time.monotonic(), d)), [(now + 0.004, b"b"), (now + 0.002, b"a")])
        deadline = time.monotonic() + 2
        while len(got) < 2 and time.monotonic() < deadline:
            time.sleep(0.001)
    finally:
        w.close()
    assert [d for _, d in got] == [b"a", b"b"]
    assert got[0][0] >= now + 0.002 and got[1][0] >= now + 0.004


# ------------------------------------------------------------------ over the real pty

@pytest.mark.slow
@pytest.mark.parametrize("baudrate,parity", [(115200, "N"), (115200, "E"), (19200, "N"), (19200, "E")])
def test_rtu_reply_comes_when_the_wire_allows(baudrate: int, parity: str) -> None:
    """FC03 position read (8 + 9 bytes) and FC16 direct-data write (41 + 8 bytes): the reply is
    never earlier than latency + bytes x bits / baud, both directions counted."""
    framing = Framing(baudrate, parity)
    with sim_process(f"drive: {{baudrate: {baudrate}, parity: {parity}}}") as ep, loop_priority():
        fd = open_raw(ep["modbus_rtu"])
        try:
            reads = round_trips(fd, rtu(POSITION_READ), 9, 60)
            writes = round_trips(fd, direct_data_write(), 8, 20)
        finally:
            os.close(fd)
    for what, times, n_bytes in (("read", reads, 8 + 9), ("write", writes, 41 + 8)):
        model = 0.001 + framing.bytes_s(n_bytes)
        print(f"{framing.describe()} {what}: model {model * 1e3:.3f} ms, min {min(times) * 1e3:.3f}, "
              f"median {statistics.median(times) * 1e3:.3f}, max {max(times) * 1e3:.3f} ms")
        assert min(times) >= model, f"{what}: a reply came before the wire allows"
        assert min(times) <= model + SLACK_BEST_S
        assert statistics.median(times) <= model + SLACK_MEDIAN_S


@pytest.mark.slow
def test_the_usb_latency_is_a_setting() -> None:
    framing = Framing(115200, "N")
    with sim_process("usb_latency_ms: 16") as ep, loop_priority():
        fd = open_raw(ep["modbus_rtu"])
        try:
            times = round_trips(fd, rtu(POSITION_READ), 9, 10)
        finally:
            os.close(fd)
    model = 0.016 + framing.bytes_s(17)
    assert model <= min(times) <= model + SLACK_BEST_S
    assert statistics.median(times) <= model + SLACK_MEDIAN_S


@pytest.mark.slow
def test_unpaced_wire_is_the_instant_pty() -> None:
    p = sim_params(9600, "E")
    p.pace_wire = False
    assert "not paced" in wire_note(p)
    with WireSim(p, tcp=False, loadcell=False) as sim:
        fd = open_raw(sim.endpoints.modbus_rtu)
        try:
            times = round_trips(fd, rtu(POSITION_READ), 9, 20)
        finally:
            os.close(fd)
    assert statistics.median(times) < 0.001 + Framing(9600, "E").bytes_s(17)


@pytest.mark.slow
def test_polled_load_cell_answers_after_both_directions_and_its_conversion() -> None:
    framing = Framing(9600)
    with sim_process("loadcell: {mode: poll, baudrate: 9600, reply_ms: 2.0}") as ep, loop_priority():
        fd = open_raw(ep["loadcell"])
        try:
            times, line = [], b""
            for _ in range(15):
                line = b""
                t0 = time.monotonic()
                os.write(fd, b"?\r\n")
                while not line.endswith(b"\r\n"):
                    ready, _, _ = select.select([fd], [], [], 1.0)
                    assert ready
                    line += os.read(fd, 256)
                times.append(time.monotonic() - t0)
                time.sleep(0.002)
        finally:
            os.close(fd)
    # the cell answers on the request's CR ("?\r", 2 bytes); its LF crosses while it converts
    model = 0.001 + 0.002 + framing.bytes_s(2 + len(line))
    assert model <= min(times) <= model + SLACK_BEST_S
    assert statistics.median(times) <= model + SLACK_MEDIAN_S


@pytest.mark.slow
def test_streamed_lines_are_paced_by_the_line() -> None:
    """200 lines/s asked of a 9600-baud cell: a 12-byte line takes 12.5 ms, so the host gets
    about 80 lines/s, each complete line at least a line's time after the one before."""
    framing = Framing(9600)
    with sim_process("loadcell: {baudrate: 9600}") as ep, loop_priority():
        fd = open_raw(ep["loadcell"])
        try:
            buf, ends = b"", []
            stop = time.monotonic() + 1.0
            while time.monotonic() < stop:
                ready, _, _ = select.select([fd], [], [], 0.1)
                if ready:
                    chunk = os.read(fd, 256)
                    now = time.monotonic()
                    buf += chunk
                    ends += [now] * chunk.count(b"\n")
        finally:
            os.close(fd)
    line_s = framing.bytes_s(len(buf.split(b"\r\n")[1]) + 2)
    gaps = [b - a for a, b in itertools.pairwise(ends[3:])]
    assert statistics.median(gaps) >= line_s * 0.9  # reads can bunch two lines, never shorten the line
    assert len(ends) <= 1.0 / line_s + 2


@pytest.mark.slow
def test_tcp_gets_a_latency_only_when_asked() -> None:
    req = bytes([0, 1, 0, 0, 0, 6]) + POSITION_READ  # MBAP header + PDU

    def rtts(sim_yaml: str) -> list[float]:
        with sim_process(sim_yaml) as ep, loop_priority():
            host, port = ep["modbus_tcp"].rsplit(":", 1)
            with contextlib.closing(socket.create_connection((host, int(port)), timeout=2)) as s:
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                out = []
                for _ in range(15):
                    t0 = time.monotonic()
                    s.sendall(req)
                    got = b""
                    while len(got) < 13:
                        got += s.recv(64)
                    out.append(time.monotonic() - t0)
                return out

    slow = rtts("tcp_latency_ms: 5")
    assert 0.005 <= min(slow) <= 0.005 + SLACK_BEST_S
    assert statistics.median(slow) <= 0.005 + SLACK_MEDIAN_S
    assert statistics.median(rtts("seed: 1")) < 0.005  # default: no latency
