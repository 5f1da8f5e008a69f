"""Uncertainty of fitted parameters when the residual is correlated in time (the one BIC that
compares models is `criterion.bic`).

At 100 Hz neighbouring residuals are not independent: the sensor's filter correlates its
noise, a drift wanders under it, and a model that misses something leaves a smooth misfit.
The textbook covariance s^2 (J^T J)^-1 then counts every sample as new information and its
standard errors come out about sqrt(L) too small (L: the residual's integral time scale).

The covariance here is the sandwich B^-1 Omega B^-1, B = J^T J, Omega the covariance of the
score sum_t J_t r_t within each trial (trials are independent). Each trial's noise is first
given a model, one of two, whichever has the larger BIC of the restricted likelihood of the
residual (the likelihood of what the fit left: the fitted directions out, `_reml`):

- an AR(p), p <= MAX_AR_ORDER by BIC, its coefficients corrected for the bias a fitted residual
  and a short record put into them (`_prewhitening`) and bounded so that the noise they describe
  is correlated over at most the record (recolouring by 1 / (1 - sum phi)^2 stays finite). Omega
  is then the HAC estimate after prewhitening (Andrews and Monahan 1992): the Bartlett sum over
  the filtered score with Andrews' (1991) plug-in bandwidth (`bandwidth`), recoloured, plus a
  random-walk drift when the prewhitened residual's lowest frequencies still show one (`_drift`);
- white noise plus a random walk from the trial's start (a local level: `_level`), whose
  covariance s_eps^2 I + s_eta^2 min(i, j) goes through J exactly (the walk as the reverse
  cumulative sum of J), both variances by restricted maximum likelihood. It is not chosen when
  the trial's own quiet approach (where the force is known to be at rest) rules out such a walk
  (`_quiet_refutes`): a model's smooth misfit in contact reads as a large walk, and on real AFM
  curves inflated the standard errors 10-50x with a noise the approach shows no trace of.

Why this noise model and not the simpler ones it replaced (each measured for coverage over
hundreds of seeds): docs/explanation/standard-errors.md, "Why this one".

`hac_covariance` appends to `notes` why an estimate is doubtful: a bound was hit (the AR
filter at the record's length, the bandwidth at its limit), a drift or a walk was included, or the
residual holds fewer than MIN_EFFECTIVE_PER_PARAM independent samples per parameter (then no
residual-based error is reliable: a few independent stretches cannot show their own spread).

BIC is defined once, on the effective number of independent residuals (see `bic`).
"""

from __future__ import annotations

import functools
import math

import numpy as np

MAX_AR_ORDER = 8  # prewhitening filter's order at most (chosen by BIC below that)
BIAS_NEGLIGIBLE = 50  # independent stretches per record beyond which the bias is not measured
BOOTSTRAP_DRAWS = 24  # simulated records that measure the prewhitening coefficients' bias
BOOTSTRAP_ROUNDS = 2
DRIFT_LR = 3.84  # a random walk is added when it improves the low-frequency fit this much (chi^2_1, 5 %)
# a walk is ruled out by the approach at rest only beyond chi^2_1's 1 %: at 5 % a small true walk
# (1x the noise end to end) was ruled out often enough to take the Hertz fit's contact point from
# 90 % coverage to 88 %; a misfit as large as the noise reaches 9-13, real AFM curves 1e4
QUIET_LR = 6.63
ANDREWS_MAX_RHO = 0.97  # the plug-in's AR(1) coefficient at most, as Andrews (1991) clips it
MAX_BANDWIDTH_FRACTION = 0.25  # of a trial's samples: beyond that the lags are too few to average
MIN_SAMPLES = 32  # a trial shorter than this is summed as white: too short to fit a noise model to
MIN_EFFECTIVE_PER_PARAM = 5.0

__all__ = ["bandwidth", "correlation", "hac_covariance", "notable_correlations", "white_covariance"]


def bandwidth(e: np.ndarray) -> tuple[int, bool]:
    """Andrews' (1991) plug-in bandwidth of the Bartlett kernel for the long-run covariance of
    the columns of `e`, from an AR(1) fitted to each (scaled to unit variance, so a parameter's
    units do not weigh it): M = 1.1447 (alpha n)^(1/3). Also whether a limit was hit (an AR(1)
    coefficient at ANDREWS_MAX_RHO or M at MAX_BANDWIDTH_FRACTION of the samples)."""
    n = len(e)
    if n < 4:
        return 1, False
    s = e / np.maximum(np.sqrt(np.mean(e * e, axis=0)), np.finfo(float).tiny)
    live = np.any(s != 0.0, axis=0)
    if not np.any(live):
        return 1, False
    s = s[:, live]
    rho = np.sum(s[1:] * s[:-1], axis=0) / np.maximum(np.sum(s[:-1] ** 2, axis=0), np.finfo(float).tiny)
    clipped = bool(np.any(np.abs(rho) > ANDREWS_MAX_RHO))
    rho = np.clip(rho, -ANDREWS_MAX_RHO, ANDREWS_MAX_RHO)
    alpha = np.sum(4 * rho ** 2 / ((1 - rho) ** 6 * (1 + rho) ** 2)) / np.sum(1 / (1 - rho) ** 4)
    M = 1.1447 * (alpha * n) ** (1 / 3)
    cap = MAX_BANDWIDTH_FRACTION * n
    return int(max(1, round(min(M, cap)))), clipped or cap < M


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


# The AR helpers here are not `noise`'s: the noise model is Yule-Walker from an autocovariance
# (always stationary, the order by BIC on the quiet stretch), while a residual's correlation is fitted
# by least squares on the residual itself (`_ar_fit`, with its small-sample bias corrected by
# `_prewhitening`), whitened along the first axis of a design matrix as well as of a series
# (`_whiten`; `noise.whiten` runs along the last), and its long-run variance taken exactly from the
# Yule-Walker equations (`_integral_scale`: inf when not stationary; `noise.integral_scale_ar` sums
# a truncated autocorrelation and stops at 1). The same names, different estimators.
def _ar_order(r: np.ndarray, pmax: int) -> int:
    """AR order of `r` by BIC over 0..pmax, every order fitted by least squares on the same samples."""
    return int(np.argmin(_ar_orders_bic(r, pmax, 0)))


def _ar_orders_bic(r: np.ndarray, pmax: int, extra: int) -> np.ndarray:
    """BIC of the AR orders 0..pmax of `r` (each fitted by least squares on the same samples), with
    `extra` further parameters counted in each."""
    n = len(r)
    X = np.column_stack([r[pmax - k:n - k] for k in range(1, pmax + 1)] + [r[pmax:]])
    G = X.T @ X
    G += (1e-12 * np.trace(G) / (pmax + 1) + np.finfo(float).tiny) * np.eye(pmax + 1)
    R = np.linalg.cholesky(G).T
    # the last column of the Cholesky factor holds the residual of every nested fit at once
    rss = np.maximum(np.cumsum(R[::-1, -1] ** 2)[::-1], np.finfo(float).tiny)
    m = n - pmax
    return m * np.log(rss / m) + np.log(m) * (np.arange(pmax + 1) + extra)


def _ar_fit(R: np.ndarray, q: int) -> np.ndarray:
    """Least-squares AR(q) coefficients of each row of `R` (records x samples)."""
    n = R.shape[1]
    X = np.stack([R[:, q - k:n - k] for k in range(1, q + 1)], axis=-1)
    Xt = X.transpose(0, 2, 1)
    return np.linalg.solve(Xt @ X, Xt @ R[:, q:, None])[..., 0]


def _integral_scale(phi: np.ndarray, largest_root: float | None = None) -> float:
    """Samples per independent value of the AR(phi) process: its long-run variance over its
    variance, gamma_0 from the Yule-Walker equations; inf if it is not stationary (the largest
    root's modulus, when known, spares finding the roots)."""
    q = len(phi)
    if q == 0:
        return 1.0
    if largest_root is None:
        largest_root = _largest_root(phi)
    if largest_root >= 1.0:
        return math.inf
    gamma0 = _autocovariance_unit(phi)[0]
    return float(1.0 / ((1.0 - phi.sum()) ** 2 * gamma0)) if gamma0 > 0 else math.inf


def _largest_root(phi: np.ndarray) -> float:
    # an AR(1)'s one root is its coefficient (np.roots gives it exactly)
    return abs(float(phi[0])) if len(phi) == 1 else float(np.max(np.abs(np.roots(np.r_[1.0, -phi]))))


def _autocovariance_unit(phi: np.ndarray) -> np.ndarray:
    """gamma_0..gamma_q of the stationary AR(phi) of unit innovation variance, from the Yule-Walker
    equations gamma_k - sum_j phi_j gamma_|k-j| = [k == 0], k = 0..q."""
    q = len(phi)
    A = np.eye(q + 1)
    for k in range(q + 1):
        for j in range(1, q + 1):
            A[k, abs(k - j)] -= phi[j - 1]
    return np.linalg.solve(A, np.eye(q + 1)[0])


def _bounded(phi: np.ndarray, m: int) -> tuple[np.ndarray, bool]:
    """`phi` with its roots pulled in (phi_k s^k, s < 1) until the process it describes is
    correlated over at most the record's `m` samples: recolouring by 1 / (1 - sum phi)^2 then
    never claims more than one independent value per record. Also whether it had to."""
    if len(phi) == 0:
        return phi, False
    root = _largest_root(phi)
    if _integral_scale(phi, root) <= m:
        return phi, False
    k = np.arange(1, len(phi) + 1)
    lo, hi = 0.0, 1.0
    for _ in range(40):
        s = 0.5 * (lo + hi)
        # phi_k s^k has the roots of phi times s: found once, not at each step
        lo, hi = (s, hi) if _integral_scale(phi * s ** k, root * s) <= m else (lo, s)
    return phi * lo ** k, True


class _LazyRandom:
    """numpy's generator seeded 0, made on first use: most fits never measure a bias, and
    numpy.random costs them 9 ms to import.

    Every one starts from the same seed, so the draws it gives depend only on the shapes asked
    for so far: they are kept (`_DRAWN`, by that sequence of shapes) and given again to the next
    one that asks for the same, where drawing them took a tenth of a misfitting curve's fit (a
    map's curves, and a fit's refits, ask for the same shapes over and over)."""

    def __init__(self) -> None:
        self._asked: tuple[tuple[int, ...], ...] = ()

    def standard_normal(self, shape: tuple[int, ...]) -> np.ndarray:
        self._asked = (*self._asked, tuple(shape))
        got = _DRAWN.get(self._asked)
        if got is None:
            rng = np.random.default_rng(0)
            for earlier in self._asked[:-1]:
                rng.normal(size=earlier)  # the stream moved past what was given from `_DRAWN`
            got = rng.normal(size=shape)
            got.flags.writeable = False
            if len(_DRAWN) >= _DRAWN_KEPT:
                _DRAWN.pop(next(iter(_DRAWN)))
            _DRAWN[self._asked] = got
        return got


_DRAWN: dict[tuple, np.ndarray] = {}
_DRAWN_KEPT = 16


def _prewhitening(r: np.ndarray, Q: np.ndarray, rng: _LazyRandom,
                  order: int | None = None) -> tuple[np.ndarray, bool]:
    """AR coefficients of the noise under the residual `r` of one trial, its order by BIC.

    Least squares on a fitted residual is biased towards white: the fit took the model's
    directions (`Q`, orthonormal, this trial's rows) out of the noise, and a short record of a
    slow process under-reads its persistence. Near a unit root that bias is the whole error
    (rho 0.996 read for 0.998 halves the standard error), so it is measured: records are
    simulated from the coefficients, projected off the same directions and refitted, and the
    coefficients moved by the difference (indirect inference, a fixed number of draws)."""
    m = len(r)
    q = _ar_order(r, min(MAX_AR_ORDER, m // 10)) if order is None else order
    if q == 0:
        return np.zeros(0), False
    observed = _ar_fit(r[None, :], q)[0]
    phi, hit = _bounded(observed, m)
    if m > BIAS_NEGLIGIBLE * _integral_scale(phi):
        # the bias moves the correlation time by about twice itself over the record (AR(1): the
        # estimate is low by (1 + 3 rho) / m): with fifty independent stretches or more the
        # standard errors move by 2 % or less, below their own scatter, and measuring it costs
        # the most of a one-curve fit
        return phi, hit
    N = 1 << math.ceil(math.log2(3 * m))
    shape = (BOOTSTRAP_DRAWS, N // 2 + 1)
    z = rng.standard_normal(shape) + 1j * rng.standard_normal(shape)
    w = np.exp(-2j * np.pi * np.arange(N // 2 + 1) / N)
    for _ in range(BOOTSTRAP_ROUNDS):
        a = 1.0 - sum(c * w ** (k + 1) for k, c in enumerate(phi))
        u = np.fft.irfft(z / np.abs(a), N, axis=1)[:, :m]  # circulant draws: stationary over m < N/3
        u -= (u @ Q) @ Q.T
        phi, hit = _bounded(phi + observed - _ar_fit(u, q).mean(axis=0), m)
    return phi, hit


def _whiten(x: np.ndarray, phi: np.ndarray) -> np.ndarray:
    q = len(phi)
    out = x[q:].copy()
    for k, c in enumerate(phi):
        out -= c * x[q - 1 - k:len(x) - 1 - k]
    return out


def _drift(w: np.ndarray, skip: int) -> float:
    """Increment variance of a random walk under the prewhitened residual `w` (0 if none).

    An AR filter of a few lags cannot follow a slow drift under white noise: the drift adds
    little variance but dominates the error of a baseline and a slope. Its spectrum rises as
    1 / omega^2 at the lowest frequencies, so `w`'s periodogram over the lowest eighth of its
    frequencies is fitted by Whittle's likelihood as a + b / (4 sin^2(omega / 2)) (white plus a
    walk), skipping the `skip` lowest that the fit itself removed; b is kept when the likelihood
    ratio against b = 0 passes DRIFT_LR. (Not on the first difference, where a walk is white:
    the difference's two ends add the same constant to every frequency, a walk that is not.)"""
    n = len(w)
    j = np.arange(skip, max(skip + 8, n // 8))
    if n < 16 or j[-1] > n // 2:
        return 0.0
    power = np.abs(np.fft.rfft(w)[j]) ** 2 / n
    X = np.column_stack([np.ones(len(j)), 0.25 / np.sin(np.pi * j / n) ** 2])
    white = np.full(len(j), np.mean(power))
    theta = np.array([white[0], 0.0])
    for _ in range(50):  # Fisher scoring of a spectrum linear in (a, b): reweighted least squares
        f = X @ theta
        Xw = X / f[:, None] ** 2
        new = np.linalg.solve(Xw.T @ X, Xw.T @ power)
        if new[1] <= 0.0 or new[0] <= 0.0:
            return 0.0
        # np.allclose(new, theta, rtol=1e-8, atol=0) on two numbers, without its array machinery
        # (a tenth of a millisecond a curve)
        done = all(a == b or (math.isfinite(b) and abs(a - b) <= 1e-8 * abs(b))
                   for a, b in zip(new.tolist(), theta.tolist(), strict=True))
        theta = new
        if done:
            break
    f = X @ theta
    lr = 2.0 * (np.sum(np.log(white) + power / white) - np.sum(np.log(f) + power / f))
    return float(theta[1]) if lr > DRIFT_LR else 0.0


def _reml(X: np.ndarray, logdet: float, k: int) -> float:
    """Restricted log-likelihood (constants left out, s^2 at its maximum) of a residual whose noise
    has covariance s^2 Sigma_0, from X = [W r, W Q] with W^T W = Sigma_0^-1 and log det Sigma_0 =
    `logdet`; Q's k orthonormal columns are the directions the fit took out. It depends on r only
    through what the fit left: P r, with P Q = 0."""
    G = X.T @ X
    m = len(X)
    if k:
        c = np.linalg.cholesky(G[1:, 1:])
        b = np.linalg.solve(c, G[1:, 0])
        rss, logdet = G[0, 0] - b @ b, logdet + 2.0 * float(np.sum(np.log(np.diag(c))))
    else:
        rss = G[0, 0]
    s2 = max(float(rss), np.finfo(float).tiny) / (m - k)
    return -0.5 * ((m - k) * math.log(s2) + logdet)


def _ar_reml(r: np.ndarray, Q: np.ndarray, phi: np.ndarray) -> float:
    """`_reml` of the residual under a stationary AR(phi): the first len(phi) samples whitened by
    their stationary covariance's Cholesky factor, the rest by the filter."""
    q = len(phi)
    X = np.column_stack([r, Q])
    if q == 0:
        return _reml(X, 0.0, Q.shape[1])
    gamma = _autocovariance_unit(phi)
    G = gamma[np.abs(np.subtract.outer(np.arange(q), np.arange(q)))]
    try:
        c = np.linalg.cholesky(G)
    except np.linalg.LinAlgError:  # a root so near one that the first samples' covariance is singular
        return _reml(_whiten(X, phi), 0.0, Q.shape[1])  # to rounding: the likelihood given them
    W = np.vstack([np.linalg.solve(c, X[:q]), _whiten(X, phi)])
    return _reml(W, 2.0 * float(np.sum(np.log(np.diag(c)))), Q.shape[1])


def _walk_basis(r: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """r and Q in the eigenbasis of K, K_ij = min(i, j): sin(a_k t), a_k = (2k - 1) pi / (2m + 1),
    eigenvalues mu_k = 1 / (4 sin^2(a_k / 2)); one FFT. Returns the products of every pair of
    the columns [r, Q] there (m, pairs of `np.triu_indices`) and mu."""
    m, k = Q.shape
    X = np.vstack([r, Q.T])
    N = 2 * m + 1
    a = (2 * np.arange(1, m + 1) - 1) * np.pi / N
    # sum_t x_t sin(pi (2k - 1) t / N) is minus the imaginary part of the length-N transform of
    # x_t e^(i pi t / N): a complex transform of N points, where the real transform of 4m + 2
    # points it equals took up to four times as long (m = 1500: 4 ms against 0.8 ms) when 2m + 1
    # has a large prime factor, as it has for most lengths
    Z = np.zeros((k + 1, m + 1), dtype=complex)  # from t = 0, where every column is zero
    Z[:, 1:] = X * np.exp(1j * np.pi / N * np.arange(1, m + 1))
    Y = -np.fft.fft(Z, N, axis=1)[:, 1:m + 1].imag.T
    Y *= 2.0 / math.sqrt(N)
    i, j = _pairs(k + 1)
    return Y[:, i] * Y[:, j], 0.25 / np.sin(0.5 * a) ** 2


@functools.lru_cache(maxsize=16)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """`np.triu_indices(n)`, made once for each of the few sizes a fit has (thousands of calls a map)."""
    i, j = np.triu_indices(n)
    i.flags.writeable = j.flags.writeable = False
    return i, j


def _walk_rss(P: np.ndarray, lam: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """For covariances diagonal in the walk basis with eigenvalues `lam` (rows: several at once),
    the restricted residual sum of squares r^T P^T Sigma^-1 P r and log det Sigma + log det
    Q^T Sigma^-1 Q."""
    i, j = _pairs(k + 1)
    w = 1.0 / lam
    G = np.zeros((len(lam), k + 1, k + 1))
    G[:, i, j] = w @ P
    G[:, j, i] = G[:, i, j]
    logdet = np.sum(np.log(lam), axis=1)
    if k:
        c = np.linalg.cholesky(G[:, 1:, 1:])
        b = np.linalg.solve(c, G[:, 1:, :1])[..., 0]
        logdet = logdet + 2.0 * np.sum(np.log(np.diagonal(c, axis1=1, axis2=2)), axis=1)
        return G[:, 0, 0] - np.sum(b * b, axis=1), logdet
    return G[:, 0, 0], logdet


def _level(r: np.ndarray, Q: np.ndarray,
           basis: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float, float, float]:
    """White noise plus a random walk from the trial's start under the residual `r`: restricted
    log-likelihood at its maximum, the white variance and the walk's increment variance (REML).

    Sigma = s^2 (I + q K) is diagonal in `_walk_basis` (`basis`, when already computed), so the
    likelihood at any q is a weighted sum, evaluated on a grid of log q and refined by a
    parabola through the best three."""
    m, k = Q.shape
    P, mu = basis if basis is not None else _walk_basis(r, Q)

    def values(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rss, logdet = _walk_rss(P, 1.0 + np.exp(u)[:, None] * mu, k)
        s2 = np.maximum(rss, np.finfo(float).tiny) / (m - k)
        return -0.5 * ((m - k) * np.log(s2) + logdet), s2

    grid = np.arange(math.log(1e-2 / m ** 2), math.log(1e3), 1.0)
    ll, _ = values(grid)
    best = int(np.argmax(ll))
    u = grid[best]
    if 0 < best < len(grid) - 1:
        y0, y1, y2 = ll[best - 1:best + 2]
        curve = y0 - 2 * y1 + y2
        if curve < 0:
            u += 0.5 * (y0 - y2) / curve
    ll, s2 = values(np.array([u]))
    return float(ll[0]), float(s2[0]), float(s2[0] * math.exp(u))


class _AtRest:
    """A trial's stretch at rest (the approach before contact: residual `r`, `J` its rows of the
    Jacobian), with what the checks against it share, each computed once: the fitted directions
    there, the residual without them, and the walk model's fit."""

    def __init__(self, r: np.ndarray, J: np.ndarray) -> None:
        self.r = r
        self.Q = _basis(J)
        self.m, self.k = self.Q.shape
        self.u = r - self.Q @ (self.Q.T @ r)
        self._walk: tuple | None = None

    def walk(self) -> tuple[float, float, float, np.ndarray, np.ndarray]:
        """`_level`'s log-likelihood, white and walk variances, and the walk basis (P, mu)."""
        if self._walk is None:
            basis = _walk_basis(self.r, self.Q)
            self._walk = (*_level(self.r, self.Q, basis), *basis)
        return self._walk


def _quiet_refutes(rest: _AtRest | None, s_eta: float) -> bool:
    """Whether the stretch at rest rules out a random walk of increment variance `s_eta`: a
    noise walks there too, where a model's smooth misfit in contact, which reads as a walk over
    the whole record, is absent. The stretch's restricted likelihood with the walk held at
    `s_eta` (the white variance at its best) against its maximum, at QUIET_LR; one-sided: a
    stretch that walks more refutes nothing."""
    if rest is None or rest.m < MIN_SAMPLES or rest.m <= 2 * rest.k + 2:
        return False
    ll, s_eps, s_eta_here, P, mu = rest.walk()
    if s_eta <= s_eta_here or s_eps <= 0.0:
        return False
    best = ll - 0.5 * (rest.m - rest.k)  # the concentrated maximum, its constant put back

    def walk_held(u: np.ndarray) -> np.ndarray:  # the walk at s_eta, the white variance s_eps e^u
        rss, logdet = _walk_rss(P, s_eps * np.exp(u)[:, None] + s_eta * mu[None, :], rest.k)
        return -0.5 * (logdet + rss)

    return 2.0 * (best - _line_max(walk_held, np.arange(-12.0, 3.01, 0.25))) > QUIET_LR


def _spectrum(phi: np.ndarray, s2: float, omega: np.ndarray) -> np.ndarray:
    """Spectral density (per sample) of an AR(phi) of innovation variance s2 at `omega`."""
    a = np.ones(len(omega), dtype=complex)
    for k, c in enumerate(phi):
        a -= c * np.exp(-1j * (k + 1) * omega)
    return s2 / np.maximum(np.abs(a) ** 2, np.finfo(float).tiny)


def _quiet_too_slow(rest: _AtRest, phi: np.ndarray, s2: float) -> bool:
    """Whether the stretch at rest rules out the residual's own noise model, AR(phi) of
    innovation variance s2, as too slow.

    A model's smooth misfit in contact reads as a strongly correlated noise: prewhitened and
    recoloured it multiplies the standard errors (by up to 100 on real AFM curves whose fit
    differs from nanite's by a few per cent). A noise is the same at rest; a misfit is not there.
    Over the stretch's frequencies where the model claims its slow power (its spectrum S above
    half its value at zero, eight at least: that is where a misfit lives, and what the standard
    errors rest on; over a wider band the test missed most misfits), Whittle's likelihood of S
    against c S, c fitted: the periodogram over S is exponential of mean 1 under the residual's
    model, so the likelihood ratio is chi^2_1. One-sided (c < 1: less power at rest than the
    model claims), at QUIET_LR. Measured on 100 records each: AR(1) at 0.99 and 0.998, low-pass
    noises at 0.005 and 0.02 of Nyquist, refuted 0-1.6 % of the time; misfits of 1-3x the noise
    under white noise every time."""
    m, k = rest.m, rest.k
    if m < MIN_SAMPLES or m < 2 * k + 20:
        return False
    j = np.arange(k + 1, m // 2)  # the lowest k went with the fitted directions
    S = _spectrum(phi, s2, 2.0 * np.pi * j / m)
    band = max(int(np.argmax(0.5 * S[0] > S)) or len(S), 8)
    power = np.abs(np.fft.rfft(rest.u)[j[:band]]) ** 2 / m
    c = float(np.mean(power / S[:band]))
    return 0.0 < c < 1.0 and 2.0 * band * (c - 1.0 - math.log(c)) > QUIET_LR


def walk_at_rest(b: np.ndarray, ar: tuple[float, ...] | np.ndarray = ()) -> float:
    """The increment variance of a random walk under a stretch at rest `b` beyond its AR(`ar`)
    noise (its straight line out, whitened by the AR, the walk found by `_drift` at the lowest
    frequencies and recoloured), or 0 when the stretch shows none.

    The adequacy test simulates the noise it measured at rest over the whole record: without the
    walk, a perfect model under a slow drift, or under an AR(1) at 0.99 that wanders over the record
    as a walk does, left a residual "correlated beyond the noise's own" and was called NOT adequate
    (a walk 3x the noise over the record: 82 % of seeds). Beyond the AR, not beyond white noise:
    a low-pass sensor's noise is not a walk, and read as one it hid every misfit."""
    m = len(b)
    if m < MIN_SAMPLES:
        return 0.0
    y = np.asarray(b, dtype=float)
    u = np.linspace(-1.0, 1.0, m)
    y = y - np.polyval(np.polyfit(u, y, 1), u)
    phi = np.asarray(ar, dtype=float)
    # white noise plus a walk against the AR, by the BIC of their restricted likelihoods as the
    # standard errors choose (`hac_covariance`): a walk that dominates the stretch is followed by an
    # AR near a unit root, which leaves `_drift` nothing to find
    Q = _basis(np.column_stack([np.ones(m), u]))
    ll_lv, _, s_eta = _level(y, Q)
    if s_eta > 0.0 and ll_lv - _ar_reml(y, Q, phi) > 0.5 * (1 - len(phi)) * math.log(m):
        return float(s_eta)
    gain = 1.0 / (1.0 - float(phi.sum())) ** 2 if len(phi) else 1.0
    return _drift(_whiten(y, phi), 3) * gain


SHAPE_FROM = 8  # the walk's shape is judged on its components from this one up (the lowest hold a misfit)


def _line_max(f, grid: np.ndarray) -> float:
    """The largest value of f (vectorised) along a line: on `grid` (evenly spaced), then on a grid
    64 times finer around its best point. A log-likelihood over thousands of components is peaked:
    half a coarse step of 0.25 off its best variance costs it some 6 units.

    Each grid is searched from every COARSE-th point and then around the best of those, which
    finds the same best point as the whole grid for a likelihood with one peak along the line
    (a variance ratio's) at a fraction of the evaluations: each costs a pass over the record's
    components, and the walk's tests took two fifths of a map curve's analysis."""
    values, at = _peak(f, grid)
    step = float(grid[1] - grid[0])
    fine = grid[at] + np.linspace(-step, step, 129)
    return max(values, _peak(f, fine)[0])


COARSE = 8  # `_line_max` looks at every COARSE-th point first


def _peak(f, grid: np.ndarray) -> tuple[float, int]:
    """The largest of f over `grid` and where it is, searched from every COARSE-th point and then
    among the points between the best one's neighbours."""
    first = np.arange(0, len(grid), COARSE)
    if first[-1] != len(grid) - 1:
        first = np.append(first, len(grid) - 1)
    best = first[int(np.argmax(f(grid[first])))]
    lo, hi = max(best - COARSE + 1, 0), min(best + COARSE, len(grid))
    near = f(grid[lo:hi])
    at = lo + int(np.argmax(near))
    return float(near[at - lo]), at


def _shape_refutes(basis: tuple[np.ndarray, np.ndarray], k: int, s_eta: float) -> bool:
    """Whether the residual's own spectrum rules out the walk it was read as: a walk's power falls
    as 1 / frequency^2 over every frequency where it stands above the white noise, where a smooth
    misfit (a model that misses a shape) holds its power in the lowest few components and little
    beyond. Over the components from SHAPE_FROM up, the walk held at `s_eta` (the white variance at
    its best) against their own best white plus walk, at QUIET_LR.

    Without it a misfit with a short stretch at rest (100 samples before contact) was read as a
    walk on every seed: the errors of a Hertz fit 40-300x the estimates' scatter."""
    P, mu = basis
    P, mu = P[SHAPE_FROM:], mu[SHAPE_FROM:]
    m = len(mu)
    if m < MIN_SAMPLES:
        return False
    scale = float(np.median(P[:, 0])) or 1.0  # the residual's power per component, roughly
    n = m - k

    def walk_held(u: np.ndarray) -> np.ndarray:  # the walk at s_eta, the white variance scale e^u
        rss, logdet = _walk_rss(P, scale * np.exp(u)[:, None] + s_eta * mu[None, :], k)
        return -0.5 * (logdet + rss)

    def both_free(u: np.ndarray) -> np.ndarray:
        # s^2 (I + q K), q = e^u, s^2 at its REML value: one line to search, not a grid over both
        # variances (6000 covariances over the record cost a fit 66 ms a trial)
        rss, logdet = _walk_rss(P, 1.0 + np.exp(u)[:, None] * mu[None, :], k)
        return -0.5 * (n * np.log(np.maximum(rss, np.finfo(float).tiny) / n) + logdet + n)

    held = _line_max(walk_held, np.arange(-12.0, 12.25, 0.25))
    best = _line_max(both_free, math.log(s_eta / scale) + np.arange(-42.0, 12.25, 0.25))
    return 2.0 * (max(best, held) - held) > QUIET_LR


def _where_it_is(J: np.ndarray, r: np.ndarray, rest: _AtRest, rng: _LazyRandom,
                 louder: list[float] | None = None) -> np.ndarray:
    """J^T Sigma J for a noise measured where it is: the stretch at rest's own AR on its rows and
    on the rows after it where the model is still at rest (its contact not reached), and in
    contact the noise of the residual there (`_in_contact`), never quieter than at rest.

    A sensor noisier in contact (the tip's contact adds force noise; on real AFM curves the short
    lags read 1.2-18x the rest on 9 of 19) made the residual's noise louder than the rest's; read
    as a misfit, the errors were the quiet rest's: on an exact Hertz curve with twice the noise in
    contact they held the truth 65 % of the time, 12 % with a correlated noise there."""
    q = rest.m
    at_rest, _ = _prewhitening(rest.u, rest.Q, rng)
    s2_rest = float(np.mean(_whiten(rest.u, at_rest) ** 2))
    # the contact: the first row past the rest where a direction idle all through the rest (the
    # contact law's) moves. The rows between are at rest too, and a noise measured over them and
    # the contact at once reads an average of the two (a quiet part cut early left 950 white rows
    # under an AR(1) at 0.95 twice as loud in contact: its errors 0.62 of the true ones)
    idle = ~np.any(J[:q] != 0.0, axis=0)
    moved = np.flatnonzero(np.any(J[q:, idle] != 0.0, axis=1)) if idle.any() else np.zeros(0, int)
    c = q + (int(moved[0]) if len(moved) else 0)
    meat = _spectral_meat(J[:c], at_rest, s2_rest)
    if len(r) - c < MIN_SAMPLES:
        return meat + _spectral_meat(J[c:], at_rest, s2_rest) if len(r) > c else meat
    var_rest = s2_rest * _unit_variance(at_rest)
    # never quieter than at rest, but in the contact's own spectrum: measured on the longer stretch
    # it is the surer (a rest of 124 samples read an AR whose long-run variance was 3.7x the white
    # noise's, and lent to the contact it took the errors with it)
    there, level = _in_contact_meat(J[c:], r[c:], rng, var_rest)
    if louder is not None:
        louder.append(math.sqrt(level / var_rest) if var_rest > 0 else 1.0)
    return meat + there


MAX_MISFIT_DEGREE = 8  # of the Legendre polynomial a misfit in contact is given, at most
WEIGHT_NEGLIGIBLE = 1e-4  # of the BIC weights' sum: a degree below it is left out of the average
JACOBIAN_RTOL = 1e-6  # directions weaker than this (relative) in the model's and the misfit's are one


def _in_contact(J: np.ndarray, r: np.ndarray, rng: _LazyRandom) -> list[tuple[float, np.ndarray, float]]:
    """The noise under a residual in contact that holds a smooth misfit too, as (weight, AR
    coefficients, variance): the misfit a Legendre polynomial in time, each degree weighed with the
    AR's order by one BIC (the likelihood of the prewhitened residual), and under each degree that
    counts the AR measured on what neither the model nor the polynomial takes, its bias corrected
    for both.

    A correlated noise and a smooth misfit differ in their spectra, not at one lag: the polynomial
    takes a misfit whole where an AR near a unit root would follow it as noise (a 20 % Hertz
    misfit read so: errors 160x the estimates' scatter), and over a noise it buys no likelihood
    worth its degrees, so a noise correlated over dozens of samples keeps its long-run variance
    (short lags alone read an AR(1) at 0.95 at 0.54 of its errors' scatter; this, 0.9, the rest
    being the contact law's own nonlinearity). Over 200 seeds the 20 % misfit's statistical error
    is 1.0-1.2x the estimates' scatter, seed by seed. A misfit faster than the polynomial follows
    counts as noise: the errors grow with it, they never shrink.

    The degrees and the orders are averaged by their BIC weights, not picked: two near a tie,
    swapped by a rounding of the Jacobian, moved a cone's errors by 13 %."""
    m = len(r)
    pmax = min(MAX_AR_ORDER, m // 10)
    # the model's directions and the polynomial's, one direction each: a Jacobian by finite
    # differences holds a constant column to 1e-8, and the rounding's tolerance kept its error as a
    # direction of its own, which took a cone's errors from 10.9 to 28.3
    model = _basis(J, JACOBIAN_RTOL)
    legendre = np.polynomial.legendre.legvander(np.linspace(-1.0, 1.0, m), MAX_MISFIT_DEGREE)
    tried, crits = [], []
    for d in range(MAX_MISFIT_DEGREE + 1):
        Q = _basis(np.column_stack([model, _basis(legendre[:, :d + 1])]), JACOBIAN_RTOL)
        u = r - Q @ (Q.T @ r)
        if not np.any(u):  # the polynomial takes the residual whole: nothing left to call noise
            break
        tried.append((Q, u))
        crits.append(_ar_orders_bic(u, pmax, d))
    if not tried:
        return [(1.0, np.zeros(0), 0.0)]
    C = np.array(crits)
    W = np.exp(-0.5 * (C - C.min()))
    W /= W.sum()
    out = []
    for d, o in zip(*np.nonzero(W >= WEIGHT_NEGLIGIBLE), strict=True):
        Q, u = tried[d]
        # each its own draws (the same for the same record): drawn from one stream, whether a
        # degree of little weight was kept would change every later degree's correction
        phi, _ = _prewhitening(u, Q, _LazyRandom(), int(o))
        s2 = float(np.sum(_whiten(u, phi) ** 2)) / max(m - len(phi) - Q.shape[1], 1)
        out.append((float(W[d, o]), phi, s2 * _unit_variance(phi)))
    kept = sum(w for w, _, _ in out)
    return [(w / kept, phi, var) for w, phi, var in out]


def _in_contact_meat(J: np.ndarray, r: np.ndarray, rng: _LazyRandom,
                     floor: float = 0.0) -> tuple[np.ndarray, float]:
    """J^T Sigma J for the noises `_in_contact` finds under the residual `r`, each variance at least
    `floor`, and their weighted variance."""
    noises = [(w, phi, max(var, floor)) for w, phi, var in _in_contact(J, r, rng)]
    parts = [(w, phi, var / _unit_variance(phi)) for w, phi, var in noises]
    return _mixture_meat(J, parts), sum(w * var for w, _, var in noises)


def _unit_variance(phi: np.ndarray) -> float:
    """The variance of an AR(phi) process per unit innovation variance (Yule-Walker)."""
    q = len(phi)
    if q == 0:
        return 1.0
    g = float(_autocovariance_unit(phi)[0])
    return g if g > 0 and math.isfinite(g) else 1.0


def _spectral_meat(J: np.ndarray, phi: np.ndarray, s2: float) -> np.ndarray:
    """J^T Sigma J for a stationary AR(phi) noise of innovation variance s2, through the spectrum
    (Whittle's circulant approximation: J's columns zero-padded past the noise's memory)."""
    return _mixture_meat(J, [(1.0, phi, s2)])


def _mixture_meat(J: np.ndarray, parts: list[tuple[float, np.ndarray, float]]) -> np.ndarray:
    """`_spectral_meat` of a weighted sum of AR noises (weight, phi, innovation variance): the
    meat is linear in the spectrum, so J is transformed once for them all."""
    m = len(J)
    nfft = 1 << math.ceil(math.log2(2 * m))
    F = np.fft.rfft(J, nfft, axis=0)
    omega = 2.0 * np.pi * np.arange(nfft // 2 + 1) / nfft
    S = sum(w * _spectrum(phi, s2, omega) for w, phi, s2 in parts)
    w = np.full(nfft // 2 + 1, 2.0)
    w[0] = 1.0
    if nfft % 2 == 0:
        w[-1] = 1.0
    return np.real((F.conj() * (w * S)[:, None]).T @ F) / nfft


def _basis(J: np.ndarray, rtol: float | None = None) -> np.ndarray:
    """Orthonormal columns spanning J's (its numerically dependent ones left out: singular values
    below `rtol` of the largest, by default the rounding's)."""
    U, sv, _ = np.linalg.svd(J, full_matrices=False)
    if not len(sv) or not sv[0] > 0:
        return U[:, :0]
    return U[:, sv > sv[0] * (max(J.shape) * np.finfo(float).eps if rtol is None else rtol)]


def hac_covariance(J: np.ndarray, r: np.ndarray, lengths: list[int],
                   notes: list[str] | None = None, quiet: list[int] | None = None,
                   stationary: list[bool] | None = None, zeros: list[float] | None = None,
                   used: list[str] | None = None) -> np.ndarray:
    """Covariance of least-squares parameters (in the units of J's columns) from the
    Jacobian `J` and the residual `r` of trials of `lengths` samples stacked in that order,
    each starting with `quiet` samples at rest (the approach before contact), if known.
    `stationary`: blocks whose noise is known not to walk (a creep-form residual: the force
    loop's own jitter of the position, bounded by the loop), given the AR model alone.
    `zeros`: per block, the variance of an error constant over the whole block that the residual
    cannot show (a tare's: the record's zero), in the residual's units squared; its score is that
    constant times the block's summed Jacobian.
    Reasons to doubt it, if any, are appended to `notes` as sentences; the noise model each block
    was given, to `used` (one phrase a block)."""
    n, p = J.shape
    g = J * r[:, None]
    rng = _LazyRandom()  # the same answer for the same fit
    meat = np.zeros((p, p))
    level_meat = np.zeros((p, p))
    bounded, clipped, drifting, misfit = [], [], [], []
    louder: list[float] = []  # per block in `misfit` given the noise where it is: past the rest over at rest
    start = 0
    for k, m in enumerate(lengths):
        sl = slice(start, start + m)
        start += m
        gk, rk = g[sl], r[sl]
        if m < MIN_SAMPLES or not np.any(rk):
            meat += gk.T @ gk
            _say(used, "white (too short to model)")
            continue
        # the trial's own model directions out of its residual: with several trials the joint fit
        # leaves in each the other trials' noise along them, smooth, which would read as a drift
        Qk = _basis(J[sl])
        rk = rk - Qk @ (Qk.T @ rk)
        phi, hit = _prewhitening(rk, Qk, rng)
        # the noise model: the AR(p), or white noise plus a walk, whichever the BIC of the
        # restricted likelihood (of the residual, the fitted directions out) prefers
        still = bool(stationary and stationary[k])
        basis = _walk_basis(rk, Qk) if m > 2 * Qk.shape[1] + 2 and not still else None
        ll_lv, s_eps, s_eta = _level(rk, Qk, basis) if basis is not None else (-math.inf, 0.0, 0.0)
        q = quiet[k] if quiet else 0
        rest = _AtRest(r[sl][:q], J[sl][:q]) if q else None
        walks = s_eta > 0.0 and ll_lv - _ar_reml(rk, Qk, phi) > 0.5 * (1 - len(phi)) * math.log(m)
        # whichever model won, a slow part that is not walk-shaped is a misfit: an AR near a unit
        # root absorbs it as readily as a walk does
        shaped = s_eta > 0.0 and _shape_refutes(basis, Qk.shape[1], s_eta)
        if walks and not shaped and not _quiet_refutes(rest, s_eta):
            # Sigma = s_eps I + s_eta K, K = C C^T: the parameters see
            # sum_t J_t W_t = sum_s (sum_{t>=s} J_t) dW_s
            Jk = J[sl]
            C = np.cumsum(Jk[::-1], axis=0)[::-1]
            level_meat += s_eps * (Jk.T @ Jk) + s_eta * (C.T @ C)
            drifting.append(k)
            _say(used, "white noise plus a random walk, from the residual")
            continue
        if shaped and rest is None:
            # a smooth misfit, not a walk, and no stretch at rest: the noise under the residual, the misfit out
            level_meat += _in_contact_meat(J[sl], r[sl], rng)[0]
            misfit.append(k)
            _say(used, "the residual's, a smooth misfit taken out (its slow part not walk-shaped)")
            continue
        if rest is not None:
            s2 = float(np.mean(_whiten(rk, phi) ** 2))
            if shaped or _quiet_too_slow(rest, phi, s2):
                # the residual's slow part is not noise: the errors are those of the noise where it is,
                # at rest as the stretch at rest shows it, in contact as the residual does without its misfit
                level_meat += _where_it_is(J[sl], r[sl], rest, rng, louder)
                misfit.append(k)
                _say(used, f"the noise where it is: at rest over {rest.m} samples, in contact the residual's "
                           "with a smooth misfit taken out")
                continue
        e = _whiten(gk, phi)
        M, lim = bandwidth(e)
        # recolouring: the prewhitened score's long-run covariance, back through 1 / phi(1)
        gain = 1.0 / (1.0 - float(phi.sum())) ** 2
        meat += _bartlett_meat(e, M) * gain
        b = _drift(_whiten(rk, phi), Qk.shape[1] + 1) * gain if not still else 0.0
        if b > 0.0 and not _quiet_refutes(rest, b):
            # a walk from the trial's start: the parameters see sum_t J_t W_t = sum_s (sum_{t>=s} J_t) dW_s
            C = np.cumsum(J[sl][::-1], axis=0)[::-1]
            meat += b * (C.T @ C)
            drifting.append(k)
        if hit:
            bounded.append(k)
        if lim:
            clipped.append(k)
        _say(used, f"AR({len(phi)}) of the residual" + (" with a drift" if k in drifting else ""))
    # the residual is smaller than the noise by the p directions the fit took out of it
    meat *= n / max(n - p, 1)
    if zeros:
        meat += zero_meat(J, lengths, zeros)
    meat += level_meat  # its variances are restricted-likelihood estimates: already for the residual's n - p
    bread = np.linalg.pinv(J.T @ J)
    cov = _undetermined(0.5 * (bread @ meat @ bread + (bread @ meat @ bread).T), J)
    if notes is not None:
        notes.extend(_doubts(cov, J, r, lengths, bounded, clipped, drifting, misfit, louder))
    return cov


def _say(used: list[str] | None, what: str) -> None:
    if used is not None:
        used.append(what)


def zero_meat(J: np.ndarray, lengths: list[int], zeros: list[float]) -> np.ndarray:
    """The score's covariance from an error constant over each block (variance `zeros[k]`, in the
    residual's units squared): that constant times the block's summed Jacobian."""
    sums = np.add.reduceat(J, np.cumsum([0, *lengths[:-1]]), axis=0)
    return sums.T @ (np.asarray(zeros, dtype=float)[:, None] * sums)


def _doubts(cov: np.ndarray, J: np.ndarray, r: np.ndarray, lengths: list[int], bounded: list[int],
            clipped: list[int], drifting: list[int], misfit: list[int],
            louder: list[float] | None = None) -> list[str]:
    n, p = J.shape
    which = lambda ks: "" if len(lengths) == 1 else " of trial" + ("s " if len(ks) > 1 else " ") + \
        ", ".join(str(k + 1) for k in ks)  # noqa: E731
    out = []
    if bounded:
        out.append(f"the residual{which(bounded)} is correlated over longer than the record (a slow drift "
                   "or a noise with a near-unit root): its correlation was capped at the record's length, "
                   "so the standard errors may be too small")
    if clipped:
        out.append(f"the sandwich's bandwidth{which(clipped)} reached its limit (what the prewhitening left "
                   "is still strongly correlated): the standard errors may be too small")
    if misfit:
        loud = max(louder or [1.0])
        past = (f"; in contact the residual, its smooth misfit taken out, reads {loud:.2g}x the noise at rest "
                "(a sensor noisier in contact, or a misfit faster than a smooth one), and the errors use that "
                "there") if loud > 1.2 else ""
        out.append(f"the residual{which(misfit)} is slower than the noise at rest before contact allows (a "
                   "misfit, not noise): the standard errors are the measured noise's, as if the model were "
                   f"right, and do not include the misfit{past}")
    if drifting:
        out.append(f"a random-walk drift under the residual{which(drifting)} was included in the standard "
                   "errors; how far a drift wanders is poorly known from one record, so they are approximate")
    white = np.diag(white_covariance(J, r))
    var = np.diag(cov)
    ok = np.isfinite(var) & (var > 0) & np.isfinite(white)
    if np.any(ok):
        n_eff = float(np.min(n * white[ok] / var[ok]))
        if n_eff < MIN_EFFECTIVE_PER_PARAM * p:
            held = "less than one independent sample" if n_eff < 1 else f"about {n_eff:.3g} independent samples"
            out.append(f"the residual holds {held} for {p} parameters (fewer "
                       f"than {MIN_EFFECTIVE_PER_PARAM:g} each): its correlation, and so the standard errors, "
                       "are poorly determined; they are often too small")
    return out


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
