"""Protocol-level tests: the exact bytes the drivers send, and how they parse replies."""

from __future__ import annotations

import os
import threading
import time

import pytest
from rig.drivers.modbus_slider import ModbusLink, ModbusSlider
from rig.drivers.registers import PROFILES
from rig.drivers.serial_loadcell import SerialLoadCell

from rig.errors import DeviceError
from tests.wire_helpers import ScriptedDevice, crc16, raw_pty, read_exactly, rtu


def test_crc_of_a_textbook_frame():
    assert crc16(bytes.fromhex("010300000001")) == bytes.fromhex("840A")


def slider_on(dev: ScriptedDevice) -> ModbusSlider:
    link = ModbusLink("rtu", port=dev.path, timeout_s=0.5)
    return ModbusSlider(link, PROFILES["oriental_az"], steps_per_mm=100.0)


def run_script(exchanges, action):
    dev = ScriptedDevice(exchanges)
    slider = slider_on(dev)
    try:
        result = action(slider)
    finally:
        slider.close()
        dev.close()
    assert dev.received == [e[0] for e in exchanges]
    return result, slider


def test_position_read_bytes():
    pos, slider = run_script(
        [(rtu("01 03 00CC 0002"), rtu("01 03 04 FFFF CFC7"))],  # -12345 steps
        lambda s: s.read_position_mm())
    assert pos == pytest.approx(-123.45)
    assert slider.stats.transactions == 1 and slider.stats.errors == 0


def test_status_and_alarm_in_one_read():
    # READY (bit 5) + IN-POS (bit 14), alarm code 0x30
    status, _ = run_script(
        [(rtu("01 03 007E 0004"), rtu("01 03 08 0000 4020 0000 0030"))],
        lambda s: s.read_status())
    assert status.ready and status.in_position and not status.moving
    assert status.alarm and status.alarm_code == 0x30


def test_move_is_one_direct_data_write():
    # 30 mm at 0.75 mm/s, 50 mm/s^2, 100 steps/mm: absolute, 3000 steps, 75 Hz, rate 5000, 100 %
    request = rtu("01 10 0058 0010 20"
                  "00000000 00000001 00000BB8 0000004B 00001388 00001388 000003E8 00000001")
    run_script([(request, rtu("01 10 0058 0010"))], lambda s: s.move_to(30.0, 0.75, 50.0))


def test_stop_then_next_move_releases_stop():
    stop = rtu("01 10 007C 0002 04 0000 0020")
    release = rtu("01 10 007C 0002 04 0000 0000")
    move = rtu("01 10 0058 0010 20"
               "00000000 00000001 00000000 000001F4 00001388 00001388 000003E8 00000001")

    def act(s):
        s.stop()
        s.move_to(0.0, 5.0, 50.0)

    run_script([(stop, rtu("01 10 007C 0002")), (release, rtu("01 10 007C 0002")),
                (move, rtu("01 10 0058 0010"))], act)


def test_exception_reply_is_counted_and_ridden_through():
    exchanges = [(rtu("01 03 00CC 0002"), rtu("01 03 04 0000 0064")),  # 100 steps = 1 mm
                 (rtu("01 03 00CC 0002"), rtu("01 83 02"))]  # illegal data address
    dev = ScriptedDevice(exchanges)
    slider = slider_on(dev)
    try:
        assert slider.read_position_mm() == 1.0
        assert slider.read_position_mm() == 1.0  # last good value, error counted
        assert slider.stats.errors == 1
    finally:
        slider.close()
        dev.close()


def test_connect_asks_again_after_a_lost_reply_and_still_verifies():
    release = (rtu("01 10 007C 0002 04 0000 0000"), rtu("01 10 007C 0002"))
    read_back = rtu("01 03 007C 0002")
    # the read-back is refused once (busy), then answered: the trial opens, the error counted
    _, slider = run_script([release, (read_back, rtu("01 83 06")), (read_back, rtu("01 03 04 0000 0000"))],
                           lambda s: s.prepare())
    assert slider.stats.errors == 1 and slider.stats.transactions == 3
    # a STOP that stays set is still refused after the retry: verification is not retried away
    with pytest.raises(DeviceError, match="STOP stays set"):
        run_script([release, (read_back, rtu("01 83 06")), (read_back, rtu("01 03 04 0000 0020"))],
                   lambda s: s.prepare())
    # and a drive that never answers the read-back fails after three attempts, saying why
    with pytest.raises(DeviceError, match="cannot read back the input command register"):
        run_script([release] + [(read_back, rtu("01 83 06"))] * 3, lambda s: s.prepare())


def test_load_cell_poll_request_and_parse():
    master, slave, path = raw_pty()
    cell = SerialLoadCell(path, mode="poll", request=b"W\r")
    try:
        assert cell.latest() is None  # nothing has answered yet
        assert read_exactly(master, 2) == b"W\r"
        os.write(master, b"  -18.78 lbF\r\n")
        deadline = time.monotonic() + 2
        while cell.stats.lines_ok == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        reading = cell.latest()
        assert reading.force_N == pytest.approx(-18.78 * 4.4482216152605)
        assert cell.stats.transactions == 2
    finally:
        cell.close()
        os.close(master)
        os.close(slave)


# ------------------------------------------------------------ RTU replies read by their length

class PiecewiseDevice:
    """Answers one request with its reply in pieces, `gap_s` apart (a USB adapter hands bytes on
    in pieces; a slow drive may pause mid-frame), then writes `after` (bytes of some later frame)."""

    def __init__(self, request: bytes, pieces: list[bytes], gap_s: float, after: bytes = b"") -> None:
        self.request, self.pieces, self.gap_s, self.after = request, pieces, gap_s, after
        self.master, self.slave, self.path = raw_pty()
        self.received = b""
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        self.received = read_exactly(self.master, len(self.request))
        for i, piece in enumerate(self.pieces):
            if i:
                time.sleep(self.gap_s)
            os.write(self.master, piece)
        if self.after:
            os.write(self.master, self.after)

    def close(self) -> None:
        self._thread.join(3.0)
        for fd in (self.master, self.slave):
            os.close(fd)


def _read_position_from(dev: PiecewiseDevice, timeout_s: float = 0.5):
    slider = ModbusSlider(ModbusLink("rtu", port=dev.path, timeout_s=timeout_s), PROFILES["oriental_az"],
                          steps_per_mm=100.0, max_consecutive_errors=10)
    try:
        reading = slider.position()
        # what the device wrote after the reply may still be on its way through the pty
        deadline = time.monotonic() + 1.0
        while slider.client.socket.in_waiting < len(dev.after) and time.monotonic() < deadline:
            time.sleep(0.005)
        waiting = slider.client.socket.in_waiting
    finally:
        slider.close()
        dev.close()
    return reading, slider, waiting


@pytest.mark.parametrize("gap_s", [0.0, 0.001, 0.006])
def test_a_reply_in_pieces_is_one_frame(gap_s):
    """Pieces of one reply, up to 6 ms apart (a drive pausing mid-frame, an adapter's USB frames),
    make one frame: the position comes, no error counted."""
    reply = rtu("01 03 04 FFFF CFC7")  # -12345 steps
    dev = PiecewiseDevice(rtu("01 03 00CC 0002"), [reply[:2], reply[2:5], reply[5:]], gap_s)
    reading, slider, _ = _read_position_from(dev)
    assert dev.received == rtu("01 03 00CC 0002")
    assert reading.fresh and reading.value == pytest.approx(-123.45)
    assert slider.stats.errors == 0


def test_the_read_takes_the_reply_and_no_byte_more():
    """The read stops at the length the reply's header gives: bytes behind it stay in the port
    (where the next request's send finds them and throws them away, as a late reply)."""
    late = rtu("01 03 04 0000 0001")
    dev = PiecewiseDevice(rtu("01 03 00CC 0002"), [rtu("01 03 04 0000 0064")], 0.0, after=late)
    reading, _, waiting = _read_position_from(dev)
    assert reading.value == pytest.approx(1.0)
    assert waiting == len(late)


def test_an_exception_reply_is_five_bytes_and_an_error():
    dev = PiecewiseDevice(rtu("01 03 00CC 0002"), [rtu("01 83 02")], 0.0)
    slider = ModbusSlider(ModbusLink("rtu", port=dev.path, timeout_s=0.5), PROFILES["oriental_az"],
                          steps_per_mm=100.0)
    try:
        with pytest.raises(DeviceError, match=r"no position read yet.*exception reply 2"):
            slider.position()
    finally:
        slider.close()
        dev.close()


def test_no_reply_is_a_timeout_not_a_hang():
    dev = PiecewiseDevice(rtu("01 03 00CC 0002"), [], 0.0)
    slider = ModbusSlider(ModbusLink("rtu", port=dev.path, timeout_s=0.05), PROFILES["oriental_az"],
                          steps_per_mm=100.0)
    t0 = time.monotonic()
    try:
        with pytest.raises(DeviceError, match="no position read yet"):
            slider.position()
    finally:
        slider.close()
        dev.close()
    assert time.monotonic() - t0 < 1.0  # one 50 ms timeout and the drain after it, not a hang
