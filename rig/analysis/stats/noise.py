"""The sensor's noise as the instrument delivers it: its level, its spectrum, its quantisation,
and how well the record pins them down.

Everything the analysis says against "the noise" (x the noise, adequate, the criterion, the
bootstrap) rests on this, so it is measured where the record shows the noise alone and never
where a contact estimate merely claims it:

- **the quiet part of the approach**: the force at rest before the first contact estimate, cut
  where it first leaves a straight line by more than its own block-to-block scatter. A first
  estimate is late by a fraction of the depth for a stiffening contact (6 % for F ~ d^1.5, 29 %
  for d^3), and a slow rise before contact (drag, long-range forces) is a signal, not noise:
  neither is allowed into the estimate;
- otherwise the residual's short-lag structure (differences over a few dozen samples keep the
  noise and barely see a smooth misfit: `from_residual`).

The spectrum is an AR(p) process, p chosen by BIC (an averaging ADC or a second-order filter is
not an AR(1)); its integral time scale S(0)/var, in samples, is what a residual as correlated as
the noise shows. A force quantised on a lattice coarser than half the noise is detected: on the
quiet approach such a record sits on a few levels and its spread says little, so the
underlying Gaussian is fitted to the level counts (interval-censored maximum likelihood) and
the quantisation error, q^2/12 once the force moves, is added. `samples` and `spread` say how
well the record pins the level down: the adequacy test (rig.analysis.stats.adequacy) allows for it.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, replace

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from rig.analysis.stats.line import fit_line, off_line

MIN_BASELINE = 200  # samples of a tare (or a rest the record sits at) to measure the noise on
# samples of an approach's own quiet part before contact that are measured rather than the
# residual: a few dozen pin the level to some 12 %, where the residual's short-lag structure on a
# misfitting curve read the misfit (an oocyte record: 0.068 nN at rest with 201 samples before
# contact, 1.42 nN from the residual with 199, and its standard errors 880x apart)
MIN_REST = 32
AT_REST = "the force at rest before contact"
SHORT_LAGS = 64  # the residual's structure is read up to this lag at most
MAX_ORDER = 24  # AR orders tried (a 10-sample boxcar needs about ten)
QUIET_SIGMAS = 4.0  # two blocks in a row this many block-scatters off the line end the quiet part


@dataclass(frozen=True)
class Noise:
    """The force sensor's noise as measured on a record: its level (``std_N``, quantisation
    included), its spectrum (``ar``, and ``scale_samples``: samples per independent value), its
    quantisation (``quantum_N``, ``origin_N``), a slow wander under it (``walk_N2``), where it was
    measured (``source``, ``level_N``, ``samples``) and how sure that is (``spread``)."""

    std_N: float  # what a perfect model's residual shows: the noise with its quantisation error
    scale_samples: float  # integral time scale: samples per independent value (1 for white noise)
    source: str
    ar: tuple[float, ...] = ()  # the spectrum: x_t = sum phi_k x_(t-k) + e_t
    gauss_std_N: float = 0.0  # the noise before quantisation
    quantum_N: float = 0.0  # the quantisation step (0: none that matters)
    origin_N: float = 0.0  # where the quantisation lattice sits
    level_N: float = 0.0  # the force at rest where it was measured
    samples: int = 0  # behind the estimate
    spread: float = 0.0  # standard deviation of ln(std_N) from those samples
    note: str = ""  # the other estimate, when it disagrees
    # a random walk under the noise at rest (its increment variance per sample, N^2; 0: none that
    # the rest shows): a drift, or a noise so slow that over the record it wanders as one
    walk_N2: float = 0.0

    def describe(self) -> str:
        parts = [self.source]
        if self.ar:
            parts.append(f"AR({len(self.ar)}), correlated over {self.scale_samples:.3g} samples")
        if self.quantum_N:
            parts.append(f"quantised in steps of {self.quantum_N:.3g} N")
        if self.walk_N2:
            parts.append(f"a drift wandering {math.sqrt(self.walk_N2 * max(self.samples, 1)):.3g} N over them")
        if self.samples:
            parts.append(f"{self.samples} samples, +/- {100 * self.spread:.2g} %")
        return "; ".join(parts)


# --- where the noise shows alone -------------------------------------------------------------

def quiet_length(y: np.ndarray) -> int:
    """Samples at the start of `y` (the approach before the first contact estimate) where the
    force is a straight line and noise: the line and the block-to-block scatter of the first
    quarter, extended block by block until two blocks in a row leave the line (refitted over the
    quiet part so far) by QUIET_SIGMAS scatters."""
    n = len(y)
    head = max(n // 4, min(n, MIN_BASELINE // 2))
    if head < 32:
        return n
    block = max(8, head // 8)
    i = np.arange(n, dtype=float)

    def scatter(end: int) -> tuple[np.ndarray, float]:
        coef = fit_line(i[:end], y[:end])
        r = y[:end] - (coef[0] * i[:end] + coef[1])
        means = r[: end // block * block].reshape(-1, block).mean(axis=1)
        return coef, float(np.sqrt(np.mean(means ** 2)))

    end = head
    coef, s = scatter(end)
    if s == 0.0:
        return n
    while end + block <= n:
        # the steps until the line is next refitted (where `end` reaches a multiple of four
        # blocks), judged at once: each step's block and the next against the same line
        steps = next((j for j in range(1, 5) if (end + j * block) % (4 * block) == 0), n)
        inside = (n - end) // block  # the blocks from `end` that the record holds whole
        t_max = min(steps, inside)
        k = min(t_max + 1, inside)
        a = end + np.arange(k * block)
        off = np.abs((y[a] - (coef[0] * i[a] + coef[1])).reshape(k, block).mean(axis=1)) > QUIET_SIGMAS * s
        # a block off the line may be the noise's own excursion; two in a row are the force rising
        # (a block with no whole block after it is judged alone)
        nxt = np.append(off[1:], True) if k == t_max else off[1:]
        rising = off[:t_max] & nxt[:t_max]
        if rising.any():
            end += int(np.argmax(rising)) * block
            break
        end += t_max * block
        if end % (4 * block) == 0:
            coef, s_new = scatter(end)
            s = max(s, s_new) if s_new > 0 else s
    return end if n - end >= block else n


# --- the spectrum ----------------------------------------------------------------------------

def autocovariance(x: np.ndarray, lags: int) -> np.ndarray:
    """Biased autocovariance of each row of `x` (or of `x`) at lags 0..lags (by FFT)."""
    x = np.atleast_2d(x)
    x = x - x.mean(axis=1, keepdims=True)
    n = x.shape[1]
    # padded only as far as the lags asked for need: the circular products wrap past them alone
    nfft = 1 << int(np.ceil(np.log2(n + max(lags, 0))))
    f = np.fft.rfft(x, nfft, axis=1)
    return np.fft.irfft(f * np.conj(f), nfft, axis=1)[:, : lags + 1] / n


def ar_fit(gamma: np.ndarray, n: int, max_order: int = MAX_ORDER) -> np.ndarray:
    """AR coefficients from an autocovariance (Levinson-Durbin, the Yule-Walker solution: always
    stationary), the order chosen by BIC as `ar_fit_rows` chooses it. One row's recursion in
    plain floats: on arrays of one row each step cost numpy's call overhead a few times over."""
    g = [float(v) for v in np.asarray(gamma, dtype=float)]
    order = min(max_order, len(g) - 1, max(n // 10, 1))
    if not g[0] > 0:
        return np.zeros(0)
    v = g[0]
    log_n = math.log(n)
    best, best_phi = n * math.log(v), []
    phi: list[float] = []
    for k in range(1, order + 1):
        refl = (g[k] - sum(phi[j] * g[k - 1 - j] for j in range(k - 1))) / v
        phi = [phi[j] - refl * phi[k - 2 - j] for j in range(k - 1)] + [refl]
        v = v * (1.0 - refl * refl)
        # an order counts while every variance up to it stays positive; the first lowest BIC wins
        if not v > 0:
            break
        crit = n * math.log(v) + k * log_n
        if crit < best:
            best, best_phi = crit, phi
    return np.array(best_phi, dtype=float)


def ar_fit_rows(gamma: np.ndarray, n: int, max_order: int = MAX_ORDER) -> list[np.ndarray]:
    """`ar_fit` of each row of autocovariances at once (every row a step of the recursion at a
    time), each row's order chosen by BIC. Schwarz's criterion: AIC's order on a few hundred
    samples of averaged noise overfits, and the spectrum at zero frequency (what the correlation
    time and the whitening rest on) swings."""
    rows = gamma.shape[0]
    order = min(max_order, gamma.shape[1] - 1, max(n // 10, 1))
    ok = gamma[:, 0] > 0
    # the recursion alone in the loop (each order's coefficients and innovation variance kept);
    # the orders' criteria after it, all at once
    phis = np.zeros((order + 1, rows, max(order, 1)))
    vs = np.empty((order + 1, rows))
    vs[0] = np.where(ok, gamma[:, 0], 1.0)
    phi = phis[0]
    for k in range(1, order + 1):
        acc = gamma[:, k] - np.einsum("ij,ij->i", phi[:, :k - 1], gamma[:, k - 1:0:-1])
        refl = acc / vs[k - 1]
        nxt = phis[k]
        if k > 1:
            nxt[:, :k - 1] = phi[:, :k - 1] - refl[:, None] * phi[:, k - 2::-1]
        nxt[:, k - 1] = refl
        vs[k] = vs[k - 1] * (1.0 - refl ** 2)
        phi = nxt
    # an order counts while every variance up to it stays positive; the first lowest BIC wins
    alive = np.logical_and.accumulate(np.vstack([ok[None, :], vs[1:] > 0]), axis=0)
    ks = np.arange(order + 1)[:, None]
    crit = n * np.log(np.where(alive, vs, 1.0)) + ks * math.log(n)
    crit[0] = n * np.log(vs[0])
    best_k = np.argmin(np.where(alive | (ks == 0), crit, np.inf), axis=0)
    return [phis[k, i, :k].copy() for i, k in enumerate(best_k)]


def response(ar: tuple[float, ...] | np.ndarray, nfreq: int) -> np.ndarray:
    """|1 / phi(e^-iw)| at nfreq frequencies from 0 to Nyquist: the AR filter's gain."""
    a = np.concatenate([[1.0], -np.asarray(ar, dtype=float)])
    return 1.0 / np.abs(np.fft.rfft(a, 2 * (nfreq - 1)))


def integral_scale_ar(ar: tuple[float, ...] | np.ndarray) -> float:
    """S(0) / variance of an AR process, in samples."""
    if len(ar) == 0:
        return 1.0
    acf = _ar_acf(ar)
    return float(max(1.0, 1.0 + 2.0 * acf[1:].sum()))


def whiten(r: np.ndarray, ar: tuple[float, ...] | np.ndarray) -> np.ndarray:
    """The residual with the noise's own correlation taken out: e_t = r_t - sum phi_k r_(t-k)
    (each row of `r`, or `r`); what a perfect model leaves is then white."""
    p = len(ar)
    if p == 0:
        return r
    out = r[..., p:].copy()
    n = r.shape[-1]
    for k, c in enumerate(ar, start=1):
        out -= c * r[..., p - k:n - k]
    return out


def variance_scale(ar: tuple[float, ...] | np.ndarray) -> float:
    """1 + 2 sum rho_k^2: how much the correlation widens a sample variance's spread."""
    if len(ar) == 0:
        return 1.0
    acf = _ar_acf(ar)
    return float(1.0 + 2.0 * (acf[1:] ** 2).sum())


def _ar_acf(ar) -> np.ndarray:
    """The AR process's autocorrelation, from its spectrum, to where it has died out (a short
    transform first: most sensors forget within a few dozen samples)."""
    for size in (1 << 11, 1 << 15, 1 << 19):
        acf = np.fft.irfft(response(ar, size + 1) ** 2)
        acf = acf[:size] / acf[0]
        if abs(acf[-1]) < 1e-4:
            break
    return acf


def integral_scale(r: np.ndarray, max_lag: int = 3000) -> float:
    """Samples per independent value: 1 + 2 * the sum of the autocorrelation up to its first
    drop below 0.05 (the residual's; the noise's comes from its AR spectrum)."""
    return float(integral_scales(np.asarray(r, dtype=float)[None, :], max_lag)[0])


def integral_scales(r: np.ndarray, max_lag: int = 3000) -> np.ndarray:
    """`integral_scale` of each row of `r`: the first lags by direct products (a residual as
    white as the noise drops below 0.05 within two or three), the rows that run on in one
    transform."""
    n = r.shape[1]
    if n < 10:
        return np.ones(r.shape[0])
    lag = min(max_lag, n // 4)
    x = r - r.mean(axis=1, keepdims=True)
    head = np.column_stack([np.einsum("ij,ij->i", x[:, k:], x[:, :n - k])
                            for k in range(min(lag, FIRST_LAGS) + 1)])
    out = _scales_from(head / n, lag, n)
    rest = np.isnan(out)
    if rest.any():
        out[rest] = _scales_from(autocovariance(r[rest], lag), lag, n)
    return out


FIRST_LAGS = 8  # the lags `integral_scales` takes directly


def _scales_from(acov: np.ndarray, lag: int, n: int) -> np.ndarray:
    """1 + 2 * the sum of each row's autocorrelation before its first drop below 0.05, from its
    autocovariances at lags 0..lag or fewer; nan for a row that needs lags beyond those given."""
    acf = acov / np.maximum(acov[:, :1], 1e-300)
    below = acf < 0.05
    dropped = below.any(axis=1)
    cut = np.where(dropped, below.argmax(axis=1), acf.shape[1] - 1)
    csum = np.concatenate([np.zeros((len(acf), 1)), np.cumsum(acf[:, 1:], axis=1)], axis=1)
    s = csum[np.arange(len(acf)), np.maximum(cut - 1, 0)]
    out = np.clip(1.0 + 2.0 * s, 1.0, n / 20.0)
    return out if acf.shape[1] > lag else np.where(dropped, out, np.nan)


# --- quantisation ----------------------------------------------------------------------------

def quantum(y: np.ndarray) -> float:
    """The step of the lattice the force sits on, or 0 when it does not sit on a coarse one."""
    y = np.asarray(y, dtype=float)
    d = np.abs(np.diff(y))
    scale = float(np.max(np.abs(y))) or 1.0
    d = d[d > 1e-9 * scale]
    if len(d) < 3 or len(np.unique(y)) > len(y) / 3:
        return 0.0
    q = float(np.min(d))
    k = d / q
    return q if np.mean(np.abs(k - np.round(k)) < 0.02) > 0.99 else 0.0


def gauss_behind_levels(y: np.ndarray, q: float) -> tuple[float, float]:
    """The standard deviation of the Gaussian noise behind a quantised record at rest, and the
    lattice's origin: maximum likelihood on the level counts about a straight line (the spread
    of a few levels says little about it: at rest between two levels a record reads one)."""
    from scipy.optimize import minimize
    from scipy.special import log_ndtr

    origin = float(y[0] - q * np.round(y[0] / q))
    k = np.round((y - origin) / q)
    u = np.linspace(-1.0, 1.0, len(y))

    def nll(p: np.ndarray) -> float:
        m = p[0] + p[1] * u
        s = math.exp(p[2])
        hi, lo = (k + 0.5 - m) / s, (k - 0.5 - m) / s
        # log(Phi(hi) - Phi(lo)), stable on either tail
        upper = np.where(lo > 0, log_ndtr(-lo), log_ndtr(hi))
        lower = np.where(lo > 0, log_ndtr(-hi), log_ndtr(lo))
        return -float(np.sum(upper + np.log1p(-np.exp(np.minimum(lower - upper, -1e-300)))))

    c = np.polyfit(u, k, 1)
    start = np.array([c[1], c[0], math.log(max(float(np.std(k - np.polyval(c, u))), 0.2))])
    res = minimize(nll, start, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-6, "maxiter": 600})
    return q * min(math.exp(float(res.x[2])), 1e3), origin


# --- the two estimates -----------------------------------------------------------------------

def from_baseline(baselines: list[np.ndarray | None]) -> Noise | None:
    """The noise of each record's force at rest (a tare, or the quiet part of its approach:
    `quiet_length`), pooled; None when no record has MIN_REST samples of it (a record keeps its
    baseline only when it has enough: `rig.analysis.trials.data.prepare`)."""
    quiet = [np.asarray(b, dtype=float) for b in baselines if b is not None and len(b) >= MIN_REST]
    if not quiet:
        return None
    parts = [_one_baseline(b) for b in quiet]
    n = sum(p.samples for p in parts)
    if len(parts) == 1:
        return parts[0]
    # several records: one sensor; the level pooled by samples, the spectrum of the longest
    var = sum(p.std_N ** 2 * p.samples for p in parts) / n
    longest = max(parts, key=lambda p: p.samples)
    gauss = math.sqrt(sum(p.gauss_std_N ** 2 * p.samples for p in parts) / n)
    spread = math.sqrt(variance_scale(longest.ar) / (2.0 * n))
    return replace(longest, std_N=math.sqrt(var), gauss_std_N=gauss, samples=n, spread=spread)


def _one_baseline(b: np.ndarray) -> Noise:
    # the same stretch is measured when a record is prepared and again when it is fitted
    key = (len(b), zlib.crc32(b.tobytes()), float(b[0]), float(b[-1]))
    if key not in _MEASURED:
        if len(_MEASURED) > 256:
            _MEASURED.clear()
        _MEASURED[key] = _measure_baseline(b)
    return _MEASURED[key]


_MEASURED: dict[tuple, Noise] = {}


def _measure_baseline(b: np.ndarray) -> Noise:
    n = len(b)
    q = quantum(b)
    u = np.linspace(-1.0, 1.0, n)
    detr = off_line(u, b)
    std = float(np.std(detr))
    gauss, origin = std, 0.0
    if q > 0.5 * std:
        gauss, origin = gauss_behind_levels(b, q)
        std = math.sqrt(gauss ** 2 + q ** 2 / 12.0)
    else:
        q = 0.0
    phi = ar_fit(autocovariance(detr, min(MAX_ORDER, n // 4))[0], n)
    ar = tuple(float(c) for c in phi)
    spread = math.sqrt(variance_scale(ar) / (2.0 * n))
    from rig.analysis.stats.uncertainty import walk_at_rest  # it measures its own noise models from this one

    return Noise(std, integral_scale_ar(ar), AT_REST, ar, gauss, q, origin,
                 float(np.mean(b)), n, spread, walk_N2=walk_at_rest(b, ar) if not q else 0.0)


def from_residual(residuals: list[np.ndarray]) -> Noise:
    """The noise from the residual's short-lag structure, for a record with no force at rest.

    The structure function D(k) = mean (r_(t+k) - r_t)^2 of noise correlated over fewer than K
    samples levels off at twice its variance beyond that; a smooth misfit adds about b k^2. So
    2 var + b k^2 is fitted over K/2..K, and the noise's autocovariance at the shorter lags is
    var - (D(k) - b k^2) / 2, from which its AR spectrum follows. Noise correlated over more
    than K samples cannot be told from a misfit on the residual alone: it is read as misfit."""
    n = sum(len(r) for r in residuals)
    source = "the residual's short-lag structure"
    longest = max(len(r) for r in residuals)
    K = int(np.clip(longest // 40, 8, SHORT_LAGS))
    lags = np.arange(1, K + 1)
    D = structure_function(residuals, K)
    far = lags >= K // 2
    A = np.column_stack([np.ones(far.sum()), lags[far].astype(float) ** 2])
    (_, b), *_ = np.linalg.lstsq(A, D[far], rcond=None)
    b = max(float(b), 0.0)
    var = max(float(np.mean(D[far] - b * lags[far] ** 2)) / 2.0, 0.0)
    if var <= 0.0:
        return Noise(0.0, 1.0, source, samples=n)
    gamma = np.concatenate([[var], var - (D[: K // 2] - b * lags[: K // 2] ** 2) / 2.0])
    phi = ar_fit(gamma, n, max_order=K // 2 - 1)
    ar = tuple(float(x) for x in phi)
    std = math.sqrt(var)
    return Noise(std, integral_scale_ar(ar), source, ar, std, samples=n,
                 spread=math.sqrt(variance_scale(ar) / (2.0 * n)))


def structure_function(residuals: list[np.ndarray], K: int) -> np.ndarray:
    """D(k) = mean (r_(t+k) - r_t)^2 at k = 1..K over the pairs of every residual, the lags of a
    residual taken as rows of one array (a loop over lags cost a curve more than a millisecond);
    nan at a lag no residual is longer than."""
    sums = np.zeros(K)
    counts = np.zeros(K)
    lags = np.arange(1, K + 1)
    for r in residuals:
        r = np.asarray(r, dtype=float)
        m = len(r)
        padded = np.concatenate([r, np.zeros(K)])
        # a few lags at a time keep a long record's rows within some 8 MB
        step = max(1, (1 << 20) // max(m, 1))
        # a lag's pairs end where the residual does: those with the padding, in the last K
        # columns alone, are left out
        lo = max(m - K, 0)
        for k0 in range(1, K + 1, step):
            k1 = min(k0 + step, K + 1)
            d = sliding_window_view(padded, m)[k0:k1] - r
            d[:, lo:] = np.where(lags[k0 - 1:k1 - 1, None] + np.arange(lo, m) < m, d[:, lo:], 0.0)
            sums[k0 - 1:k1 - 1] += np.einsum("ij,ij->i", d, d)
        counts += np.maximum(m - lags, 0)
    with np.errstate(invalid="ignore"):
        return sums / counts


def measure(baselines: list[np.ndarray | None], residuals: list[np.ndarray]) -> Noise:
    """The noise from the quiet approach when the records have one, else from the residual; when
    both exist and disagree beyond their spreads, the note says by how much (a residual far
    noisier at short lags than the approach: the sensor changed in contact, or the model misses
    something fast)."""
    base = from_baseline(baselines)
    if base is None:
        return from_residual(residuals)
    other = from_residual(residuals)
    ratio = other.std_N / base.std_N if base.std_N > 0 else math.inf
    allowed = 3.0 * math.hypot(base.spread, other.spread) + 0.1
    if abs(math.log(max(ratio, 1e-300))) > allowed:
        base = replace(base, note=f"the residual's short-lag structure reads {other.std_N:.3g} N, "
                                  f"{ratio:.2g}x the {base.std_N:.3g} N at rest before contact (a sensor "
                                  "noisier in contact, or a misfit faster than a few dozen samples)")
    return base
