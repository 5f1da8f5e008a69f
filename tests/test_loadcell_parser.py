"""The load-cell line parser: formats, units, calibration, and random bytes (never a crash)."""

from __future__ import annotations

import contextlib
import math
import os
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rig.drivers.serial_loadcell import LineFormat, LineRejected, SerialLoadCell, parse_line

from tests.wire_helpers import raw_pty


@pytest.mark.parametrize("line,expected", [
    (b"4.285 N", 4.285),
    (b"+0001.5000 N", 1.5),
    (b"-18.78 lbF", -18.78 * 4.4482216152605),
    (b"250 g", 0.250 * 9.80665),
    (b"0.5", 0.5),
    (b"1e-3 kN", 1.0),
])
def test_formats(line, expected):
    assert parse_line(line, LineFormat()) == pytest.approx(expected)


def test_counts_calibration_and_custom_pattern():
    fmt = LineFormat(pattern=r"^ST,GS,(?P<value>[-+]?\d+)$", counts=True, gain_N_per_count=0.002,
                     offset_counts=1000)
    assert parse_line(b"ST,GS,+1500", fmt) == pytest.approx(1.0)
    with pytest.raises(LineRejected, match="does not match"):
        parse_line(b"US,GS,+1500", fmt)


@pytest.mark.parametrize("line,why", [
    (b"", "empty"), (b"abc N", "does not match"), (b"1.2 furlong", "unknown unit"),
    (b"\xff\xfe", "not ASCII"), (b"9999 N", "beyond the cell's range"), (b"1.2.3 N", "does not match"),
])
def test_rejections(line, why):
    with pytest.raises(LineRejected, match=why):
        parse_line(line, LineFormat())


@settings(max_examples=2000, deadline=None)
@given(st.binary(max_size=64))
def test_random_bytes_never_crash(data):
    fmt = LineFormat(max_abs_N=100.0)
    try:
        force = parse_line(data, fmt)
    except LineRejected:
        return
    assert math.isfinite(force) and abs(force) <= 100.0


@settings(max_examples=200, deadline=None)
@given(st.text(alphabet="0123456789+-.eE Nlbfkg\t", max_size=24))
def test_number_like_text_never_crashes(text):
    with contextlib.suppress(LineRejected):
        parse_line(text.encode(), LineFormat())


def test_reader_survives_a_stream_of_garbage():
    master, slave, path = raw_pty()
    cell = SerialLoadCell(path)
    try:
        rng = __import__("random").Random(7)
        junk = bytes(rng.randrange(256) for _ in range(5000))
        os.write(master, junk + b"\r\n" + b"1.25 N\r\n")
        deadline = time.monotonic() + 3
        while (cell.latest() is None or cell.latest().force_N != 1.25) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert cell.latest().force_N == 1.25
        assert cell.stats.lines_bad > 0
    finally:
        cell.close()
        os.close(master)
        os.close(slave)
