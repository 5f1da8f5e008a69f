"""Limits as pure functions of one tick's state."""

from __future__ import annotations

import math

import pytest

from rig.control.safety import TickState, check
from rig.specs.config import LimitsConfig

LIM = LimitsConfig(max_force_N=10, travel_mm=(-5, 45), max_speed_mm_s=10, loadcell_stale_ms=100,
                   overspeed_factor=1.5)
OK = dict(force_N=1.0, position_abs_mm=10.0, speed_mm_s=1.0, loadcell_age_s=0.0)


def test_nominal_state_passes():
    assert check(TickState(**OK), LIM) is None


@pytest.mark.parametrize("change,kind", [
    ({"force_N": 10.001}, "force_limit"),
    ({"position_abs_mm": 45.01}, "travel"),
    ({"position_abs_mm": -5.01}, "travel"),
    ({"speed_mm_s": -15.1}, "overspeed"),
    ({"loadcell_age_s": 0.101}, "loadcell_stale"),
    ({"loadcell_age_s": None}, "loadcell_stale"),
    ({"alarm_code": 0x85}, "drive_alarm"),
])
def test_each_limit(change, kind):
    fault = check(TickState(**{**OK, **change}), LIM)
    assert fault is not None and fault.kind == kind


def test_limits_are_inclusive():
    assert check(TickState(**{**OK, "force_N": 10.0, "position_abs_mm": 45.0,
                               "speed_mm_s": 15.0, "loadcell_age_s": 0.1}), LIM) is None


@pytest.mark.parametrize("source", ["estimated", "measured"])
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_a_force_that_is_not_a_number_is_a_fault(source, value):
    """On a rig without a load cell the force is a model's: a NaN from it compared False with
    the limit and switched the limit off."""
    fault = check(TickState(**{**OK, "force_N": value, "force_source": source}), LIM)
    assert fault is not None and fault.kind == "force_invalid"
    assert fault.message.endswith("the force limit cannot be checked")
