"""Power-law (fractional) relaxation evaluated fast: the fractional Maxwell element (a spring k
in series with a springpot) as a fixed sum of exponentials on log-spaced time constants.

Its relaxation modulus k E_a(-(t/tau)^a) (E_a the Mittag-Leffler function) is completely
monotone: a mixture of exponentials exp(-r t / tau) whose weight over r has a closed-form
distribution function, so each of a few modes per decade carries the exact weight of its cell
of rates, placed at the cell's median rate (the inverse of that function, also closed-form).
A mode is a Maxwell element, i.e. a first-order lag of the indentation rate, so the branch is
a handful of linear filters: no ODE solver and no history sum.
"""

from __future__ import annotations

import numpy as np

from rig.models.core import first_order_lag

MODES_PER_DECADE = 4


def mittag_leffler_cdf(r: np.ndarray, alpha: float) -> np.ndarray:
    """Weight of the rates below r (in units of 1/tau) in E_a(-(t/tau)^a); 0 at r = 0, 1 at infinity."""
    s, c = np.sin(np.pi * alpha), np.cos(np.pi * alpha)
    return (np.arctan((np.power(r, alpha) + c) / s) - np.arctan2(c, s)) / (np.pi * alpha)


def _median_rate(cdf: np.ndarray, alpha: float) -> np.ndarray:
    """The rate r (units of 1/tau) below which a fraction `cdf` of the weight lies."""
    s, c = np.sin(np.pi * alpha), np.cos(np.pi * alpha)
    u = s * np.tan(np.pi * alpha * cdf + np.arctan2(c, s)) - c
    return np.power(np.maximum(u, 1e-300), 1.0 / alpha)


def modes(duration_s: float, dt_s: float, tau_s: float, alpha: float,
          per_decade: int = MODES_PER_DECADE) -> tuple[np.ndarray, np.ndarray]:
    """Rates (1/s) and weights (summing to 1) of the modes that stand for E_a(-(t/tau)^a) over a
    record: rates from a tenth of the record's inverse length (slower ones act as springs over it)
    to a few per sample (faster ones relax within a sample); the tails go to the end modes."""
    lo, hi = np.log10(0.1 / max(duration_s, dt_s)), np.log10(3.0 / dt_s)
    n = max(2, int(np.ceil((hi - lo) * per_decade)))
    edges = np.logspace(lo, hi, n + 1)
    cdf = mittag_leffler_cdf(edges * tau_s, alpha)
    cdf[0], cdf[-1] = 0.0, 1.0
    # each mode at its cell's median rate; the end cells reach to 0 and to infinity
    lo_edge, hi_edge = edges[:-1].copy(), edges[1:].copy()
    lo_edge[0], hi_edge[-1] = 0.0, np.inf
    rates = np.clip(_median_rate(0.5 * (cdf[:-1] + cdf[1:]), alpha) / tau_s, lo_edge, hi_edge)
    rates = np.maximum(rates, 1e-6 * edges[0])  # a mode slower than that is a spring over the record
    return rates, np.diff(cdf)


def fractional_maxwell(v_m_s: np.ndarray, dt_s: float, k_N_per_m: float, tau_s: float,
                       alpha: float) -> np.ndarray:
    """Force (N) of the branch driven by the indentation rate: sum over modes of
    f_i + df_i/dt / rate_i = k w_i / rate_i dx/dt."""
    rates, weights = modes(len(v_m_s) * dt_s, dt_s, tau_s, alpha)
    f = np.zeros(len(v_m_s))
    for rate, w in zip(rates, weights, strict=True):
        if w > 1e-12:
            f += first_order_lag((k_N_per_m * w / rate) * v_m_s, dt_s, 1.0 / rate)
    return f
