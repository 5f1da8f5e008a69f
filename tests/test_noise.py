"""Coloured noise: the noise level and correlation time are measured as the instrument delivers
them, and adequacy is judged against that noise, not against whiteness at the sample rate."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from rig.analysis.diagnosis.explain import explain
from rig.analysis.fitting.fit import fit
from rig.analysis.stats.noise import from_baseline, from_residual, integral_scale
from rig.analysis.trials.data import load_trial
from rig.models import CATALOGUE, build_model
from rig.specs.config import RigConfig
from tests.conftest import PROTOCOLS, run_sim


def ar1(n: int, rho: float, std: float, seed: int) -> np.ndarray:
    """A first-order low-pass of white noise, scaled to `std`."""
    w = np.random.default_rng(seed).normal(0.0, std * np.sqrt(1 - rho ** 2), n)
    return lfilter([1.0], [1.0, -rho], w)


@pytest.mark.parametrize(("rho", "seed"), [(0.0, 1), (0.5, 2), (0.8, 3), (0.9, 4)])
def test_noise_level_and_correlation_from_the_residual(rho, seed):
    n = 40000
    noise = ar1(n, rho, 0.05, seed)
    t = np.linspace(0.0, 1.0, n)
    misfit = 0.3 * np.exp(-t / 0.2)  # a smooth model error many times the noise
    est = from_residual([noise + misfit])
    assert est.std_N == pytest.approx(0.05, rel=0.05)
    assert est.scale_samples == pytest.approx((1 + rho) / (1 - rho), rel=0.15)
    # white-noise arithmetic (differences over sqrt 2) would call filtered noise much smaller
    if rho >= 0.5:
        assert np.std(np.diff(noise)) / np.sqrt(2) < 0.75 * est.std_N


def test_noise_from_a_baseline_at_rest():
    base = [ar1(3000, 0.7, 2e-10, 5), ar1(2500, 0.7, 2e-10, 6)]
    est = from_baseline(base)
    assert est.std_N == pytest.approx(2e-10, rel=0.1)
    assert est.scale_samples == pytest.approx(integral_scale(base[0]), rel=0.3)
    assert from_baseline([np.zeros(20)]) is None  # too short to say


def filtered_trials(tmp_path, cutoff_Hz: float, seed: int):
    paths = []
    for i, v in enumerate(("0.75", "1.5", "3")):
        cfg = RigConfig()
        cfg.sim.loadcell.lowpass_Hz = cutoff_Hz
        cfg.sim.seed = seed * 10 + i
        paths.append(run_sim(PROTOCOLS / f"paper-{v}mm_s.yaml", cfg, tmp_path, name=f"{v}.mcap").log_path)
    return [load_trial(p) for p in paths]


@pytest.mark.parametrize(("cutoff_Hz", "seed"), [(12.0, 31), (12.0, 32), (20.0, 33)])
def test_a_filtered_load_cell_without_hidden_effects_is_adequate(tmp_path, cutoff_Hz, seed):
    """The simulated indicator low-passes its signal and its noise (at 100 Hz logging). The
    paper's model is the truth here: it must be called adequate and nothing suggested."""
    trials = filtered_trials(tmp_path, cutoff_Hz, seed)
    res = fit(build_model("proposed"), trials)
    a = np.exp(-2 * np.pi * cutoff_Hz * 0.01)
    assert res.noise_L == pytest.approx((1 + a) / (1 - a), rel=0.2)  # the filter's own correlation
    assert res.noise_N == pytest.approx(0.08 * np.sqrt((1 - a) / (1 + a)), rel=0.1)
    assert res.adequate, res.report()
    ex = explain(res, dict(CATALOGUE))
    assert ex.suggestions == [], ex.summary
    assert ex.summary.startswith("the model is adequate")
    # the white-noise view would have refused it: noise from differences over sqrt 2 and a
    # residual that must be uncorrelated sample to sample
    white_noise = float(np.std(np.concatenate([np.diff(r) for r in res.residuals])) / np.sqrt(2))
    assert res.overall.rmse_N > 1.2 * white_noise and res.white_L > 1.5


def test_filter_config_is_off_by_default():
    assert RigConfig().sim.loadcell.lowpass_Hz == 0.0
