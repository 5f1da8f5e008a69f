"""--profile: profile-likelihood intervals for parameters that trade off (the fractional branch's
k, tau and alpha are correlated beyond 0.97). Where the data pin the valley down, the profile is
the +/-1.96 SE interval (an independent check of both); where they do not, it is lopsided as a
time constant's should be, and still holds the truth."""

from __future__ import annotations

import json

import numpy as np

from rig.analysis.fitting.fit import fit
from rig.analysis.intervals.profile import interval, trading
from rig.analysis.trials.data import prepare
from rig.cli import main
from rig.models import build_model
from rig.records.csvfile import write_trial_csv
from rig.records.record import Record
from rig.specs.frames import Frame
from tests.conftest import per_seed
from tests.test_fractional_exact import exact_force_N

TRUTH = {"k_f_N_per_m": 0.03, "tau_f_s": 0.05, "alpha_f": 0.3}


def fractional(seed: int, noise_N: float):
    rng = np.random.default_rng(seed)
    dt = 1e-3
    t = np.arange(0.0, 6.2, dt)
    x = np.clip(1e-6 * (t - 0.2), 0.0, 1e-6)
    m = prepare(Record("shape", "csv", t, x, np.zeros_like(t), Frame.SURFACE)).motion
    force = exact_force_N(np.where(m.x_m > 0, m.v_m_s, 0.0), dt, *TRUTH.values())
    rec = Record(f"fractional-{seed}", "mcap", t, x, force + rng.normal(0.0, noise_N, len(t)), Frame.SURFACE,
                 baseline_force_N=rng.normal(0.0, noise_N, 1000))
    return prepare(rec)


def _tau(seed: int, noise_N: float) -> tuple[float, float, float, float, float]:
    res = fit(build_model("fractional_relaxation"), [fractional(seed, noise_N)])
    iv = interval(res, "tau_f_s")
    return iv.value, iv.low, iv.high, *iv.wald


def test_where_the_valley_is_narrow_the_profile_is_the_wald_interval():
    for _, low, high, w_low, w_high in per_seed(_tau, range(2), 2e-11):
        width = w_high - w_low
        assert abs(low - w_low) < 0.03 * width and abs(high - w_high) < 0.03 * width


def test_where_it_is_wide_the_profile_is_lopsided_and_holds_the_truth():
    for v, low, high, w_low, _ in per_seed(_tau, range(3), 4e-10):
        assert low < TRUTH["tau_f_s"] < high
        assert high - v > 1.15 * (v - low)  # a time constant: longer on the slow side
        assert low > w_low  # the symmetric interval reaches further down than the data allow


def test_the_command_line_profiles_what_trades_off(tmp_path, capsys):
    trial = fractional(1, 1e-10)
    res = fit(build_model("fractional_relaxation"), [trial])
    assert set(trading(res)) == {"k_f_N_per_m", "tau_f_s", "alpha_f"}
    path = tmp_path / "fractional.csv"
    write_trial_csv(trial, path)
    assert main(["analyze", str(path), "--model", "fractional_relaxation", "--profile", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["profile"]) == {"k_f_N_per_m", "tau_f_s", "alpha_f"}
    tau = out["profile"]["tau_f_s"]
    assert tau["low"] < tau["value"] < tau["high"]
    assert main(["analyze", str(path), "--model", "fractional_relaxation", "--profile"]) == 0
    text = capsys.readouterr().out
    assert "profile 95 % intervals (parameters that trade off" in text
    assert text.count("+/-1.96 SE: [") == 3
    assert main(["analyze", str(path), "--model", "hooke", "--profile"]) == 0
    assert "profile: no parameters trade off" in capsys.readouterr().out
