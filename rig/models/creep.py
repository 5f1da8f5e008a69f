"""Creep form: where a controller held the force, the model is solved for the indentation.

On samples where the force was held (the rig's ramp_force and hold_force, an AFM's
creep-compliance pause) the force is the input and the probe's position is what responds, so
the model predicts the position x(t) from the measured force: x with tissue(x) = the force
the tissue carried. The rest of the record stays as it is (x measured, the force predicted),
and one evaluation runs over the whole record, so the lag's state carries from a ramp into
the hold that follows it and back out.

The force the tissue carried is the reading with the sensor's own terms taken off (offset,
drift, friction: from the record's own motion) and the delay undone (the reading moved back
by it). Frame compliance is explicit here: the tissue sees x - f / k_frame with f that force.

The position on held samples is found by Newton's method, all held samples at once. The
step is exact for drive -> lag (+ a parallel branch filtering the rate): the drive acts
sample by sample (its slopes in x and v, by differences), the velocity on held samples is the
second-order backward difference of x (causal: the model's response to the force so far),
each lag a two-term recursion, so multiplied through by the lags' denominators the step is
one sparse banded solve. A branch of another form is left out of the step; convergence is
checked on the equation itself. The last solution on the same motion is kept as the next
start: a fit evaluates the model many times at nearly the same parameters.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rig.models.frame import NotConverged, backtrack

HELD_RTOL = 1e-10  # of the held force's own peak
HELD_MAX_ITER = 40


@dataclass
class HeldSolution:
    """The positions on held samples that make the model carry the measured force, and how well the force
    equation holds there (its largest error)."""

    x_m: np.ndarray  # the position on held samples
    residual_N: float  # how well the force equation holds there (largest error)


def backward_velocity(x: np.ndarray, dt: float) -> np.ndarray:
    """dx/dt by the second-order backward difference (first order at the first two samples)."""
    v = np.empty_like(x)
    v[0] = 0.0
    if len(x) > 1:
        v[1] = (x[1] - x[0]) / dt
    if len(x) > 2:
        v[2:] = (3.0 * x[2:] - 4.0 * x[1:-1] + x[:-2]) / (2.0 * dt)
    return v


def _shift(idx: np.ndarray, k: int) -> np.ndarray:
    """Whether held sample j's k-th predecessor in time is also held (a position in `idx`, j - k)."""
    ok = np.zeros(len(idx), dtype=bool)
    if k < len(idx):
        ok[k:] = idx[k:] - idx[:-k] == k
    return ok


def _poly_matrix(coef, idx: np.ndarray):
    """sum_k coef[k] S^k on the held samples, S the one-sample delay within runs of held samples."""
    from scipy import sparse

    n = len(idx)
    out = sparse.csr_matrix((n, n))
    for k, c in enumerate(coef):
        if c == 0.0:
            continue
        if k == 0:
            out = out + sparse.identity(n, format="csr") * c
            continue
        ok = _shift(idx, k)
        rows = np.flatnonzero(ok)
        out = out + sparse.csr_matrix((np.full(len(rows), c), (rows, rows - k)), shape=(n, n))
    return out


def solve_held(tissue: Callable[[np.ndarray], np.ndarray], drive_slopes: Callable,
               x: np.ndarray, held: np.ndarray, target_N: np.ndarray, dt: float,
               lag: tuple[float, float, float], branch: tuple[float, float, float] | None,
               start: np.ndarray | None) -> HeldSolution:
    """The positions z on the `held` samples with tissue(x with z there)[held] = target_N[held].

    `tissue(x_full)` gives the tissue force over the record for positions `x_full`;
    `drive_slopes(x_full)` the drive's slopes in position and rate on the held samples, and
    whether each is in contact; `lag` and `branch` are (b0, b1, a) of y[i] = a y[i-1] + b0 u[i]
    + b1 u[i-1] (the branch's u the rate). `start`: the last solution, if any."""
    from scipy.sparse.linalg import spsolve

    idx = np.flatnonzero(held)
    goal = target_N[idx]
    scale = max(float(np.max(np.abs(goal))), 1e-300)
    z = x[idx].copy()
    if start is not None and len(start) == len(idx):
        z = start.copy()

    def residual(zz: np.ndarray) -> np.ndarray:
        xf = x.copy()
        xf[idx] = zz
        return tissue(xf)[idx] - goal

    r = residual(z)
    norm = float(np.max(np.abs(r)))
    if start is not None and len(start) == len(idx):
        cold = x[idx].copy()
        r_cold = residual(cold)
        if float(np.max(np.abs(r_cold))) < norm:
            z, r, norm = cold, r_cold, float(np.max(np.abs(r_cold)))
    b0, b1, a = lag
    la, lb = (1.0, -a), (b0, b1)
    ba, bb = ((1.0, -branch[2]), (branch[0], branch[1])) if branch else ((1.0,), (0.0,))
    La, Lb = _poly_matrix(la, idx), _poly_matrix(lb, idx)
    Ba, Bb = _poly_matrix(ba, idx), _poly_matrix(bb, idx)
    # the backward difference on held samples (as `backward_velocity`): a predecessor that is not
    # held is measured, fixed
    Dv = _poly_matrix((1.5 / dt, -2.0 / dt, 0.5 / dt), idx)
    from scipy import sparse

    left = La @ Ba
    for _ in range(HELD_MAX_ITER):
        if norm <= HELD_RTOL * scale:
            break
        xf = x.copy()
        xf[idx] = z
        alpha, beta, contact = drive_slopes(xf)
        # out of contact the drive has no slope: the step is taken as if at the record's secant
        # stiffness there, so that Newton moves the position back into contact
        floor = 1e-3 * max(float(np.max(np.abs(alpha))), scale / max(float(np.max(np.abs(x))), 1e-300))
        alpha = np.where(contact, alpha, floor)
        M = sparse.diags(alpha) + sparse.diags(beta) @ Dv
        A = Lb @ Ba @ M
        if branch:
            A = A + Bb @ La @ sparse.diags(contact.astype(float)) @ Dv
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                step = spsolve(A.tocsc(), -(left @ r))
        except (RuntimeError, ValueError):
            break
        if not np.all(np.isfinite(step)):
            break
        found = backtrack(lambda s, z=z: residual(z + s), step, norm)
        if found is None:
            break
        step, r = found
        z, norm = z + step, float(np.max(np.abs(r)))
    if norm > HELD_RTOL * scale * 1e3:
        warnings.warn(NotConverged(f"creep form: the held force equation holds only to {norm:.3g} N", norm),
                      stacklevel=4)
        if norm > 1e-3 * scale:
            # no position found: never the measured one (where the solve starts), which would read
            # as a perfect prediction and draw a fit to parameters where the solve fails
            return HeldSolution(np.full_like(z, np.nan), norm)
    return HeldSolution(z, norm)
