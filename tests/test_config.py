"""Rig config: the shipped file is the built-in default; bad configs say where and what."""

from __future__ import annotations

import pytest

from rig.errors import SpecError
from rig.specs.config import RigConfig, load_config, parse_config
from tests.conftest import ROOT


def test_shipped_sim_config_equals_builtin_defaults():
    assert load_config(ROOT / "config" / "sim-rig.yaml") == RigConfig()


def test_defaults_round_trip_through_yaml():
    cfg = RigConfig()
    assert parse_config(cfg.to_yaml()) == cfg


def test_partial_config_keeps_defaults():
    cfg = parse_config("limits: {max_force_N: 8}\nsim: {tissue: {k3_N_per_m: 30}}\n")
    assert cfg.limits.max_force_N == 8
    assert cfg.sim.tissue.k3_N_per_m == 30
    assert cfg.loop.rate_Hz == 100


def test_hidden_effect_switched_on_in_config():
    cfg = parse_config("sim: {effects: {delay: {delay_s: 0.05}, drift: {}}}\n")
    assert cfg.sim.effects.active() == ["drift", "delay"]
    assert cfg.sim.effects.delay.delay_s == 0.05


@pytest.mark.parametrize("text,line,fragment", [
    ("loop: {rate_hz: 100}\n", 1, "did you mean 'rate_Hz'"),
    ("limits:\n  max_force_N: -3\n", 2, "must be greater than 0"),
    ("limits:\n  travel_mm: [10, 0]\n", 2, "min < max"),
    ("estimator: {law: magic}\n", 1, "'magic' is not one of"),
    ("sim:\n  effects:\n    delays: {delay_s: 1}\n", 3, "did you mean 'delay'"),
    ("loop: {rate_Hz: fast}\n", 1, "expected a number"),
])
def test_bad_config(text, line, fragment):
    with pytest.raises(SpecError) as info:
        parse_config(text, "rig.yaml")
    msg = str(info.value)
    assert msg.startswith(f"rig.yaml:{line}"), msg
    assert fragment in msg
