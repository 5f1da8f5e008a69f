"""Smaller seams of the loop: an over-range reading kept until the loop has seen it, a stale
position never taken for arrival, a hold during an abort carried out (not answered ok and
dropped)."""

from __future__ import annotations

import os
import time

from rig.drivers.serial_loadcell import SerialLoadCell

from rig.clock import VirtualClock
from rig.control.devices import open_devices
from rig.control.states import StopMode
from rig.control.trial import Trial
from rig.recording.logs import read_log
from rig.specs.config import RigConfig
from rig.specs.protocol import parse_protocol
from tests.wire_helpers import raw_pty


def test_an_over_range_reading_is_kept_until_the_loop_has_seen_it():
    """A good line right after an overload used to replace it before the loop's next tick: the
    loop never saw the overload."""
    master, slave, path = raw_pty()
    cell = SerialLoadCell(path)
    try:
        os.write(master, b"900 N\r\n0.50 N\r\n")
        deadline = time.monotonic() + 3
        while (cell.stats.lines_ok < 1 or cell.stats.out_of_range < 1) and time.monotonic() < deadline:
            time.sleep(0.005)
        assert cell.stats.lines_ok == 1 and cell.stats.out_of_range == 1
        first = cell.latest()
        assert first.over_range and first.force_N == 900.0
        second = cell.latest()  # seen once: now the newest good reading
        assert not second.over_range and second.force_N == 0.5
    finally:
        cell.close()
        os.close(master)
        os.close(slave)


def _trial(tmp_path, text: str):
    cfg = RigConfig()
    clock = VirtualClock(0)
    dev = open_devices(cfg, clock)
    return Trial(parse_protocol(text, "t.yaml"), cfg, dev.slider, dev.loadcell, clock, tmp_path / "t.mcap"), dev


RAMP_HOLD = ("name: ramp hold\nsteps:\n  - ramp: {to_mm: 5, speed_mm_s: 5}\n  - hold: {duration_s: 0.5}\n"
             "  - return: {speed_mm_s: 5}\n")


def test_a_stale_position_is_no_arrival(tmp_path):
    """The position reads fail just as the ramp nears its target: the step used to end on the
    stale value (and the drive's motion unknown); it now ends only on fresh readings."""
    trial, dev = _trial(tmp_path, RAMP_HOLD)
    window = {}

    def blind(snap):
        if snap.step == 0 and "from" not in window and abs(snap.position_mm - 5.0) <= 0.02:  # the tolerance
            window["from"] = snap.t_s
            dev.slider.unreadable = True
        elif "from" in window and "to" not in window and snap.t_s >= window["from"] + 0.15:
            window["to"] = snap.t_s
            dev.slider.unreadable = False

    trial.on_tick = blind
    result = trial.run()
    dev.close()
    assert result.outcome == "completed", result.fault
    assert "to" in window
    log = read_log(result.log_path)
    hold = next(e for e in log.events if e["kind"] == "step_start" and e["data"]["step"] == 1)
    assert hold["t_s"] > window["to"]  # not before a fresh position came back
    assert abs(log.samples["position_mm"][-1]) <= 0.02


def test_a_hold_during_an_abort_stops_the_return_where_it_is(tmp_path):
    trial, dev = _trial(tmp_path, "name: r\nsteps:\n  - ramp: {to_mm: 10, speed_mm_s: 5}\n")
    tickets = {}

    def operator(snap):
        if snap.t_s >= 1.5 and "abort" not in tickets:
            tickets["abort"] = trial.request_stop(StopMode.ABORT, user="tester")
        if snap.step_kind == "return" and snap.position_mm < 3.0 and "hold" not in tickets:
            tickets["hold"] = trial.request_stop(StopMode.HOLD, user="tester")

    trial.on_tick = operator
    result = trial.run()
    dev.close()
    hold = tickets["hold"]
    assert hold.done.is_set() and hold.acknowledged and hold.message.startswith("STOP sent in")
    assert result.outcome == "stopped"
    pos = read_log(result.log_path).samples["position_mm"]
    assert 1.0 < pos[-1] < 3.0  # held where it was, not returned to the start
