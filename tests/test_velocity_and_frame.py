"""The indentation rate is smoothed only as much as the moving samples need, and the frame's
compliance is the model without it in the limit of a stiff frame."""

from __future__ import annotations

import numpy as np
import pytest

from rig.analysis.trials.data import prepare
from rig.models import build_model
from rig.records.record import Record
from rig.specs.frames import Frame


def ramp_in_a_long_hold(seed: int) -> tuple[Record, float]:
    """An oocyte-like record: a 1 s ramp at 20 um/s, then 31 s of hold, 1 kHz, encoder noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 32.0, 1e-3)
    speed = 20e-6
    x = np.clip(speed * (t - 0.5), 0.0, speed * 1.0) + rng.normal(0.0, 2e-9, len(t))
    return Record("oocyte-like", "csv", t, x, 1e-9 * x / 20e-6, Frame.SURFACE), speed


@pytest.mark.parametrize("seed", range(3))
def test_the_rate_follows_the_ramp_not_the_hold(seed):
    rec, speed = ramp_in_a_long_hold(seed)
    m = prepare(rec).motion
    t, v = m.t_s, m.v_m_s
    mid = (t > 0.8) & (t < 1.2)
    assert np.median(v[mid]) == pytest.approx(speed, rel=0.02)
    # the corner at the ramp's start is sharp: the rate rises from 10 % to 90 % of the speed
    # within a few hundredths of the ramp, not over a window set by the whole record's speed
    rising = np.flatnonzero((v > 0.1 * speed) & (v < 0.9 * speed) & (t < 0.8))
    assert len(rising) <= 30, len(rising)


@pytest.mark.parametrize("model", ["kelvin", "proposed", "hunt_crossley"])
def test_a_stiff_frame_is_the_model_without_it(model):
    rec, _ = ramp_in_a_long_hold(1)
    m = prepare(rec).motion
    base = build_model(model)
    values = {p.name: p.init for p in base.params}
    values.update({"k_N_per_m": 50.0, "k1_N_per_m3": 2e9, "tau1_s": 2.0, "k_N_per_m_n": 1e5})
    framed = build_model(model, ["compliance"])
    f0 = base.predict(values, m)
    f1 = framed.predict({**values, "k_frame_N_per_m": 1e12}, m)
    assert np.max(np.abs(f1 - f0)) <= 1e-9 * np.max(np.abs(f0))
