"""Standard errors with a correlated residual: the reported +/- must cover the truth as often
as it claims, over many seeds, where the white-noise formula claims far too much; the one BIC."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from rig.sim.params import DriftParams
from scipy.optimize import least_squares
from scipy.signal import lfilter

from rig.analysis.diagnosis.explain import explain
from rig.analysis.fitting.fit import fit
from rig.analysis.stats.criterion import bic, delta_bic
from rig.analysis.stats.uncertainty import hac_covariance, white_covariance
from rig.analysis.trials.data import load_trial
from rig.analysis.workflow.results import result_json
from rig.models import CATALOGUE, build_model
from rig.specs.config import RigConfig
from tests.conftest import run_sim

TRUE = np.array([1.0, 5.0, 0.2])  # amplitude, time constant (s), offset of a relaxation


def _relaxation(z: np.ndarray, t: np.ndarray) -> np.ndarray:
    return z[0] * np.exp(-t / z[1]) + z[2]


def _coverage(rho: float, seeds: int, n: int = 2500, trials: int = 2) -> dict[str, np.ndarray]:
    """Fraction of seeds whose fitted parameters lie within 1 and 1.96 reported standard
    errors of the truth; AR(1) noise of coefficient `rho`, several trials fitted jointly."""
    t = np.linspace(0.0, 30.0, n)
    rng = np.random.default_rng(7)
    hits = {k: np.zeros((2, 3)) for k in ("hac", "white")}
    for _ in range(seeds):
        e = rng.normal(size=(trials, n + 300))
        noise = 0.05 * lfilter([np.sqrt(1 - rho ** 2)], [1, -rho], e, axis=1)[:, 300:]
        y = np.concatenate([_relaxation(TRUE, t) + nk for nk in noise])
        sol = least_squares(lambda z, y=y: np.tile(_relaxation(z, t), trials) - y, [0.8, 4.0, 0.1])
        for k, cov in (("hac", hac_covariance(sol.jac, sol.fun, [n] * trials)),
                       ("white", white_covariance(sol.jac, sol.fun))):
            z = np.abs(sol.x - TRUE) / np.sqrt(np.diag(cov))
            hits[k] += [z <= 1.0, z <= 1.96]
    return {k: v / seeds for k, v in hits.items()}


@pytest.mark.parametrize("rho", [0.9, 0.98])
def test_reported_errors_cover_the_truth_with_correlated_noise(rho):
    """AR(1) noise correlated over 19 and 99 samples: the sandwich's 68 % and 95 % intervals
    hold (200 seeds: a coverage is known to about +/- 0.03); the white formula's are far
    too narrow, about sqrt(L) times."""
    cov = _coverage(rho, 200)
    one, two = cov["hac"]
    # the prewhitening's bias correction errs on the wide side at rho 0.98 (1 SE holds 0.75-0.83)
    assert np.all((one > 0.58) & (one < 0.86)), one
    assert np.all((two > 0.90) & (two < 0.99)), two
    assert np.all(cov["white"][1] < 0.6), cov["white"]


def test_white_noise_is_not_inflated():
    one, two = _coverage(0.0, 200)["hac"]
    assert np.all((one > 0.58) & (one < 0.78)), one
    assert np.all((two > 0.90) & (two < 0.99)), two


N_LINEAR = 3000


def linear_design(n: int = N_LINEAR) -> np.ndarray:
    """Baseline, slope and a Hertz-like term E max(x - x_c, 0)^1.5 with x_c known: the
    Jacobian of a linear least-squares fit of an indentation curve."""
    x = np.linspace(0.0, 1.0, n)
    return np.column_stack([np.ones(n), x, np.clip(x - 0.4, 0.0, None) ** 1.5])


def ar1_noise(rng: np.random.Generator, n: int, seeds: int, rho: float) -> np.ndarray:
    """(n, seeds) stationary AR(1) noise of unit variance."""
    e = rng.normal(size=(n, seeds)) * np.sqrt(1 - rho ** 2)
    e[0] = rng.normal(size=seeds)
    return lfilter([1.0], [1.0, -rho], e, axis=0)


def walk_noise(rng: np.random.Generator, n: int, seeds: int, size: float) -> np.ndarray:
    """White noise of unit variance plus a random walk from zero whose end-to-end standard
    deviation is `size` times the noise's."""
    return rng.normal(size=(n, seeds)) + np.cumsum(rng.normal(size=(n, seeds)), axis=0) * size / np.sqrt(n)


def linear_coverage(noise: np.ndarray, J: np.ndarray, covariance=hac_covariance) -> np.ndarray:
    """Per parameter, the fraction of the noise's columns whose least-squares error lies
    within 1.96 reported standard errors (the truth is zero)."""
    beta = np.linalg.lstsq(J, noise, rcond=None)[0]
    resid = noise - J @ beta
    se = np.array([np.sqrt(np.diag(covariance(J, resid[:, s], [len(J)]))) for s in range(noise.shape[1])])
    return np.mean(np.abs(beta.T) <= 1.96 * se, axis=0)


def test_errors_cover_near_a_unit_root_and_under_a_drift():
    """A linear indentation fit over 3000 samples, 200 seeds. AR(1) at rho 0.998 (about three
    independent stretches per record): the previous estimator (rho clipped at 0.99, bandwidth
    2) held the truth within 1.96 SE 40-48 % of the time, this one 94-98 %. White noise plus a
    walk as large as the noise over the record: 17-26 % with that estimator, 77-83 % with AR(8)
    prewhitening and a drift check, 88-93 % now that a local-level model competes with the AR."""
    J = linear_design()
    rng = np.random.default_rng(1)
    noise = ar1_noise(rng, N_LINEAR, 200, 0.998)
    told = lambda J, r, lengths: hac_covariance(J, r, lengths, quiet=[_approach(J)])  # noqa: E731
    for covariance in (hac_covariance, told):  # a slow noise is as slow at rest: not taken for a misfit
        near = linear_coverage(noise, J, covariance)
        assert np.all((near > 0.88) & (near < 0.995)), near
    drift = linear_coverage(walk_noise(rng, N_LINEAR, 200, 1.0), J)
    assert np.all((drift > 0.85) & (drift < 0.99)), drift


@pytest.mark.parametrize("size", [1.0, 3.0, 10.0])
def test_errors_cover_under_a_random_walk(size):
    """White noise plus a walk from zero 1, 3 and 10 times the noise end to end, 150 seeds: the
    residual's noise model is chosen between an AR(p) and white plus a walk by their restricted
    likelihoods, so an AR(8) that follows part of a large walk no longer hides it. With the AR
    alone and a drift check the truth was within 1.96 SE 77-81 %, 35-42 % and 65-83 % of the time.
    Told where the force was at rest (the approach), the walk is still found there, and still covered."""
    J = linear_design()
    noise = walk_noise(np.random.default_rng(2), N_LINEAR, 150, size)
    at_rest = _approach(J)
    for covariance in (hac_covariance, lambda J, r, lengths: hac_covariance(J, r, lengths, quiet=[at_rest])):
        cover = linear_coverage(noise, J, covariance)
        assert np.all((cover > 0.88) & (cover < 0.99)), cover


def _approach(J: np.ndarray) -> int:
    return int(np.argmax(J[:, 2] > 0))  # samples before the contact term starts


@pytest.mark.parametrize("misfit", [1.5, 3.0, 10.0])
def test_a_misfit_gets_the_errors_of_the_noise_at_rest(misfit):
    """The same misfits, 20 seeds: read as a correlated noise, the misfit multiplied the standard
    errors (up to 100x on real AFM curves). The approach at rest shows white noise, so the errors
    are that noise's, as if the model were right (within 25 % of the white-noise formula on the
    noise alone), and the note says the misfit is not in them."""
    J = linear_design()
    x = np.linspace(0.0, 1.0, N_LINEAR)
    shape = misfit * np.where(x > 0.4, np.sin(3 * np.pi * (x - 0.4) / 0.6), 0.0)
    rng = np.random.default_rng(6)
    for _ in range(20):
        e = rng.normal(size=N_LINEAR)
        y = e + shape
        r = y - J @ np.linalg.lstsq(J, y, rcond=None)[0]
        notes: list[str] = []
        se = np.sqrt(np.diag(hac_covariance(J, r, [N_LINEAR], notes, [_approach(J)])))
        noise_only = np.sqrt(np.diag(white_covariance(J, e - J @ np.linalg.lstsq(J, e, rcond=None)[0])))
        assert np.all(np.abs(se / noise_only - 1) < 0.25), se / noise_only
        assert any("a misfit, not noise" in n for n in notes), notes


@pytest.mark.parametrize("misfit", [1.5, 3.0, 10.0])
def test_a_misfit_in_contact_is_not_read_as_a_walk(misfit):
    """A smooth misfit in contact (a model that misses something) under white noise, 20 seeds:
    over the whole record it reads as a random walk from the start, which the standard errors
    then include (on real AFM curves that inflated them 10-50x). The approach, where the force
    is known to be at rest, shows no such walk: told where it is, the walk is not included. Not
    told, the residual's own spectrum rules it out: a walk's power falls as 1/f^2 past its lowest
    components, a smooth misfit's does not (`_shape_refutes`; before it, every seed not told was
    read as a walk)."""
    J = linear_design()
    x = np.linspace(0.0, 1.0, N_LINEAR)
    shape = misfit * np.where(x > 0.4, np.sin(3 * np.pi * (x - 0.4) / 0.6), 0.0)
    rng = np.random.default_rng(5)
    walks = {"told": 0, "not told": 0}
    for _ in range(20):
        y = rng.normal(size=N_LINEAR) + shape
        r = y - J @ np.linalg.lstsq(J, y, rcond=None)[0]
        for key, quiet in (("told", [_approach(J)]), ("not told", None)):
            notes: list[str] = []
            hac_covariance(J, r, [N_LINEAR], notes, quiet)
            walks[key] += any("random-walk drift" in n for n in notes)
    assert walks == {"told": 0, "not told": 0}, walks


def test_doubtful_errors_say_why():
    """Three independent stretches for three parameters: the note says so; a white residual
    gets none, and the call without `notes` still returns the covariance."""
    J = linear_design()
    rng = np.random.default_rng(3)
    cases = ((ar1_noise(rng, N_LINEAR, 1, 0.998)[:, 0], True), (rng.normal(size=N_LINEAR), False))
    for noise, doubtful in cases:
        resid = noise - J @ np.linalg.lstsq(J, noise, rcond=None)[0]
        notes: list[str] = []
        cov = hac_covariance(J, resid, [N_LINEAR], notes)
        assert np.array_equal(cov, hac_covariance(J, resid, [N_LINEAR]))
        assert any("for 3 parameters (fewer than" in x for x in notes) == doubtful, notes
        if not doubtful:
            assert notes == []


def test_fit_errors_match_the_spread_over_seeds(tmp_path):
    """A trial of the simulated rig with noise correlated over several samples (a filtering
    indicator's, AR(1) with rho 0.8): the standard errors `fit` reports match how far the
    parameters scatter between forty noise draws. (The noise is added to the prepared trial, so
    its zero is exact; on a raw record the tare's error is counted apart:
    test_a_tares_error_counts_in_the_standard_errors.)"""
    cfg = RigConfig()
    cfg.sim.loadcell.noise_N = 0.0
    proto = ("name: ramp\nsteps:\n  - ramp: {to_mm: 30, speed_mm_s: 3}\n  - hold: {duration_s: 20}\n"
             "  - return: {to_mm: 0, speed_mm_s: 5}\n")
    clean = load_trial(run_sim(proto, cfg, tmp_path).log_path)
    rng = np.random.default_rng(11)
    values, errs = [], []
    for _ in range(40):
        noise = 0.2 * lfilter([np.sqrt(1 - 0.8 ** 2)], [1, -0.8], rng.normal(size=clean.n + 200))[200:]
        # the noise comes after the tare: this record's zero is exact (no tare to count)
        res = fit(build_model("proposed"), [dataclasses.replace(clean, force_N=clean.force_N + noise,
                                                                baseline_n=0)])
        assert res.white_L > 5.0  # the residual is the correlated noise
        values.append([res.values[k] for k in res.model.param_names])
        errs.append([res.stderr[k] for k in res.model.param_names])
    spread = np.std(values, axis=0, ddof=1)
    reported = np.sqrt(np.mean(np.square(errs), axis=0))
    ratio = spread / reported
    # forty draws know a spread to about +/- 11 %; the white formula's ratio would be about 3
    assert np.all((ratio > 0.65) & (ratio < 1.45)), dict(zip(res.model.param_names, ratio, strict=True))
    assert res.correlations(), "the cubic's terms trade off: their correlation is reported"
    text = res.report()
    assert "correlations (|C| >= 0.1, largest first)" in text
    a, b, c = res.correlations()[0]
    assert f"C({a}, {b}) = {c:+.3f}" in text
    assert abs(c) == max(abs(x[2]) for x in res.correlations())
    out = json.loads(json.dumps(result_json(res, ["x"])))
    corr = out["correlations"]
    assert corr[a][b] == pytest.approx(c) and corr[b][a] == pytest.approx(c) and corr[a][a] == 1.0


def test_one_bic_everywhere(tmp_path):
    """FitResult, the JSON and --explain's dBIC use the effective-sample BIC; no plain BIC is left.
    A fit's BIC counts the records (their samples over the noise's correlation time: the same for
    every model on them); --explain compares a model with its candidates at the base model's
    residual count, record by record."""
    cfg = RigConfig()
    cfg.sim.effects.drift = DriftParams(rate_N_per_s=0.004)
    proto = ("name: ramp\nsteps:\n  - ramp: {to_mm: 30, speed_mm_s: 3}\n  - hold: {duration_s: 30}\n"
             "  - return: {to_mm: 0, speed_mm_s: 5}\n")
    trial = load_trial(run_sim(proto, cfg, tmp_path).log_path)
    base = fit(build_model("proposed"), [trial])
    r = np.concatenate(base.residuals)
    n, k = len(r), len(base.model.params)
    assert base.white_L > 10  # a missed drift: a smooth, correlated residual
    assert base.n_eff == pytest.approx(n / base.white_L)
    rss = float(r @ r)
    counted = n / base.noise_L
    assert base.bic_samples == pytest.approx(counted)
    assert base.bic == pytest.approx(counted * np.log(rss / n) + k * np.log(counted))
    out = result_json(base, ["x"])["fit"]
    assert out["bic"] == base.bic and out["effective_samples"] == base.bic_samples
    assert out["residual_effective_samples"] == base.n_eff
    ex = explain(base, {k: CATALOGUE[k] for k in ("drift", "offset", "friction")})
    top = ex.ranked[0]
    assert top.effect == "drift" and ex.n_eff == base.n_eff
    ratio = (top.rmse_N / base.overall.rmse_N) ** 2
    assert top.delta_bic == pytest.approx(delta_bic(ratio, len(top.fit.model.params) - k, base.n_eff))
    # the same definition: the difference of the two models' BIC at the simpler one's N_eff
    assert top.delta_bic == pytest.approx(bic(rss * ratio, n, len(top.fit.model.params), base.n_eff)
                                          - bic(rss, n, k, base.n_eff))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_tares_error_counts_in_the_standard_errors(seed):
    """Each record tared on the mean of 50 samples at rest carries that mean's error as a constant
    under every sample, which its residual cannot show: `zeros` puts it in the sandwich. Over 300
    draws of three ramps sharing one slope, the slope's 1.96-SE interval covers the truth about
    95 % of the time with it, and far less without."""
    from rig.analysis.stats.uncertainty import hac_covariance

    rng = np.random.default_rng(seed)
    m, sigma, n_tare = 400, 1.0, 50
    x = np.concatenate([np.linspace(0.0, 1.0, m)] * 3)
    J = x[:, None]
    covered = {True: 0, False: 0}
    draws = 300
    for _ in range(draws):
        zero = rng.normal(0.0, sigma / np.sqrt(n_tare), 3)
        y = 2.0 * x + np.repeat(zero, m) + rng.normal(0.0, sigma, 3 * m)
        b = float(x @ y / (x @ x))
        r = y - b * x
        for with_zero in (True, False):
            zeros = [sigma ** 2 / n_tare] * 3 if with_zero else None
            se = float(np.sqrt(hac_covariance(J, r, [m] * 3, zeros=zeros)[0, 0]))
            covered[with_zero] += abs(b - 2.0) <= 1.96 * se
    assert 0.92 <= covered[True] / draws <= 0.98, covered
    assert covered[False] / draws < 0.8, covered
