"""Power-law (fractional) relaxation evaluated fast: the fractional Maxwell element (a spring k
in series with a springpot) as a fixed sum of exponentials on log-spaced time constants.

Its relaxation modulus k E_a(-(t/tau)^a) (E_a the Mittag-Leffler function) is completely
monotone: a mixture of exponentials exp(-r t / tau) whose weight over the log-rate y = ln r has
the closed-form density g(y) = sin(pi a) / (2 pi (cosh(a y) + cos(pi a))). A mode is a Maxwell
element, i.e. a first-order lag of the indentation rate, so the branch is a linear filter: no
ODE solver and no history sum.

The mixture must be summed exactly to the noise: a fit of a record made by this very branch
has to return its parameters, and AFM noise is ~0.05 % of the peak force. Hence:

- Cells of a sixth of a decade of rate each carry two modes, the two-point Gauss rule of the
  cell under g: together they keep the cell's mass and its first three moments of log-rate, so
  the error of the sum is fourth order in the cell width (<4e-6 of the peak up to alpha 0.8,
  1.2e-5 at 0.95, against an exact convolution: tests/test_fractional_exact.py). One mode per cell
  keeps only two moments, and its error, second order, is ~0.05-0.1 % even at 12 cells per
  decade; a midpoint rule in y would converge faster for a moderate alpha but fails as alpha
  nears 1, where g narrows to a peak thinner than a cell (at alpha 0.95, 0.7 % of the peak).
- The cells span 0.01/duration to 100/dt and always the decade either side of 1/tau, where g
  peaks: beyond that g is a smooth power-law tail, and each tail is one more mode whose weight
  is the tail's mass (closed form) and whose rate keeps the moment that governs it. Slower
  than the record, a mode is nearly a spring, exp(-r t) ~ 1 - r t: it keeps the tail's mean
  rate, and what it misses, var(r) t^2 / 2, is ~1e-6 of the peak from 0.01/duration (1e-4
  from 0.1/duration: at alpha 0.1 half the weight is slower than that). Faster than a sample,
  a mode relaxes within the sample, and what remains of it is the viscous force k w v / r of a
  ramp: it keeps the tail's mean relaxation time E[1/r].
- The lags are discretised exactly for a rate linear between samples (as `first_order_lag`),
  including modes much faster than a sample, whose response to a ramp is k w v / r. All the
  modes share the input, so their impulse responses are summed into one kernel and applied by
  one FFT convolution: the cost barely grows with the number of modes.
"""

from __future__ import annotations

import functools

import numpy as np

CELLS_PER_DECADE = 6
MODES_PER_DECADE = 2 * CELLS_PER_DECADE  # a two-point Gauss rule per cell
SLOW_EDGE_PER_DURATION = 0.01  # slowest cell edge, in units of 1/duration
FAST_EDGE_PER_DT = 100.0  # fastest cell edge, in units of 1/dt
PEAK_HALF_WIDTH = np.log(10.0)  # log-rate either side of 1/tau always covered by cells

_SINGLE_THREAD_GEMM = 1 << 19  # multiply-adds per matrix product (see modes_kernel)


@functools.cache
def _rules() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Legendre (10 points: each cell's moments under g) and Gauss-Laguerre (24: the tails'
    moments, to ~1e-14) nodes and weights; made on first use (numpy.polynomial costs an import a
    fit without the branch need not pay)."""
    return (*np.polynomial.legendre.leggauss(10), *np.polynomial.laguerre.laggauss(24))


def mittag_leffler_cdf(r: np.ndarray, alpha: float) -> np.ndarray:
    """Weight of the rates below r (in units of 1/tau) in E_a(-(t/tau)^a); 0 at r = 0, 1 at infinity."""
    s, c = np.sin(np.pi * alpha), np.cos(np.pi * alpha)
    return (np.arctan((np.power(r, alpha) + c) / s) - np.arctan2(c, s)) / (np.pi * alpha)


def log_rate_density(y: np.ndarray, alpha: float) -> np.ndarray:
    """Weight per unit of y = ln(r tau) in E_a(-(t/tau)^a); written with cosh, which overflows
    only to a zero weight far in the tails."""
    with np.errstate(over="ignore"):
        return np.sin(np.pi * alpha) / (2.0 * np.pi * (np.cosh(alpha * y) + np.cos(np.pi * alpha)))


def _cell_gauss_rules(edges: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Log-rates and weights of the two-point Gauss rule of each cell under g, the cell's mass
    exact (closed form) and its moments from a 10-point Gauss-Legendre rule: g is analytic
    within pi (1 - a) / a of the real axis, so even at alpha 0.95 that rule holds ~1e-8."""
    lo, hi = edges[:-1], edges[1:]
    half = 0.5 * (hi - lo)
    gl_x, gl_w, _, _ = _rules()
    xi = gl_x[None, :]  # the cell mapped to [-1, 1]
    p = gl_w[None, :] * log_rate_density((lo + half)[:, None] + half[:, None] * xi, alpha)
    mass = np.diff(mittag_leffler_cdf(np.exp(edges), alpha))
    m0 = np.sum(p, axis=1)
    m0 = np.where(m0 > 0, m0, 1.0)
    mean = np.sum(p * xi, axis=1) / m0
    d = xi - mean[:, None]
    var = np.maximum(np.sum(p * d * d, axis=1) / m0, 1e-300)
    skew = np.sum(p * d * d * d, axis=1) / m0
    # nodes: roots of the degree-2 orthogonal polynomial d^2 - (skew / var) d - var
    b = skew / var
    root = np.sqrt(b * b + 4.0 * var)
    d_plus, d_minus = 0.5 * (b + root), 0.5 * (b - root)
    w_plus = mass * -d_minus / (d_plus - d_minus)
    centre = lo + half * (1.0 + mean)
    y = np.concatenate([centre + half * d_minus, centre + half * d_plus])
    return y, np.concatenate([mass - w_plus, w_plus])


def _tail_moment(edge: float, alpha: float, power: float) -> float:
    """Integral of g(y) exp(power (y - edge)) beyond the edge, on the side where it decays
    (power > 0: below the edge, power < 0: above), by Gauss-Laguerre: past the peak g is a
    power law times a smooth factor."""
    rate = alpha + abs(power)
    _, _, lag_x, lag_w = _rules()
    y = edge - np.sign(power) * lag_x / rate
    return float(np.sum(lag_w * log_rate_density(y, alpha) * np.exp(power * (y - edge) + lag_x)) / rate)


def modes(duration_s: float, dt_s: float, tau_s: float, alpha: float,
          per_decade: int = MODES_PER_DECADE) -> tuple[np.ndarray, np.ndarray]:
    """Rates (1/s) and weights (summing to 1) of the modes that stand for E_a(-(t/tau)^a) over a
    record: two per cell from a tenth of the record's inverse length to a hundred per sample,
    and one for each tail beyond (see the module's docstring)."""
    cells_per_decade = max(1, per_decade // 2)
    y_lo = min(np.log(SLOW_EDGE_PER_DURATION / max(duration_s, dt_s) * tau_s), -PEAK_HALF_WIDTH)
    y_hi = max(np.log(FAST_EDGE_PER_DT / dt_s * tau_s), PEAK_HALF_WIDTH)
    n = max(1, int(np.ceil((y_hi - y_lo) / np.log(10.0) * cells_per_decade)))
    y, w = _cell_gauss_rules(np.linspace(y_lo, y_hi, n + 1), alpha)
    cdf = mittag_leffler_cdf(np.exp(np.array([y_lo, y_hi])), alpha)
    w_slow, w_fast = float(cdf[0]), float(1.0 - cdf[1])
    # the slow tail keeps its mean rate, the fast tail its mean relaxation time
    y_slow = y_lo + np.log(_tail_moment(y_lo, alpha, 1.0) / w_slow) if w_slow > 0 else y_lo
    y_fast = y_hi - np.log(_tail_moment(y_hi, alpha, -1.0) / w_fast) if w_fast > 0 else y_hi
    rates = np.exp(np.concatenate([[y_slow], y, [y_fast]])) / tau_s
    weights = np.concatenate([[w_slow], w, [w_fast]])
    keep = weights > 1e-15  # far tails of a narrow distribution: nothing to carry
    return rates[keep], weights[keep]


def _fft_length(n: int) -> int:
    """Smallest 2^i 3^j 5^k >= n: a length numpy's FFT handles at full speed."""
    best, p2 = 1 << max(0, (n - 1).bit_length()), 1
    while p2 < best:
        p3 = p2
        while p3 < best:
            p5 = p3
            while p5 < n:
                p5 *= 5
            best = min(best, p5)
            p3 *= 3
        p2 *= 2
    return best


def modes_kernel(rates_per_s: np.ndarray, weights: np.ndarray, n: int, dt_s: float) -> np.ndarray:
    """Impulse response (per unit k, in s) of the sum of lags k w / r * (r-lag of the rate):
    force[i] = k sum_j h[j] v[i - j], each lag solved exactly for v linear between samples.

    h[0] = sum w dt b0 / x and h[j] = sum w dt (1 - a)(1 - b0) / x a^(j-1) (x = r dt, a = e^-x,
    b0 = 1 - (1 - a) / x): a mode far faster than a sample gives h[0] ~ w / r, its ramp force
    k w v / r. The powers a^j come in blocks, a^(B q + m) = a^(B q) a^m, so the kernel is one
    matrix product and ~2 sqrt(n) exponentials per mode rather than n."""
    x = np.asarray(rates_per_s, dtype=float) * dt_s
    w = np.asarray(weights, dtype=float)
    one_minus_a = -np.expm1(-x)
    small = x < 1e-3  # 1 - (1 - a) / x loses its digits: its series instead
    b0_over_x = np.where(small, 0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0 - x / 120.0)),
                         (1.0 - one_minus_a / np.where(small, 1.0, x)) / np.where(small, 1.0, x))
    h = np.zeros(n)
    h[0] = dt_s * np.sum(w * b0_over_x)
    if n > 1:
        tail_amp = dt_s * w * (one_minus_a / np.where(x > 0, x, 1.0)) * (1.0 - x * b0_over_x)
        m = n - 1
        block = max(1, int(np.sqrt(m)))
        q = np.arange(-(-m // block))
        powers_in = _decay(np.outer(x, np.arange(block)))  # a^m, m < block
        powers_of = _decay(np.outer(q * block, x))  # a^(B q)
        # in slices small enough that OpenBLAS keeps to one thread: past ~1e6 multiply-adds it
        # starts a pool, and on a loaded machine the hand-over took 11 ms where the work took 0.05
        rows = max(1, _SINGLE_THREAD_GEMM // (len(x) * block))
        out = np.empty((len(q), block))
        for i in range(0, len(q), rows):
            np.matmul(powers_of[i:i + rows] * tail_amp, powers_in, out=out[i:i + rows])
        h[1:] = out.ravel()[:m]
    return h


def _decay(exponent: np.ndarray) -> np.ndarray:
    """exp(-exponent), zero below e^-300: products of such powers would reach subnormal floats,
    which multiply ~100x slower (a tau of 1e4 s took 14 ms a call instead of 0.4)."""
    return np.where(exponent < 300.0, np.exp(-np.minimum(exponent, 300.0)), 0.0)


def fractional_maxwell(v_m_s: np.ndarray, dt_s: float, k_N_per_m: float, tau_s: float,
                       alpha: float) -> np.ndarray:
    """Force (N) of the branch driven by the indentation rate: sum over modes of
    f_i + df_i/dt / rate_i = k w_i / rate_i dx/dt."""
    v = np.asarray(v_m_s, dtype=float)
    n = len(v)
    if n == 0:
        return np.zeros(0)
    rates, weights = modes(n * dt_s, dt_s, tau_s, alpha)
    h = modes_kernel(rates, weights, n, dt_s)
    size = _fft_length(2 * n)
    f = np.fft.irfft(np.fft.rfft(v, size) * np.fft.rfft(h, size), size)[:n] * k_N_per_m
    moving = np.flatnonzero(v)
    f[:moving[0] if len(moving) else n] = 0.0  # no rate yet: no force, not the FFT's rounding
    return f
