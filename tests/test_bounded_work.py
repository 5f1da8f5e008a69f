"""A tick's work does not grow with the protocol: the time left, which the status snapshot reads
every tick, is the current step's rest plus a sum made once. At `repeat: 5000` a walk over every
remaining step every tick took 25 ms a tick (287 late and 527 missed ticks in 11 s)."""

from __future__ import annotations

import pytest

import rig.control.sequencer as sequencer_module
from rig.control.sequencer import Sequencer
from rig.specs.protocol import parse_protocol


def _sequencer(repeat: int) -> Sequencer:
    text = (f"name: many\nrepeat: {repeat}\nsteps:\n  - ramp: {{to_mm: 1, speed_mm_s: 5}}\n"
            "  - hold: {duration_s: 0.1}\n  - ramp: {to_mm: 0, speed_mm_s: 5}\n")
    return Sequencer(parse_protocol(text, "<test>"), start_mm=0.0, accel_mm_s2=50.0, tare_s=0.5,
                     tolerance_mm=0.02, rate_Hz=100.0)


@pytest.mark.parametrize("repeat", [3, 3000])
def test_the_time_left_costs_the_same_whatever_the_protocol(repeat, monkeypatch):
    seq = _sequencer(repeat)
    calls = []
    real = sequencer_module.move_time
    monkeypatch.setattr(sequencer_module, "move_time", lambda *a: calls.append(a) or real(*a))
    t, pos = 0.0, 0.0
    for _ in range(400):  # the tare, then the first steps, as the loop would tick them
        t += 0.01
        for cmd in seq.tick(t, pos, 0.0, False):
            pos = getattr(cmd, "to_mm", pos)
        seq.time_left_s(t)
    assert seq.index >= 2
    assert len(calls) <= 400  # one planned move a tick at most, never one a remaining step


def test_the_time_left_adds_up_to_the_plan():
    seq = _sequencer(3)
    # 3 x (two 1 mm moves at 5 mm/s with 50 mm/s^2 ramps, 0.3 s each, and a 0.1 s hold) + the tare
    assert seq.time_left_s(0.0) == pytest.approx(0.5 + 3 * (0.3 + 0.1 + 0.3), abs=1e-9)
