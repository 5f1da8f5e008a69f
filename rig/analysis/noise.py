"""The sensor's noise as the instrument delivers it: its level and its correlation time.

Indicators filter their signal, so their noise is not white at the sample rate: a perfect
model leaves a residual as correlated as the noise itself. The noise is measured where the
record shows it alone:

- the force at rest before contact (detrended), when the record has enough of it;
- otherwise the residual's short-lag structure: differences at lags 1 and 2 keep the noise
  and barely see a smooth misfit. For noise that is a first-order low-pass of white noise
  (an AR(1) process with coefficient rho), D1 = 2 s^2 (1 - rho), D2 = 2 s^2 (1 - rho^2),
  so rho = D2/D1 - 1 and s^2 = D1 / (2 (1 - rho)).

Either way the result is a level (std) and an integral time scale in samples (1 for white
noise, (1 + rho)/(1 - rho) for AR(1)): a model is adequate when its residual is as large and
as correlated as that noise, no more.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_BASELINE = 200
MAX_RHO = 0.98


@dataclass(frozen=True)
class Noise:
    std_N: float
    scale_samples: float  # integral time scale: samples per independent value
    source: str


def integral_scale(r: np.ndarray, max_lag: int = 3000) -> float:
    """Samples per independent value: 1 + 2 * the sum of the autocorrelation up to its first
    drop below 0.05."""
    r = r - r.mean()
    n = len(r)
    if n < 10 or not np.any(r):
        return 1.0
    lag = min(max_lag, n // 4)
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(r, nfft)
    acf = np.fft.irfft(f * np.conj(f), nfft)[: lag + 1]
    acf = acf / acf[0]
    below = np.flatnonzero(acf < 0.05)
    cut = below[0] if len(below) else lag
    return float(np.clip(1.0 + 2.0 * acf[1:cut].sum(), 1.0, n / 20.0))


def from_baseline(baselines: list[np.ndarray]) -> Noise | None:
    use = [b for b in baselines if b is not None and len(b) >= MIN_BASELINE]
    if not use:
        return None
    std = float(np.sqrt(np.mean([np.var(b) for b in use])))
    scale = float(np.mean([integral_scale(b) for b in use]))
    return Noise(std, scale, "force at rest before contact")


def from_residual(residuals: list[np.ndarray]) -> Noise:
    d1 = float(np.mean(np.concatenate([np.diff(r) ** 2 for r in residuals])))
    d2 = float(np.mean(np.concatenate([(r[2:] - r[:-2]) ** 2 for r in residuals if len(r) > 2])))
    if d1 <= 0.0:
        return Noise(0.0, 1.0, "residual short-lag differences")
    rho = float(np.clip(d2 / d1 - 1.0, 0.0, MAX_RHO))
    std = float(np.sqrt(d1 / (2.0 * (1.0 - rho))))
    return Noise(std, (1.0 + rho) / (1.0 - rho), "residual short-lag differences")
