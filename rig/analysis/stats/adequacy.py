"""Is a model's residual the noise? Three tests, each against what a perfect model would show on
this very record.

A model is adequate when its residual is no larger than the noise overall (ADEQUATE_RMSE) and
in every phase (ADEQUATE_PHASE), and no more correlated in time than the noise
(ADEQUATE_WHITE, on the integral time scales): tolerances a user reads as "within 1.2x the
noise". What a perfect model's residual shows is not a constant, though: the noise is itself
an estimate (from a few hundred samples of approach, or from the residual), a short phase's RMSE
scatters, a force quantised on a coarse lattice leaves a residual that follows the record's
own course (flat where the force holds still, uniform where it moves), and a filtered sensor's
residual correlation scatters widely. So each limit is the tolerance times the upper tail of
that statistic under a perfect model, found by simulation: the measured noise spectrum drawn
DRAWS times, quantised on the record's own lattice about the fitted prediction, the noise
re-estimated from a simulated approach exactly as the record's was, and each statistic taken
as the analysis takes it. A long record with a long quiet approach gets limits at the
tolerances; a short approach or a coarse quantiser widens them by as much as it must.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from rig.analysis.stats.draws import Draws
from rig.analysis.stats.line import off_line
from rig.analysis.stats.noise import (
    AT_REST,
    MAX_ORDER,
    Noise,
    ar_fit_rows,
    autocovariance,
    from_residual,
    gauss_behind_levels,
    integral_scale_ar,
    integral_scales,
    response,
    whiten,
)

ADEQUATE_RMSE = 1.2
ADEQUATE_PHASE = 1.5
ADEQUATE_WHITE = 1.5  # residual correlation time over the noise's own
DRAWS = 24
Z = 2.0  # how far into the simulated tail a perfect model may go (one-sided, about 2 %)
MAX_SIM_BASELINE = 20000
# standard errors of the noise's slowest root allowed above its estimate: the rest cut by
# `quiet_length` from an AR(1) at 0.95-0.995 (300 records each) holds the true root under the
# estimate plus 2, 2.5 and 3 of them in 80-94 %, 93-97 % and 97-99 % of records
SLOW_SE = 3.0


@dataclass(frozen=True)
class Limits:
    """How far a right model's residual may go on this record, in units of the noise: its RMSE overall and
    per phase, and its correlation time with the noise's own taken out."""

    rmse: float  # RMSE over the noise, at most
    phase: dict[str, float]  # a phase's RMSE over the noise, at most
    white: float  # the residual's correlation time, the noise's own taken out (samples), at most


def simulate(noise: Noise, n: int, draws: int, rng: Draws | np.random.Generator) -> np.ndarray:
    """`draws` series of `n` samples of the noise before quantisation (its AR spectrum, by spectral
    synthesis on a period long enough that the wrap does not matter), with the walk the rest
    showed (`Noise.walk_N2`), if any."""
    span = int(min(max(4 * noise.scale_samples, 64), 1 << 16))
    m = 1 << int(np.ceil(np.log2(n + span)))
    key = (rng.position, draws, m, tuple(noise.ar)) if isinstance(rng, Draws) else None
    spectrum = _white_spectrum(rng, draws, m)
    got = _SERIES.get(key) if key else None
    if got is None:
        gain = response(noise.ar, m // 2 + 1) if noise.ar else np.ones(m // 2 + 1)
        power = (gain[0] ** 2 + gain[-1] ** 2 + 2.0 * np.sum(gain[1:-1] ** 2)) / m
        got = (np.fft.irfft(spectrum * gain, m, axis=1), math.sqrt(power))
        if key:
            # the same draws through the same spectrum give the same series: every curve of a map
            # whose noise has the same AR filter (white, most often) shares them
            got[0].flags.writeable = False
            if len(_SERIES) >= _SPECTRA_KEPT:
                _SERIES.pop(next(iter(_SERIES)))
            _SERIES[key] = got
    x, root = got
    x = x[:, :n] * (noise.gauss_std_N / root)
    if noise.walk_N2 > 0.0:
        # the walk the rest showed, from the record's start (its own draws: the same for the same
        # record, apart from the stream the spectrum's come from)
        steps = np.random.default_rng(n).standard_normal((draws, n))
        x = x + np.cumsum(steps, axis=1) * math.sqrt(noise.walk_N2)
    return x


_SPECTRA: dict[tuple[int, int, int], np.ndarray] = {}
_SERIES: dict[tuple, tuple[np.ndarray, float]] = {}
_SPECTRA_KEPT = 8


def _white_spectrum(rng: Draws | np.random.Generator, draws: int, m: int) -> np.ndarray:
    """The transform of `draws` rows of `m` standard normal draws from `rng`. A Draws stream
    gives the same draws from the same place, so every curve of a batch (each simulated from
    the stream's start) shares them: they are drawn and transformed once, and the stream is
    moved on past them as drawing them would."""
    if not isinstance(rng, Draws):
        return np.fft.rfft(rng.standard_normal((draws, m)), axis=1)
    key = (rng.position, draws, m)
    got = _SPECTRA.get(key)
    if got is None:
        got = np.fft.rfft(rng.standard_normal((draws, m)), axis=1)
        got.flags.writeable = False
        if len(_SPECTRA) >= _SPECTRA_KEPT:
            _SPECTRA.pop(next(iter(_SPECTRA)))
        _SPECTRA[key] = got
    else:
        rng.skip(draws * m)
    return got


def quantise(x: np.ndarray, noise: Noise) -> np.ndarray:
    """`x` on the sensor's grid of readings (its quantum from the noise model), as the instrument would have
    recorded it; unchanged where there is no quantum."""
    q = noise.quantum_N
    return x if q <= 0 else noise.origin_N + q * np.round((x - noise.origin_N) / q)


def limits(noise: Noise, predictions: list[np.ndarray], phases: list[np.ndarray],
           names: tuple[str, ...], seed: int = 0) -> Limits:
    """The three limits for residuals of a fit whose `predictions` (one per record, with the
    records' `phases`, per sample) carry `noise`, by simulating perfect models."""
    if noise.std_N <= 0.0:
        return Limits(ADEQUATE_RMSE, dict.fromkeys(names, ADEQUATE_PHASE), ADEQUATE_WHITE)
    noise = slowest_allowed(noise)
    rng = Draws(seed)
    sims = []
    for p in predictions:
        x = simulate(noise, len(p), DRAWS, rng)
        sims.append(quantise(p + x, noise) - p if noise.quantum_N else x)
    stds, spectra = _reestimated(noise, sims, rng)
    all_r = np.concatenate(sims, axis=1)
    rmse = np.sqrt(np.mean(all_r ** 2, axis=1)) / stds
    phase = {}
    for ph in names:
        r = np.concatenate([s[:, m == ph] for s, m in zip(sims, phases, strict=True)], axis=1)
        if r.shape[1]:
            phase[ph] = _upper(np.sqrt(np.mean(r ** 2, axis=1)) / stds) * ADEQUATE_PHASE
    white = np.mean([_whitened_scales(s, spectra) for s in sims], axis=0)
    return Limits(_upper(rmse) * ADEQUATE_RMSE, phase, _upper(white) * ADEQUATE_WHITE)


def slowest_allowed(noise: Noise) -> Noise:
    """The noise as slow as its rest cannot rule out: the AR spectrum's slowest (real, positive)
    root r moved up by its small-sample bias (2 + 4 r) / n for a line taken out of n samples and
    by SLOW_SE of its standard errors sqrt((1 - r^2) / n). A rest a few correlation times long
    reads a slow noise as faster and quieter than it is (an AR(1) at 0.99 over 350 samples at
    0.97 in the median, and the line takes up much of its variance), and the rest is where the
    force happened to stay on a line, which selects the quiet stretches of a slow noise: a
    perfect model's residual in contact then looks twice the noise. The limits are the upper
    tail under the slowest noise the record allows, which leaves them where they were when the
    rest is long against the noise's correlation time."""
    n = noise.samples
    if noise.source != AT_REST or not n or not noise.ar:
        return noise
    roots = np.roots(np.concatenate([[1.0], -np.asarray(noise.ar, dtype=float)]))
    k = int(np.argmax(np.abs(roots)))
    r = roots[k]
    if abs(r.imag) > 1e-9 or r.real <= 0.0:
        return noise
    r = float(r.real)
    up = min(r + SLOW_SE * math.sqrt(max(1.0 - r * r, 0.0) / n) + (2.0 + 4.0 * r) / n, 1.0 - 0.5 / n)
    if up <= r:
        return noise
    roots[k] = up
    ar = tuple(float(c) for c in -np.real(np.poly(roots))[1:])
    return replace(noise, ar=ar, scale_samples=integral_scale_ar(ar))


def _whitened_scales(sims: np.ndarray, spectra: list[np.ndarray]) -> np.ndarray:
    """Each draw whitened by its own re-estimated spectrum, all measured in one transform (the
    first samples, which a longer filter has no history for, dropped alike from every draw)."""
    p = max((len(ar) for ar in spectra), default=0)
    n = sims.shape[1]
    # every draw through its own filter at once: a shorter filter's missing terms are zeros,
    # whose products take nothing from the sum (the same numbers as one draw at a time)
    coef = np.zeros((len(spectra), p))
    for k, ar in enumerate(spectra):
        coef[k, :len(ar)] = ar
    out = sims[:, p:].copy()
    for k in range(1, p + 1):
        out -= coef[:, k - 1:k] * sims[:, p - k:n - k]
    return integral_scales(out)


def whitened_scale(residuals: list[np.ndarray], noise: Noise) -> float:
    """The residual's correlation time once the noise's own is taken out (its AR filter): about
    one sample for a perfect model whatever the sensor's filter, many for a shape it misses."""
    return float(np.mean([integral_scales(whiten(r[None, :], noise.ar))[0] for r in residuals]))


def _upper(stat: np.ndarray) -> float:
    """The statistic's upper tail under a perfect model: Z standard deviations above its mean,
    on a log scale (ratios), and never below 1."""
    logs = np.log(np.maximum(stat, 1e-300))
    return float(max(math.exp(logs.mean() + Z * logs.std(ddof=1)), 1.0))


def _reestimated(noise: Noise, sims: list[np.ndarray], rng) -> tuple[np.ndarray, list[np.ndarray]]:
    """The noise's level and spectrum as the record's own estimate would have found them in each
    draw: from a simulated quiet approach of the same length, or from the residual."""
    draws = sims[0].shape[0]
    if noise.samples and noise.source == AT_REST:
        nb = min(noise.samples, MAX_SIM_BASELINE)
        base = quantise(noise.level_N + simulate(noise, nb, draws, rng), noise)
        # every draw less its straight line at once, then each one's spectrum
        detr = off_line(np.linspace(-1.0, 1.0, nb), base)
        gamma = autocovariance(detr, min(MAX_ORDER, nb // 4))
        spectra = ar_fit_rows(gamma, nb)
        stds = np.sqrt(np.maximum(gamma[:, 0], 0.0))
        if noise.quantum_N:
            q = noise.quantum_N
            stds = np.array([math.sqrt(gauss_behind_levels(b, q)[0] ** 2 + q ** 2 / 12.0) for b in base])
        return np.maximum(stds, 1e-300), spectra
    est = [from_residual([s[k] for s in sims]) for k in range(draws)]
    return np.array([max(e.std_N, 1e-300) for e in est]), [np.array(e.ar) for e in est]
