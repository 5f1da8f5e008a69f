"""Frame compliance: the tissue sees x - f / k_frame, and f depends on what it sees.

The force is found by Newton's method over the whole record. Substituting the last force (a
fixed point) diverges once the frame is softer than the tissue: each pass over-corrects the
last. Newton's step is exact for the chain drive -> lag (+ a parallel branch filtering the
rate) -> no-pull clamp, and cheap: the drive acts sample by sample (its slopes in x and v, by
differences), velocity is a three-point difference, each lag is a two-term recursion and the
clamp a mask, so the step is one banded solve (LAPACK's gbtrf/gbtrs). What the step leaves
out (a branch of another form) only slows it down: convergence is checked on the equation
itself.

A fit evaluates the model many times at nearly the same parameters (its Jacobian by
differences), so the last solution on the same motion and its factored Newton matrix are
kept: from there one step with the kept matrix (a chord step) usually suffices, and the
matrix is rebuilt only when such a step stops contracting.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

FRAME_RTOL = 1e-10  # of the force's own peak: far below any sensor's resolution
FRAME_MAX_ITER = 60
WARM_RTOL = 1e-3  # a last solution this close is kept as the start without trying a cold one
CHORD_CONTRACTION = 0.25  # a kept matrix whose step shrinks the error less than this is rebuilt
KEEP_CONTRACTION = 1e-3  # kept for the next call if its last step shrank the error this much

Give = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # force -> indentation, its rate
Tissue = Callable[[np.ndarray, np.ndarray], np.ndarray]  # indentation, rate -> tissue force
Drive = Callable[[np.ndarray, np.ndarray], np.ndarray]  # indentation, rate -> drive (in contact)


class NotConverged(RuntimeWarning):
    """The force equation holds only to `residual_N` (the largest error, in newtons)."""

    def __init__(self, message: str, residual_N: float = float("nan")) -> None:
        super().__init__(message)
        self.residual_N = residual_N


@dataclass
class Solution:
    """The force through a compliant frame, and the Newton step it ended on (None where no iteration was
    needed)."""

    force_N: np.ndarray
    newton: _Step | None


def _poly(*factors: tuple[float, ...]) -> np.ndarray:
    """The product of polynomials in the one-sample shift S (coefficients of S^0, S^1, ...)."""
    out = np.array([1.0])
    for f in factors:
        out = np.convolve(out, f)
    return out


def _shifted(p: np.ndarray, bands: tuple[np.ndarray, np.ndarray, np.ndarray]) -> dict[int, np.ndarray]:
    """p(S) T for T tridiagonal (lo, md, up): its bands by offset d = i - j, as rows i."""
    lo, md, up = bands
    n = len(md)
    t = {-1: up, 0: md, 1: lo}
    out: dict[int, np.ndarray] = {}
    for k, pk in enumerate(p):
        if pk == 0.0:
            continue
        for dt, band in t.items():
            d = dt + k
            row = out.setdefault(d, np.zeros(n))
            row[k:] += pk * band[:n - k]
    return out


def _tri_times(bands, r: np.ndarray) -> np.ndarray:
    lo, md, up = bands
    out = md * r
    out[1:] += lo[1:] * r[:-1]
    out[:-1] += up[:-1] * r[1:]
    return out


def _shift_poly(p: np.ndarray, r: np.ndarray) -> np.ndarray:
    out = p[0] * r
    for k in range(1, len(p)):
        out[k:] += p[k] * r[:-k]
    return out


@dataclass
class _Step:
    """Newton's step for f = C (L D(f) + B E(f)), factored. D is the drive (sample by sample in
    indentation and rate), L the lag; E the rate in contact, B the parallel branch's filter of
    it; C the no-pull clamp's mask. With L = L_b / L_a and B = B_b / B_a (polynomials in the
    one-sample shift S) and M, N minus the slopes of D and E in the force (tridiagonal), the
    step is s = -r + C z where
        L_a B_a z + (L_b B_a M + B_b L_a N) C z = (L_b B_a M + B_b L_a N) r:
    bands from three below the diagonal to one above."""

    drive_rhs: np.ndarray  # L_b B_a
    rate_rhs: np.ndarray  # B_b L_a
    m: tuple[np.ndarray, np.ndarray, np.ndarray]
    nb: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    live: np.ndarray
    lu: np.ndarray
    piv: np.ndarray
    kl: int
    ku: int

    @classmethod
    def build(cls, m, nb, live, lag: tuple[float, float, float],
              branch: tuple[float, float, float] | None) -> _Step | None:
        b0, b1, a = lag
        la, lb = (1.0, -a), (b0, b1)
        ba, bb = ((1.0, -branch[2]), (branch[0], branch[1])) if branch and nb is not None else ((1.0,), (0.0,))
        drive_rhs, rate_rhs = _poly(lb, ba), _poly(bb, la)
        bands = _shifted(drive_rhs, m)
        if nb is not None and np.any(rate_rhs):
            for d, row in _shifted(rate_rhs, nb).items():
                bands[d] = bands.get(d, 0.0) + row
        n = len(live)
        for d, row in bands.items():  # the clamp's mask on the columns j = i - d
            if d >= 0:
                row[d:] *= live[:n - d]
                row[:d] = 0.0
            else:
                row[:d] *= live[-d:]
                row[d:] = 0.0
        for d, c in enumerate(_poly(la, ba)):
            bands[d] = bands.get(d, np.zeros(n)) + c
        kl = max(d for d in bands if np.any(bands[d]) or d == 0)
        ku = max(0, -min(bands))
        ab = np.zeros((2 * kl + ku + 1, n))  # gbtrf's layout: entry (i, j) at [kl + ku + i - j, j]
        for d, row in bands.items():
            if d > kl:
                continue
            if d >= 0:
                ab[kl + ku + d, :n - d] = row[d:]
            else:
                ab[kl + ku + d, -d:] = row[:d]
        from scipy.linalg import lapack  # only a frame solve needs it; a plain fit does not import it

        lu, piv, info = lapack.dgbtrf(ab, kl, ku)
        if info != 0 or not np.all(np.isfinite(lu)):
            return None
        return cls(drive_rhs, rate_rhs, m, nb, live, lu, piv, kl, ku)

    def __call__(self, r: np.ndarray) -> np.ndarray:
        rhs = _shift_poly(self.drive_rhs, _tri_times(self.m, r))
        if self.nb is not None and np.any(self.rate_rhs):
            rhs += _shift_poly(self.rate_rhs, _tri_times(self.nb, r))
        from scipy.linalg import lapack

        z, info = lapack.dgbtrs(self.lu, self.kl, self.ku, rhs, self.piv)
        return -r + self.live * z if info == 0 else -r


def solve(give: Give, tissue: Tissue, drive: Drive, lag: tuple[float, float, float], x: np.ndarray,
          v: np.ndarray, dt: float, last: Solution | None = None,
          branch: tuple[float, float, float] | None = None) -> Solution:
    """The force f with f = tissue(give(f)). `lag` is (b0, b1, a) of the tissue's lag, y[i] =
    a y[i-1] + b0 u[i] + b1 u[i-1] ((1, 0, 0) without one); `branch` the same for a parallel
    branch driven by the rate of indentation (None: none, or not of that form, and left out
    of the step). The start is `last` (the solution at nearby parameters) when the equation
    nearly holds there, else the tissue's force with a rigid frame."""
    n = len(x)

    def residual(f: np.ndarray):
        xc, vc = give(f)
        out = tissue(xc, vc)
        return f - out, out, xc, vc

    def start(f0: np.ndarray):
        r, out, xc, vc = residual(f0)
        return float(np.max(np.abs(r))), (f0, r, out, xc, vc)

    warm = last is not None and len(last.force_N) == n
    best = start(last.force_N) if warm else None
    newton = last.newton if warm else None
    if best is None or not best[0] <= WARM_RTOL * max(float(np.max(np.abs(last.force_N))), 1e-300):
        cold = start(tissue(x, v))
        if best is None or not best[0] <= cold[0]:
            best, newton = cold, None
    norm, (f, r, out, xc, vc) = best
    x_scale = max(float(np.max(np.abs(x))), 1e-300)
    v_scale = max(float(np.max(np.abs(v))), x_scale / max(n * dt, dt))
    fresh = False
    contraction = 1.0  # of the last step taken
    for _ in range(FRAME_MAX_ITER):
        scale = max(float(np.max(np.abs(f))), 1e-300)
        if norm <= FRAME_RTOL * scale:
            # the matrix is kept for the next call only if it was still close to the solution's
            return Solution(f - r, newton if contraction <= KEEP_CONTRACTION else None)
        if newton is None:
            newton = _build(give, drive, lag, branch, f, xc, vc, out, x_scale, v_scale, scale, dt)
            fresh = True
        step = newton(r) if newton is not None else -r
        if not np.all(np.isfinite(step)):
            step = -r
        if not fresh:  # a kept matrix: its step is taken if it contracts, else the matrix is rebuilt
            r_new, out_new, xc_new, vc_new = residual(f + step)
            norm_new = float(np.max(np.abs(r_new)))
            if not norm_new <= CHORD_CONTRACTION * norm:
                newton = None
                if not norm_new < norm:
                    continue
        else:
            found = backtrack(lambda s, f=f: residual(f + s), step, norm)
            if found is None:
                break
            step, (r_new, out_new, xc_new, vc_new) = found
            norm_new = float(np.max(np.abs(r_new)))
            fresh = False
        contraction = norm_new / norm
        f, r, out, xc, vc, norm = f + step, r_new, out_new, xc_new, vc_new, norm_new
    warnings.warn(NotConverged(f"frame compliance: the force did not converge (residual {norm:.3g} N)", norm),
                  stacklevel=4)
    return Solution(f - r, None)


def backtrack(evaluate: Callable, step: np.ndarray, norm: float, tries: int = 30):
    """Newton's step halved until the equation's error falls below `norm`: (step, what
    `evaluate(step)` gave, its first item the residual), or None if it never does."""
    for _ in range(tries):
        got = evaluate(step)
        r = got[0] if isinstance(got, tuple) else got
        norm_new = float(np.max(np.abs(r)))
        if np.isfinite(norm_new) and norm_new < norm:
            return step, got
        step = 0.5 * step
    return None


def _build(give: Give, drive: Drive, lag, branch, f, xc, vc, out, x_scale, v_scale, scale, dt) -> _Step | None:
    """Newton's matrix at f: the drive's slopes in x and v (zero out of contact), the frame's
    give (1/k) by differences."""
    contact = xc > 0
    xp = np.maximum(xc, 0.0)
    d0 = drive(xp, vc)
    hx, hv = 1e-6 * x_scale, 1e-6 * v_scale
    alpha = np.where(contact, (drive(xp + hx, vc) - d0) / hx, 0.0)
    beta = np.where(contact, (drive(xp, vc + hv) - d0) / hv, 0.0)
    hf = 1e-6 * scale
    gv = -(give(f + hf)[0] - xc) / hf
    m = _slope_bands(alpha, beta, gv, dt)
    nb = _slope_bands(np.zeros_like(gv), contact.astype(float), gv, dt) if branch else None
    return _Step.build(m, nb, (out > 0).astype(float), lag, branch)


def _slope_bands(alpha, beta, gv, dt):
    """(diag(alpha) + diag(beta) D) diag(gv), D the three-point difference (one-sided at the
    ends, as np.gradient): minus a sample-wise term's slope in the force, as (lo, md, up)."""
    n = len(gv)
    c = 0.5 / dt
    md = alpha * gv
    lo = np.zeros(n)
    up = np.zeros(n)
    up[1:-1] = beta[1:-1] * c * gv[2:]
    lo[1:-1] = -beta[1:-1] * c * gv[:-2]
    md[0] -= beta[0] / dt * gv[0]
    up[0] = beta[0] / dt * gv[1]
    md[-1] += beta[-1] / dt * gv[-1]
    lo[-1] = -beta[-1] / dt * gv[-2]
    return lo, md, up
