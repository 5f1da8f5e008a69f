"""Hereditary integrals of viscoelastic contact: Lee and Radok while the contact grows, Ting's
construction when it shrinks, for a relaxation modulus written as a constant plus exponentials.

A rigid indenter pushed a depth d into an elastic half-space takes F = E g(d), g the indenter's
geometric function (m^2, `rig.models.contact.geometry_factor`, Poisson's ratio folded in). For a
linear viscoelastic half-space of relaxation modulus E(t) (Pa):

- Lee and Radok (1960), contact radius growing:      F(t) = int_0^t E(t - s) d/ds g(d(s)) ds
- Ting (1966), contact radius shrinking (retract):   F(t) = int_0^t1 E(t - s) d/ds g(d(s)) ds,
  t1(t) the earlier time on the loading side with the same contact radius, found from
                                                     int_t1^t E(t - s) d/ds d(s) ds = 0
  The contact is lost (F = 0) once no t1 >= 0 solves it. With E constant this is d(t1) = d(t):
  the elastic law. For a flat punch (g linear in d) the force equals Lee-Radok's throughout.

T. C. T. Ting, "The contact stresses between a rigid indenter and a viscoelastic half-space",
J. Appl. Mech. 33:845 (1966); E. H. Lee and J. R. M. Radok, J. Appl. Mech. 27:438 (1960); the
same construction for cells: Efremov et al., Sci. Rep. 7:1541 (2017).

Discretisation (product integration): d is linear between samples, and each exponential mode
E_k exp(-r_k t) is convolved exactly by a one-step recursion y[i] = a y[i-1] + J (u[i] - u[i-1]),
a = exp(-r dt), with J the mode's share of the increment as it is spread over the sample:
(1 - a)/(r dt) for a linear one (d itself, and g of a flat punch). g = c d^n of a curved indenter
is not linear within a sample, and against a kernel as sharp as t^-beta at a sample's age that
matters (6.9e-4 of the peak at beta 0.6 with g taken linear, 3.5e-5 with this): its share is
Kummer's M(1, n+1, -r dt) where d starts from zero, and elsewhere the mix of that and the linear
share with the same mean position within the sample (exact as d0/d1 -> 0 and -> 1). The first
touch falls inside a sample: its increment is put in the last fraction of the sample that the
next step's speed gives, so the force is continuous as a fitted contact point crosses samples.
Ting's t1 is found on the loading side by bisection over samples (the integral falls as t1 moves
later while d grows) and within its sample by Newton's method on the exact integral, so the force
is continuous in the parameters. Rows where the depth is below its running maximum but the
integral is still positive (a noisy hold) keep Lee-Radok: there the contact has not receded.
With more than one maximum of the depth the history before t1 is taken as the depth itself
(Ting's single-maximum solution applied at each later maximum): exact for approach-retract and
ramp-hold-retract, an approximation for repeated cycles.

Measured against adaptive quadrature of the exact history (tests/test_viscoelastic.py): within
3.8e-5 of the peak force for paraboloid, sphere, cone and flat punch, SLS and power law (beta 0.2, 0.6),
ramp-hold, approach-retract and ramp-hold-retract.
"""

from __future__ import annotations

import numpy as np

__all__ = ["hereditary_force", "mode_recursions"]


def mode_recursions(inputs: np.ndarray, rates_per_s: np.ndarray, dt_s: float) -> np.ndarray:
    """Y[k, i] = sum_{l <= i} a_k^(i - l) inputs[k, l], a_k = exp(-r_k dt): K recursions at once,
    by the doubling scan of `rig.models.core.linear_recursion` (log2(n) vector passes instead of
    a Python loop)."""
    a = np.exp(-np.maximum(np.asarray(rates_per_s, dtype=float) * dt_s, 0.0))
    order = np.argsort(-a, kind="stable")  # slowest first: the modes still live are a leading block
    y = np.array(inputs, dtype=float)[order]
    k, ak = 1, a[order]
    n = y.shape[1]
    while k < n:
        # past a^k < 1e-18 older increments no longer reach a float's digits
        live = int(np.count_nonzero(ak > 1e-18))
        if live == 0:
            break
        y[:live, k:] += ak[:live, None] * y[:live, :-k]
        k, ak = 2 * k, ak * ak
    out = np.empty_like(y)
    out[order] = y
    return out


def _linear_weight(x: np.ndarray) -> np.ndarray:
    """int_0^1 exp(-x (1 - u)) du = (1 - e^-x) / x: a mode's share of an increment spread evenly
    over the sample before (x = r dt)."""
    xs = np.maximum(x, 1e-300)
    return np.where(x < 1e-12, 1.0 - 0.5 * x, -np.expm1(-xs) / xs)


def _power_weight(x: np.ndarray, n: float) -> np.ndarray:
    """int_0^1 exp(-x (1 - u)) d(u^n) = M(1, n + 1, -x) (Kummer's function): the same share for an
    increment that grows as u^n over the sample, as g = c d^n does from the first touch."""
    from scipy.special import hyp1f1  # only the models of curved contacts need it

    return hyp1f1(1.0, n + 1.0, -np.asarray(x, dtype=float))


def _profile_mean(d0: np.ndarray, d1: np.ndarray, n: float) -> np.ndarray:
    """Where within a sample (0 to 1) an increment of d^n falls on average when d grows linearly
    from d0 to d1 > d0: 1/2 for d0 = d1, n/(n+1) from d0 = 0."""
    rho = np.clip(d0 / np.where(d1 > 0, d1, 1.0), 0.0, 1.0)
    eps = 1.0 - rho
    close = eps < 1e-6  # the series about rho = 1 keeps the digits the closed form cancels
    lr = np.log(np.where(rho > 0, rho, 1.0))
    one_minus_rn1 = np.where(rho > 0, -np.expm1((n + 1.0) * lr), 1.0)
    one_minus_rn = np.where(rho > 0, -np.expm1(n * lr), 1.0)
    safe = np.where(close, 1.0, eps)
    closed = (1.0 - one_minus_rn1 / ((n + 1.0) * safe)) / np.where(close, 1.0, one_minus_rn)
    series = 0.5 + (n - 1.0) * eps / 12.0
    return np.where(close, series, closed)


def hereditary_force(d_m: np.ndarray, g_m2: np.ndarray, dt_s: float, e_const_Pa: float,
                     rates_per_s: np.ndarray, weights_Pa: np.ndarray, exponent: float = 1.0) -> np.ndarray:
    """Force (N) of a rigid indenter at depth `d_m` (>= 0, uniform samples `dt_s` apart) into a
    half-space of relaxation modulus E(t) = e_const + sum_k w_k exp(-r_k t), `g_m2` = g(d) the
    indenter's geometric function at each depth (~ d^exponent near the first touch): Lee-Radok
    while the contact grows, Ting's t1 construction while it shrinks, zero once it is lost."""
    d = np.concatenate([[0.0], np.asarray(d_m, dtype=float)])  # at rest one sample before
    g = np.concatenate([[0.0], np.asarray(g_m2, dtype=float)])
    n = len(d)
    r = np.asarray(rates_per_s, dtype=float)
    w = np.asarray(weights_Pa, dtype=float)
    x = r * dt_s
    step_d_all = np.diff(d, prepend=0.0)
    step_g_all = np.diff(g, prepend=0.0)
    lin = _linear_weight(x)
    in_d = lin[:, None] * step_d_all[None, :]
    in_g = lin[:, None] * step_g_all[None, :]
    # The first touch falls inside a sample: d = 0 before it and rising after, at the speed of
    # the next step (a ramp's), so the increment arrives in the last fraction f of the sample.
    # Everything here is continuous in the contact point, which a fit moves across samples.
    touch = np.flatnonzero((d[:-1] <= 0.0) & (d[1:] > 0.0)) + 1
    nxt = np.minimum(touch + 1, n - 1)
    ahead = d[nxt] - d[touch]
    frac = np.where((nxt > touch) & (ahead > d[touch]), d[touch] / np.where(ahead > 0, ahead, 1.0), 1.0)
    in_d[:, touch] = _linear_weight(np.outer(x, frac)) * step_d_all[touch]
    if exponent != 1.0 and len(r):
        # g grows as d^n, not linearly, within a sample: exact for the sample of the first touch
        # (from d = 0), elsewhere the profile with the same mean position within the sample
        grow = step_d_all > 0
        grow[touch] = False
        mean = _profile_mean(d[np.maximum(np.arange(n) - 1, 0)], d, exponent)
        lam = np.where(grow, (mean - 0.5) / (exponent / (exponent + 1.0) - 0.5), 0.0)
        curved = _power_weight(x, exponent)
        in_g = in_g + (curved - lin)[:, None] * (lam * step_g_all)[None, :]
        in_g[:, touch] = _power_weight(np.outer(x, frac), exponent) * step_g_all[touch]
    else:
        in_g[:, touch] = _linear_weight(np.outer(x, frac)) * step_g_all[touch]
    yd = mode_recursions(in_d, r, dt_s)
    yg = mode_recursions(in_g, r, dt_s)
    s_d = e_const_Pa * d + w @ yd  # int_0^t E(t - s) dd: Ting's integral from the start
    force = e_const_Pa * g + w @ yg  # Lee-Radok
    peak = np.maximum.accumulate(d)
    at_peak = np.maximum.accumulate(np.where(d >= peak, np.arange(n), 0))
    rows = np.flatnonzero(d < peak)
    if len(rows) == 0:
        return force[1:]

    def h(j: np.ndarray, i: np.ndarray) -> np.ndarray:
        """int_{t_j}^{t_i} E(t_i - s) dd(s) for pairs of samples."""
        decay = np.exp(-np.outer(x, i - j))
        return s_d[i] - e_const_Pa * d[j] - np.einsum("k,ki,ki->i", w, decay, yd[:, j])

    jm = at_peak[rows]
    receding = h(jm, rows) < 0.0
    lost = receding & (s_d[rows] <= 0.0)
    force[rows[lost]] = 0.0
    keep = receding & ~lost
    i, hi = rows[keep], jm[keep]
    if len(i) == 0:
        return force[1:]
    lo = np.zeros_like(i)  # h(0) = s_d > 0 and h(hi) < 0: a crossing lies between
    while np.any(hi - lo > 1):
        mid = (lo + hi) // 2
        up = h(mid, i) >= 0.0
        lo, hi = np.where(up, mid, lo), np.where(up, hi, mid)
    h_lo, h_hi = h(lo, i), h(hi, i)
    step_d = d[lo + 1] - d[lo]
    step_g = g[lo + 1] - g[lo]
    span = (i - lo) * dt_s  # t_i - t_lo

    def partial(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per unit rate of u over the interval: int_{t_lo}^{t_lo + theta dt} of the modes'
        part of E(t_i - s) ds, and E(t_i - t_lo - theta dt)."""
        left = span - theta * dt_s
        near = np.exp(-np.outer(r, left))
        q = w @ (near * -np.expm1(-np.outer(r, theta * dt_s)) / np.maximum(r, 1e-300)[:, None])
        return q, e_const_Pa + w @ near

    # Newton on theta from the straight line between the two samples; the exact integral keeps
    # the force continuous as t1 moves across a sample
    theta = np.clip(h_lo / np.where(h_lo > h_hi, h_lo - h_hi, 1.0), 0.0, 1.0)
    rate_d = step_d / dt_s
    for _ in range(4):
        q, e_at = partial(theta)
        resid = h_lo - rate_d * (e_const_Pa * theta * dt_s + q)
        slope = rate_d * dt_s * e_at
        theta = np.clip(theta + resid / np.where(slope > 0, slope, np.inf), 0.0, 1.0)
    q, _ = partial(theta)
    decay = np.exp(-np.outer(x, i - lo))
    force[i] = (e_const_Pa * (g[lo] + theta * step_g) + np.einsum("k,ki,ki->i", w, decay, yg[:, lo])
                + step_g / dt_s * q)
    return force[1:]
