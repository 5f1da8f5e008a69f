"""Uncertainty of fitted parameters when the residual is correlated in time, and the one BIC.

At 100 Hz neighbouring residuals are not independent: the sensor's filter correlates its
noise, and a model that misses something leaves a smooth misfit. The textbook covariance
s^2 (J^T J)^-1 then counts every sample as new information and its standard errors come
out about sqrt(L) too small (L: the residual's integral time scale in samples).

The covariance here is the HAC sandwich B^-1 Omega B^-1, B = J^T J, Omega the long-run
covariance of the score g_t = J_t r_t within each trial (trials are independent), estimated
the Newey-West way (Bartlett weights 1 - |lag|/M over lags below M) after AR(1)
prewhitening (Andrews and Monahan 1992): the score is filtered with the residual's lag-one
correlation rho, e_t = g_t - rho g_(t-1), the Bartlett sum taken over e with a bandwidth
from e's own correlation time (M = BANDWIDTH_PER_L x its integral time scale), and the
result recoloured by 1 / (1 - rho)^2.

Why this one: a block bootstrap would refit the model a hundred times per fit; the plain
Newey-West sum needs a bandwidth many times the correlation time to lose its downward bias,
and the fit's own residual (which sums to zero against J) biases it further, so at the
correlation times of a filtered sensor it covered a 95 % interval only 80-92 % of the time.
Prewhitening leaves little correlation for the Bartlett sum to truncate and brings the
coverage to nominal (tests/test_uncertainty.py measures it over many seeds).

BIC is defined once, on the effective number of independent residuals (see `bic`).
"""

from __future__ import annotations

import math

import numpy as np

from rig.analysis.noise import integral_scale

BANDWIDTH_PER_L = 2.0
MAX_RHO = 0.99  # prewhitening filter's coefficient at most: recolouring by 1/(1-rho)^2 stays bounded
MAX_BANDWIDTH_FRACTION = 0.25  # of a trial's samples: beyond that the lags are too few to average

__all__ = ["bandwidth", "bic", "correlation", "delta_bic", "effective_samples", "hac_covariance",
           "notable_correlations", "white_covariance"]


def bandwidth(L: float, n: int) -> int:
    """Lags (samples) the sandwich sums over, from the residual's integral time scale `L`."""
    return int(max(1, min(math.ceil(BANDWIDTH_PER_L * max(L, 1.0)), MAX_BANDWIDTH_FRACTION * n)))


def _bartlett_meat(g: np.ndarray, M: int) -> np.ndarray:
    """sum over |l| < M of (1 - |l|/M) sum_t g_t g_{t+l}^T, exactly: every window of M
    consecutive samples (the partial ones at either end included) contains a pair l apart
    M - |l| times, so the sum of the windows' outer products is M times the Bartlett sum."""
    if M <= 1:
        return g.T @ g
    padded = np.vstack([np.zeros((M, g.shape[1])), g, np.zeros((M - 1, g.shape[1]))])
    c = np.cumsum(padded, axis=0)
    windows = c[M:] - c[:-M]  # sums of g over [t - M + 1, t] for every t touching the data
    return windows.T @ windows / M


def hac_covariance(J: np.ndarray, r: np.ndarray, lengths: list[int]) -> np.ndarray:
    """Covariance of least-squares parameters (in the units of J's columns) from the
    Jacobian `J` and the residual `r` of trials of `lengths` samples stacked in that order."""
    n, p = J.shape
    g = J * r[:, None]
    meat = np.zeros((p, p))
    start = 0
    for m in lengths:
        gk, rk = g[start:start + m], r[start:start + m]
        start += m
        if m < 3 or not np.any(rk):
            meat += gk.T @ gk
            continue
        rho = float(np.clip(rk[1:] @ rk[:-1] / (rk @ rk), 0.0, MAX_RHO))
        e = gk[1:] - rho * gk[:-1]
        M = bandwidth(integral_scale(rk[1:] - rho * rk[:-1]), m)
        meat += _bartlett_meat(e, M) / (1.0 - rho) ** 2
    # the residual is smaller than the noise by the p directions the fit took out of it
    meat *= n / max(n - p, 1)
    bread = np.linalg.pinv(J.T @ J)
    cov = bread @ meat @ bread
    return _undetermined(0.5 * (cov + cov.T), J)


def white_covariance(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The textbook s^2 (J^T J)^-1: right only for an uncorrelated residual."""
    n, p = J.shape
    return _undetermined(np.linalg.pinv(J.T @ J) * float(r @ r) / max(n - p, 1), J)


def _undetermined(cov: np.ndarray, J: np.ndarray) -> np.ndarray:
    """`cov` with an infinite variance for every parameter the residual does not depend on.

    The pseudo-inverse gives such a parameter (a zero column of J) a variance of zero, which
    reads as exact where the truth is the opposite: the data say nothing about it.
    """
    norms = np.linalg.norm(J, axis=0)
    dead = ~(norms > np.finfo(float).eps * max(float(np.max(norms, initial=0.0)), np.finfo(float).tiny))
    if np.any(dead):
        cov = cov.copy()
        cov[dead, :] = np.nan
        cov[:, dead] = np.nan
        cov[dead, dead] = np.inf
    return cov


def correlation(cov: np.ndarray) -> np.ndarray:
    """Correlation matrix of a covariance; NaN where a variance is zero or not finite."""
    d = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        c = cov / np.outer(d, d)
    c[~np.isfinite(c)] = np.nan
    np.fill_diagonal(c, np.where(d > 0, 1.0, np.nan))
    return np.clip(c, -1.0, 1.0)


def notable_correlations(names: list[str], corr: np.ndarray,
                         floor: float = 0.1) -> list[tuple[str, str, float]]:
    """Pairs whose |correlation| is at least `floor`, largest first (lmfit's report)."""
    pairs = [(names[i], names[j], float(corr[i, j]))
             for i in range(len(names)) for j in range(i + 1, len(names))
             if np.isfinite(corr[i, j]) and abs(corr[i, j]) >= floor]
    return sorted(pairs, key=lambda x: -abs(x[2]))


def effective_samples(n: int, L: float) -> float:
    """Independent residuals among `n` samples correlated over `L` samples (at least 10)."""
    return max(n / max(L, 1.0), 10.0)


def bic(rss: float, n: int, k: int, n_eff: float) -> float:
    """BIC on the effective number of independent residuals, N_eff = N / L:

        BIC = N_eff ln(RSS / N) + k ln(N_eff)

    A white residual keeps N_eff = N (the textbook BIC); a correlated one counts each
    independent stretch once instead of every sample. Two models are compared at the same
    N_eff (the simpler model's), so their difference is N_eff ln(RSS_1 / RSS_0) + dk ln(N_eff)."""
    return float(n_eff * math.log(max(rss / max(n, 1), 1e-300)) + k * math.log(max(n_eff, 1.0)))


def delta_bic(rss_ratio: float, dk: int, n_eff: float) -> float:
    """`bic` of a model with `dk` more parameters and `rss_ratio` times the RSS, minus the
    simpler model's, both at the simpler model's N_eff."""
    return bic(rss_ratio, 1, dk, n_eff) - bic(1.0, 1, 0, n_eff)
