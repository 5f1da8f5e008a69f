"""Models linear in all their parameters but one, fitted by variable projection.

An elastic contact law over a baseline, F = E g(x - x_c) + offset, is linear in E and the
offset once the contact point x_c is fixed: for each x_c, linear least squares gives the best
E and offset in one step, and the fit is left with a cost of one variable (Golub and Pereyra,
1973). That cost is scanned across the contact point's whole range and refined around its
lowest point, so the result is the global least-squares optimum: a local solver started from a
guessed contact point can settle in a neighbouring valley. The whole fit is numpy: a user
fitting one curve does not pay for importing a general solver.

A model qualifies when every drive and sensor effect is flagged `linear` (its output is its
one parameter times a term that does not depend on it), nothing lags, branches or waits, and
at most one parameter sits in the geometry. The linear combination is checked against the
model's own prediction at the optimum; anything unexpected (a bound reached, a clamp that
bites) hands the fit back to the general solver.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rig.models.core import Model

GRID = 48  # cost evaluations across the contact point's range before refining
GOLDEN = 0.5 * (3.0 - 5.0 ** 0.5)


@dataclass
class Solution:
    """What a least-squares solver leaves: the fit variables, half the sum of squares, the
    residual and its Jacobian there, and how many residual evaluations it took."""

    x: np.ndarray
    cost: float
    fun: np.ndarray
    jac: np.ndarray | None
    nfev: int


def split(model: Model) -> tuple[int | None, list[int]] | None:
    """(index of the one nonlinear parameter or None, indices of the linear ones), or None when
    the model is not of this form."""
    stages = {e.stage for e in model.effects}
    if stages - {"geometry", "drive", "sensor"} or any(e.needs_force for e in model.effects):
        return None
    if model.records > 1 and model.has_record_params:
        return None  # a contact point per record: more than one nonlinear parameter
    names = model.param_names
    linear, nonlinear = [], []
    for e in model.effects:
        idx = [names.index(p.name) for p in e.params]
        if e.stage == "geometry":
            nonlinear += idx
        elif e.linear and len(idx) == 1:
            if e.stage == "drive" and e.params[0].lo < 0:
                return None  # a drive term bounded below zero could make the tissue pull: the clamp bites
            linear += idx
        else:
            return None
    if len(set(nonlinear)) > 1 or set(linear) & set(nonlinear) or len(set(linear)) != len(linear):
        return None
    return (nonlinear[0] if nonlinear else None), linear


def solve(resid_at, predict_z, z0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
          target: np.ndarray, form: tuple[int | None, list[int]], predict_many=None) -> Solution | None:
    """The least-squares optimum in the fit variables z.

    `predict_z(z)` is the model's prediction (in the record's force scale, all trials joined),
    `target` the measurement in the same scale, `resid_at(z)` their difference as the general
    solver sees it. `predict_many(zs)`, where given, is `predict_z` of every row of `zs` at
    once (one row of predictions each, or None where it cannot): the scan's columns are then
    computed in one pass. None when the optimum is not an interior point of the linear form."""
    k_nl, lin = form
    nfev = 0
    fixed: dict[int, np.ndarray] = {}  # columns the nonlinear variable does not move (a record's zero)

    def column(j: int, z_nl: float | None) -> np.ndarray:
        nonlocal nfev
        z = np.zeros_like(z0)
        if k_nl is not None:
            z[k_nl] = z_nl
        z[j] = 1.0
        nfev += 1
        return predict_z(z)

    if k_nl is not None:
        # a column equal at both ends of the nonlinear variable's range is taken as not moving
        # with it: computed once, not at every point of the search
        ends = [float(lo[k_nl]) + 1e-6 * (hi[k_nl] - lo[k_nl]), float(hi[k_nl]) - 1e-6 * (hi[k_nl] - lo[k_nl])]
        if np.all(np.isfinite(ends)):
            for j in lin:
                a, b = column(j, ends[0]), column(j, ends[1])
                if np.array_equal(a, b) and np.array_equal(a, column(j, 0.5 * (ends[0] + ends[1]))):
                    fixed[j] = a

    def columns(z_nl: float | None) -> np.ndarray:
        return np.column_stack([fixed[j] if j in fixed else column(j, z_nl) for j in lin])

    def linear_part(z_nl: float | None) -> tuple[np.ndarray, float, np.ndarray]:
        A = columns(z_nl)
        coef = _bounded_lstsq(A, target, lo[lin], hi[lin])
        combined = A @ coef
        r = combined - target
        return coef, 0.5 * float(r @ r), combined

    def grid_costs(grid: np.ndarray) -> np.ndarray:
        """The cost at every point of the scan: its moving columns from one call of
        `predict_many`, checked against `predict_z` at both ends (a model whose terms do not
        broadcast over many contact points falls back to one point at a time)."""
        nonlocal nfev
        moving = [j for j in lin if j not in fixed]
        stacks = {}
        if predict_many is not None and moving:
            for j in moving:
                zs = np.zeros((len(grid), len(z0)))
                zs[:, k_nl] = grid
                zs[:, j] = 1.0
                got = predict_many(zs)
                if got is None or got.shape != (len(grid), len(target)) or not (
                        np.array_equal(got[0], column(j, float(grid[0])))
                        and np.array_equal(got[-1], column(j, float(grid[-1])))):
                    stacks = {}
                    break
                nfev += len(grid) - 2  # the two ends were counted as they were checked
                stacks[j] = got
        if not stacks:
            return np.array([linear_part(float(c))[1] for c in grid])
        # every point's linear least squares at once, by its normal equations on scaled
        # columns: the scan only picks the valley, and its lowest point's cost, which Brent
        # starts from, is then taken exactly as the search takes it
        cols = [fixed[j] if j in fixed else stacks[j] for j in lin]  # (samples,) or (points, samples)

        def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            if a.ndim == 2 and b.ndim == 2:
                return np.einsum("pn,pn->p", a, b)
            return a @ b if a.ndim == 2 else (b @ a if b.ndim == 2 else np.full(len(grid), float(a @ b)))

        k = len(cols)
        G = np.empty((len(grid), k, k))
        for a in range(k):
            for b in range(a, k):
                G[:, a, b] = G[:, b, a] = dot(cols[a], cols[b])
        rhs = np.stack([dot(c, target) for c in cols], axis=1)
        norm = np.sqrt(np.einsum("pkk->pk", G))
        norm[norm == 0.0] = 1.0
        with np.errstate(all="ignore"):
            try:
                coef = np.linalg.solve(G / (norm[:, :, None] * norm[:, None, :]),
                                       (rhs / norm)[..., None])[..., 0] / norm
            except np.linalg.LinAlgError:
                return np.array([linear_part(float(c))[1] for c in grid])
            r = -target
            for a in range(k):
                r = r + (coef[:, a, None] * cols[a] if cols[a].ndim == 2 else np.outer(coef[:, a], cols[a]))
            out = 0.5 * np.einsum("pn,pn->p", r, r)
        # a point whose free solution leaves the bounds (or is singular) is solved as the search does
        bad = ~np.isfinite(out) | np.any((coef < lo[lin]) | (coef > hi[lin]) | ~np.isfinite(coef), axis=1)
        for i in np.flatnonzero(bad):
            out[i] = linear_part(float(grid[i]))[1]
        return out

    z_nl = None if k_nl is None else _minimise(lambda c: linear_part(c)[1], float(lo[k_nl]), float(hi[k_nl]),
                                               grid_costs)
    coef, _, combined = linear_part(z_nl)
    z = z0.copy()
    z[lin] = coef
    if k_nl is not None:
        z[k_nl] = z_nl
    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    inside = np.all((z[lin] - lo[lin] > 1e-6 * span[lin]) & (hi[lin] - z[lin] > 1e-6 * span[lin]))
    r = resid_at(z)
    nfev += 1
    # the columns' combination is the model only when no clamp or bound intervened
    scale = max(1.0, float(np.abs(target).max()))
    if not inside or not np.allclose(r + target, combined, rtol=1e-9, atol=1e-12 * scale):
        return None
    return Solution(z, 0.5 * float(r @ r), r, None, nfev)


def _bounded_lstsq(A: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Least squares with each coefficient kept within its bounds: a coefficient the free
    solution pushes out is held at the bound it crossed and the rest solved again (exact for the
    one or two coefficients these models have, where at most one bound is active)."""
    coef = np.linalg.lstsq(A, b, rcond=None)[0]
    out = (coef < lo) | (coef > hi)
    if not np.any(out):
        return coef
    fixed = np.clip(coef, lo, hi)
    free = ~out
    if np.any(free):
        rest = b - A[:, out] @ fixed[out]
        fixed[free] = np.clip(np.linalg.lstsq(A[:, free], rest, rcond=None)[0], lo[free], hi[free])
    return fixed


def _minimise(cost, lo: float, hi: float, costs=None, tol: float = 1e-10) -> float:
    """The lowest point of a cost of one variable on [lo, hi]: a grid finds the valley of the
    global minimum, golden-section search with parabolic steps (Brent) refines it. `costs`, where
    given, is the cost at every point of the grid at once."""
    lo_in = lo + 1e-6 * (hi - lo)
    hi_in = hi - 1e-6 * (hi - lo)
    grid = np.linspace(lo_in, hi_in, GRID)
    if costs is None:
        values = np.array([cost(c) for c in grid])
        i = int(np.argmin(values))
    else:
        values = costs(grid)
        i = int(np.argmin(values))
        values[i] = cost(grid[i])
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, GRID - 1)]
    return _brent(cost, a, b, grid[i], values[i], tol)


def _brent(f, a: float, b: float, x: float, fx: float, tol: float = 1e-10, iters: int = 100) -> float:
    """Brent's minimisation on [a, b] from the interior point x (Numerical Recipes, 10.2)."""
    w = v = x
    fw = fv = fx
    d = e = 0.0
    for _ in range(iters):
        m = 0.5 * (a + b)
        tol1 = tol * abs(x) + 1e-12
        tol2 = 2.0 * tol1
        if abs(x - m) <= tol2 - 0.5 * (b - a):
            break
        parabolic = False
        if abs(e) > tol1:
            r = (x - w) * (fx - fv)
            q = (x - v) * (fx - fw)
            p = (x - v) * q - (x - w) * r
            q = 2.0 * (q - r)
            if q > 0:
                p = -p
            q = abs(q)
            if abs(p) < abs(0.5 * q * e) and q * (a - x) < p < q * (b - x):
                e, d = d, p / q
                u = x + d
                if u - a < tol2 or b - u < tol2:
                    d = tol1 if m >= x else -tol1
                parabolic = True
        if not parabolic:
            e = (a if x >= m else b) - x
            d = GOLDEN * e
        u = x + (d if abs(d) >= tol1 else (tol1 if d > 0 else -tol1))
        fu = f(u)
        if fu <= fx:
            if u >= x:
                a = x
            else:
                b = x
            v, fv, w, fw, x, fx = w, fw, x, fx, u, fu
        else:
            if u < x:
                a = u
            else:
                b = u
            if fu <= fw or w == x:
                v, fv, w, fw = w, fw, u, fu
            elif fu <= fv or v in (x, w):
                v, fv = u, fu
    return x
