"""Online RLS: convergence, freezing out of contact, bounded covariance, forgetting laws."""

from __future__ import annotations

import numpy as np
import pytest

from rig.control.estimator import StiffnessRLS, excitation_order
from rig.recording.logs import read_log


def test_converges_to_a_constant_stiffness():
    rng = np.random.default_rng(3)
    rls = StiffnessRLS(rate_Hz=100)
    x = np.linspace(0.001, 0.02, 2000)
    f = 120.0 * x + rng.normal(0, 0.08, x.size)
    for xi, fi in zip(x, f, strict=True):
        rls.update(xi, fi)
    assert rls.k == pytest.approx(120.0, rel=0.03)


def test_a_priori_error_uses_previous_estimate():
    rls = StiffnessRLS(rate_Hz=100, initial_stiffness_N_per_m=50.0)
    step = rls.update(0.01, 0.8)
    assert step.force_pred_N == pytest.approx(0.5)
    assert step.error_N == pytest.approx(0.3)
    assert step.updated and rls.k > 50.0


def test_frozen_out_of_contact_and_covariance_bounded():
    rls = StiffnessRLS(rate_Hz=100, contact_mm=0.2)
    for _ in range(100):
        rls.update(0.01, 0.8)
    k, p = rls.k, rls.p
    for _ in range(10_000):  # probe lifted off: x = 0, force 0
        step = rls.update(0.0, 0.0)
        assert not step.updated and step.forgetting == 1.0
    assert rls.k == k and rls.p == p
    rls2 = StiffnessRLS(rate_Hz=100, lambda_min=0.5, lambda_max=0.5)
    for _ in range(1000):  # heavy forgetting with a tiny regressor would wind P up
        rls2.update(0.00021, 0.06)
    assert rls2.p <= rls2.p_max


def test_forgetting_drops_when_error_grows():
    rls = StiffnessRLS(rate_Hz=100, memory_s=1.0)
    rng = np.random.default_rng(0)
    for _ in range(500):
        rls.update(0.02, 2.0 + rng.normal(0, 0.08))
    quiet = np.mean([rls.update(0.02, 2.0 + rng.normal(0, 0.08)).forgetting for _ in range(200)])
    assert quiet == pytest.approx(0.99, abs=0.005)
    jumps = [rls.update(0.02, 3.0 + rng.normal(0, 0.08)).forgetting for _ in range(5)]
    assert min(jumps) < 0.95


def test_excitation_order():
    t = np.arange(0, 60, 0.01)
    ramp_hold = np.minimum(t * 0.75, 30.0)
    sine = 2.0 * np.sin(2 * np.pi * 0.5 * t)
    res = 0.01
    assert excitation_order(np.zeros_like(t), res) == 0
    assert excitation_order(ramp_hold, res) == 1
    assert excitation_order(sine, res) == 2


def _tracking(rls_kwargs, x, f, t, t_hold, contact):
    rls = StiffnessRLS(rate_Hz=100, **rls_kwargs)
    k = np.empty(len(x))
    e = np.empty(len(x))
    x_prev = 0.0
    for i in range(len(x)):
        s = rls.update(x_prev, f[i])
        k[i], e[i] = s.stiffness_N_per_m, s.error_N
        x_prev = x[i]
    trans = (t > t_hold - 1) & (t < t_hold + 10) & contact
    late = (t > t_hold + 50) & (t < t_hold + 60)
    return np.sqrt(np.mean(e[trans] ** 2)), np.std(k[late])


def test_time_varying_forgetting_beats_fixed_at_the_transition(paper_075_log):
    """Same nominal memory: the varying law tracks the ramp-to-hold corner better, and is as
    quiet as the fixed law once the force has settled at the end of the hold."""
    log = read_log(paper_075_log.log_path)
    s = log.samples
    kinds = np.array(log.step_kind)
    t = s["t_s"]
    t_hold = t[np.argmax(kinds == "hold")]
    x, f = s["position_mm"] / 1000.0, s["force_N"]
    noise = 0.08
    for memory_s in (0.3, 1.0):
        rms_v, quiet_v = _tracking({"law": "constant_information", "memory_s": memory_s},
                                   x, f, t, t_hold, log.contact)
        rms_f, quiet_f = _tracking({"law": "fixed", "memory_s": memory_s}, x, f, t, t_hold, log.contact)
        # tracking error beyond the sensor noise
        excess_v = np.sqrt(max(rms_v ** 2 - noise ** 2, 0))
        excess_f = np.sqrt(max(rms_f ** 2 - noise ** 2, 0))
        assert excess_v < 0.8 * excess_f, (memory_s, excess_v, excess_f)
        assert quiet_v <= 1.15 * quiet_f, (memory_s, quiet_v, quiet_f)
