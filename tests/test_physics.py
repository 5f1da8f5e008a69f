"""The simulated rig's physics: the paper's magnitudes, the slider profile, each hidden effect."""

from __future__ import annotations

import numpy as np
import pytest
from rig.sim.params import (
    ComplianceParams,
    ContactOffsetParams,
    DelayParams,
    DriftParams,
    FrictionParams,
    OffsetParams,
    Relaxation2Params,
    SimParams,
)
from rig.sim.physics import SimRig, SliderMotion


def ramp_hold(params: SimParams, speed=0.75, depth=30.0, hold_s=60.0, dt=0.01):
    """Run ramp-hold-return; return time, slider position, sensor force (no noise) at dt."""
    rig = SimRig(params)
    rig.slider.move_to(depth, speed)
    t_ramp = depth / speed + 0.5
    ts = np.arange(dt, t_ramp + hold_s + depth / 5 + 2, dt)
    pos, force, tissue = [], [], []
    returned = False
    for t in ts:
        if not returned and t >= t_ramp + hold_s:
            rig.slider.move_to(0.0, 5.0)
            returned = True
        rig.advance(t)
        pos.append(rig.slider.position_mm)
        force.append(rig.sensor_force_N)
        tissue.append(rig.tissue_force_N)
    return ts, np.array(pos), np.array(force), np.array(tissue), t_ramp


def quiet(**effects) -> SimParams:
    p = SimParams()
    p.loadcell.noise_N = 0.0
    for k, v in effects.items():
        setattr(p.effects, k, v)
    return p


@pytest.fixture(scope="module")
def base():
    return ramp_hold(quiet())


def test_paper_magnitudes(base):
    t, _x, f, _, t_ramp = base
    peak = f[t < t_ramp].max()
    relaxed = f[(t > t_ramp + 55) & (t < t_ramp + 59)].mean()
    assert 5.0 <= peak <= 6.5
    assert 2.2 <= relaxed <= 2.6
    # ever steeper during the ramp: the second half gains more than the first
    ramp = f[t < t_ramp - 0.5]
    assert ramp[-1] - ramp[len(ramp) // 2] > 1.5 * (ramp[len(ramp) // 2] - ramp[0])


def test_force_never_negative(base):
    _, _, f, tissue, _ = base
    assert tissue.min() >= 0.0 and f.min() >= 0.0


def test_faster_ramp_peaks_higher():
    peaks = [ramp_hold(quiet(), speed=v, hold_s=1)[2].max() for v in (0.75, 3.0)]
    assert peaks[1] > peaks[0] + 2


def test_slider_trapezoid_respects_accel_and_speed():
    m = SliderMotion(accel_mm_s2=50.0, stop_decel_mm_s2=2000.0)
    m.move_to(10.0, 4.0)
    dt = 0.0005
    v = [0.0]
    for _ in range(20000):
        m.step(dt)
        v.append(m.velocity_mm_s)
        if not m.moving:
            break
    assert m.position_mm == 10.0 and not m.moving
    v = np.array(v)
    assert v.max() == pytest.approx(4.0, rel=1e-6)
    accel = np.abs(np.diff(v[:-1])) / dt
    assert accel.max() <= 50.0 * (1 + 1e-6)
    assert v[-2] <= 2 * 50.0 * dt + 1e-9  # lands at the target at crawl speed, no crash stop
    # trapezoid: 4 mm/s reached after 80 ms, cruising, 10 mm in about 10/4 + 4/50 s
    assert len(v) * dt == pytest.approx(10 / 4 + 4 / 50, abs=0.01)


def test_stop_decelerates_at_stop_rate():
    m = SliderMotion(accel_mm_s2=50.0, stop_decel_mm_s2=2000.0)
    m.move_to(30.0, 3.0)
    for _ in range(2000):
        m.step(0.0005)
    m.stop()
    steps = 0
    while m.moving:
        m.step(0.0005)
        steps += 1
    assert steps * 0.0005 <= 3.0 / 2000.0 + 0.001


def test_feedback_position_is_quantised():
    rig = SimRig(quiet())
    rig.slider.move_to(1.2345, 1.0)
    rig.advance(3.0)
    assert rig.feedback_position_mm() * 100 == pytest.approx(round(rig.feedback_position_mm() * 100))


def test_noise_level_matches_config():
    p = SimParams()
    rig = SimRig(p)
    readings = np.array([rig.read_force_N() for _ in range(4000)])
    assert readings.std() == pytest.approx(0.08, rel=0.06)
    assert np.allclose(readings / 0.001, np.round(readings / 0.001))


# ------------------------------------------------------------ hidden effects, as mechanisms

def test_relaxation2_adds_slow_decay(base):
    t, _, f2, _, t_ramp = ramp_hold(quiet(relaxation2=Relaxation2Params(k_m_N_per_m=60, tau_m_s=40)))
    _, _, f, _, _ = base
    hold = (t > t_ramp + 30) & (t < t_ramp + 59)
    # late in the hold the base model has settled; the second branch is still relaxing
    slope_base = np.polyfit(t[hold], f[hold], 1)[0]
    slope_r2 = np.polyfit(t[hold], f2[hold], 1)[0]
    assert slope_r2 < slope_base - 0.005


def test_drift_is_linear_in_time_also_before_contact():
    rig = SimRig(quiet(drift=DriftParams(rate_N_per_s=0.01)))
    rig.advance(10.0)  # probe never moves: no contact at all
    assert rig.sensor_force_N == pytest.approx(0.1, rel=1e-3)


def test_offset_appears_once_the_probe_moves():
    rig = SimRig(quiet(offset=OffsetParams(force_N=0.3)))
    rig.advance(1.0)
    assert rig.sensor_force_N == 0.0
    rig.slider.move_to(-2.0, 1.0)  # away from the tissue: only the cable pulls
    rig.advance(3.0)
    assert rig.sensor_force_N == pytest.approx(0.3)


def test_contact_offset_delays_contact():
    _t, x, f, _, _ = ramp_hold(quiet(contact_offset=ContactOffsetParams(x0_mm=2.0)), hold_s=1)
    first = x[np.argmax(f > 0)]
    assert 2.0 <= first <= 2.1


def test_delay_shifts_the_force(base):
    _t, _, fd, _, _ = ramp_hold(quiet(delay=DelayParams(delay_s=0.1)))
    _, _, f, _, _ = base
    # the delayed trace is the base trace 10 samples (0.1 s) later
    assert np.allclose(fd[10:500], f[:490], atol=1e-9)


def test_compliance_reduces_indentation(base):
    _, _, fc, _, _t_ramp = ramp_hold(quiet(compliance=ComplianceParams(k_frame_N_per_m=2000)))
    _, _, f, _, _ = base
    assert fc.max() < f.max() - 0.3


def test_friction_follows_the_sign_of_velocity(base):
    t, _, ff, _, t_ramp = ramp_hold(quiet(friction=FrictionParams(force_N=0.2)))
    _, _, f, _, _ = base
    d = ff - f
    ramp = (t > 2) & (t < t_ramp - 2)
    hold = (t > t_ramp + 2) & (t < t_ramp + 58)
    assert np.allclose(d[ramp], 0.2, atol=1e-3)
    assert np.allclose(d[hold], 0.0, atol=1e-6)
