"""The commonest AFM fit, an elastic contact from a fitted contact point over the record's
zero, F = E g(max(x - x_c, 0)) + offset, solved with sums instead of the general machinery.

It is the variable projection of `rig.analysis.fitting.separable` (the same scan of the contact point's
range, the same Brent refinement, so the same valley and the same optimum), with each point's
two-column least squares done from six sums, and the last digits settled by Gauss-Newton steps
on the exact Jacobian (E and the offset enter linearly; the contact point through g', by a
central difference of g alone). A map of thousands of curves pays for each fit a few hundred
numpy operations instead of some fifteen thousand Python calls; the optimum is the one the
general path reaches (`tests/test_contact_fit.py` holds the two together).

Only a model the lean prediction (`rig.analysis.fitting.lean`) serves qualifies, on one record, with
parameters scaled linearly into the fit variables; anything else, or an optimum on a bound of
E or the offset, is handed back (None) to the general path.
"""

from __future__ import annotations

import numpy as np

from rig.analysis.fitting.separable import Solution, _minimise

__all__ = ["solve"]

STEPS = 8  # Gauss-Newton steps at most; two or three settle a curve at the noise
BRENT_TOL = 1e-6


def solve(predict, resid, names: list[str], to_si, z0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
          x_m: np.ndarray, force_N: np.ndarray, inv_F: float) -> Solution | None:
    """The least-squares optimum in the fit variables z (as `separable.solve` finds it, with the
    Jacobian there), or None when this model or optimum is not of the form solved here.

    `predict` is the lean prediction (its `parts` name the contact point, the modulus and the
    offset, and give g), `resid(z)` the residual as the general path computes it, `to_si` the
    fit variables' map to SI, `inv_F` the force scale's inverse."""
    parts = getattr(predict, "parts", None)
    if parts is None:
        return None
    x_c, modulus, offset, g, law = parts
    try:
        k, e, o = names.index(x_c), names.index(modulus), names.index(offset)
    except ValueError:
        return None
    if len(names) != 3:
        return None
    scale = to_si(np.ones(3))
    probe = np.array([0.37, -1.3, 2.9])
    if not np.array_equal(to_si(probe), probe * scale) or not np.all(np.isfinite(scale)):
        return None  # the fit variables are not the SI values over fixed scales
    s_k, s_e, s_o = scale[k], scale[e], scale[o]
    x = np.asarray(x_m, dtype=float)
    t = np.asarray(force_N, dtype=float) * inv_F
    n = len(t)
    if n < 4 or not (np.all(np.isfinite(x)) and np.all(np.isfinite(t))):
        return None
    c = s_o * inv_F  # the offset's column: a constant
    sum_t, sum_tt = float(t.sum()), float(t @ t)
    lo_e, hi_e, lo_o, hi_o = lo[e], hi[e], lo[o], hi[o]

    power = _power(law)

    def column(z_k: float) -> np.ndarray:
        # a power law's column in fewer passes than its law's general form (the same to rounding):
        # the search and the steps take some thirty a curve
        d = np.maximum(x - z_k * s_k, 0.0)
        return (_powered(d, *power) if power else g(d)) * (s_e * inv_F)

    def coefficients(a: np.ndarray) -> tuple[float, float]:
        """The two-column least squares, bounded as `separable._bounded_lstsq` bounds it."""
        sa, saa, sat = float(a.sum()), float(a @ a), float(a @ t)
        var = saa - sa * sa / n
        ze = (sat - sa * sum_t / n) / var if var > 0 else 0.0
        zo = (sum_t - ze * sa) / (n * c)
        if lo_e <= ze <= hi_e and lo_o <= zo <= hi_o:
            return ze, zo
        if not lo_e <= ze <= hi_e:
            ze = min(max(ze, lo_e), hi_e)
            zo = min(max((sum_t - ze * sa) / (n * c), lo_o), hi_o)
        else:
            zo = min(max(zo, lo_o), hi_o)
            ze = min(max((sat - zo * c * sa) / saa, lo_e), hi_e) if saa > 0 else 0.0
        return ze, zo

    def cost(z_k: float) -> float:
        a = column(z_k)
        ze, zo = coefficients(a)
        r = a * ze + (zo * c - t)
        return 0.5 * float(r @ r)

    def costs(grid: np.ndarray) -> np.ndarray:
        # every point of the scan at once from its sums; a point whose free solution leaves the
        # bounds is solved as the search solves it. The scan only picks the valley, and a power
        # law's columns are taken in fewer passes (the same to rounding)
        D = np.maximum(x[None, :] - (grid * s_k)[:, None], 0.0)
        A = _powered(D, *power) * (s_e * inv_F) if power else g(D) * (s_e * inv_F)
        sa, saa, sat = A.sum(axis=1), np.einsum("pn,pn->p", A, A), A @ t
        with np.errstate(all="ignore"):
            var = saa - sa * sa / n
            ze = (sat - sa * sum_t / n) / var
            zo = (sum_t - ze * sa) / (n * c)
            out = 0.5 * np.maximum(sum_tt - sum_t * sum_t / n - ze * (sat - sa * sum_t / n), 0.0)
        bad = ~np.isfinite(out) | (ze < lo_e) | (ze > hi_e) | (zo < lo_o) | (zo > hi_o) | ~(var > 0)
        for i in np.flatnonzero(bad):
            out[i] = cost(float(grid[i]))
        return out

    # the valley to a millionth: Gauss-Newton, below, takes the last digits in a step or two
    z_k = _minimise(cost, float(lo[k]), float(hi[k]), costs, tol=BRENT_TOL)
    z = np.array(z0, dtype=float)
    z[k] = z_k
    z[e], z[o] = coefficients(column(z_k))
    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    if not all(z[j] - lo[j] > 1e-6 * span[j] and hi[j] - z[j] > 1e-6 * span[j] for j in (e, o)):
        return None  # E or the offset on a bound: the general path says what that means

    def residual(z: np.ndarray) -> np.ndarray:
        return column(z[k]) * z[e] + (z[o] * c - t)

    def jacobian(z: np.ndarray) -> np.ndarray:
        # the same central difference the general path takes in the contact point (a sample
        # entering contact makes the cost's slope kink there); E and the offset are exact
        h = 6e-6 * max(1.0, abs(z[k]))
        J = np.empty((n, 3))
        J[:, e] = column(z[k])
        J[:, o] = c
        J[:, k] = (column(z[k] + h) - column(z[k] - h)) * (z[e] / (2 * h))
        return J

    r = residual(z)
    cost_z = 0.5 * float(r @ r)
    J = jacobian(z)
    nfev = 2 * 48
    for _ in range(STEPS):
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        trial = np.clip(z + step, lo, hi)
        r_new = residual(trial)
        cost_new = 0.5 * float(r_new @ r_new)
        nfev += 1
        if not cost_new <= cost_z * (1.0 + 1e-12):
            break
        moved = np.max(np.abs(trial - z) / np.maximum(1.0, np.abs(z)))
        z, r, cost_z = trial, r_new, cost_new
        J = jacobian(z)
        if moved < 1e-12:
            break
    if not lo[k] < z[k] < hi[k]:
        return None
    # the residual as the general path computes it (the model's own prediction), checked
    # against the sums' combination: a clamp or a law that does not broadcast would show here
    fun = resid(z)
    if not np.allclose(fun, r, rtol=1e-9, atol=1e-12 * max(1.0, float(np.abs(t).max()))):
        return None
    return Solution(z, 0.5 * float(fun @ fun), fun, J, nfev)



def _power(law) -> tuple[float, float] | None:
    """(c, p) of an elastic contact whose force per unit modulus is c d^p (rig.models.contact)."""
    from rig.models.contact import power_law

    ind, nu = getattr(law, "indenter", None), getattr(law, "poisson", None)
    if ind is None or nu is None:
        return None
    got = power_law(ind)
    return None if got is None else (got[0] / (1.0 - nu * nu), got[1])


def _powered(d: np.ndarray, c: float, p: float) -> np.ndarray:
    if p == 1.5:
        out = np.sqrt(d)
        out *= d
    elif p == 2.0:
        out = d * d
    elif p == 1.0:
        out = d.copy()
    else:
        out = d ** p
    out *= c
    return out
