"""Online stiffness estimation: f(t) = k x(t-1) + e(t) by RLS with time-varying forgetting.

Why this model: a ramp-and-hold motion is sufficiently rich of exact order 1, so the
only identifiable ARMAX structure is y(t) = b1 u(t-1) + e(t), i.e. Hooke's law with a
one-sample delay (see `excitation_order`). `k` is therefore not a material stiffness:
it absorbs every dynamic this one-parameter model leaves out.

Forgetting law (`law: constant_information`), after Fortescue, Kershenbaum & Ydstie
(1981), with the squared prediction error smoothed over `smoothing_s` so one noise
spike does not flush the memory:

    s(t)      = a s(t-1) + (1 - a) e(t)^2                       a = exp(-1/(smoothing_s * rate))
    lambda(t) = 1 - s(t) / (sigma^2 N0 (1 + x(t-1)^2 P(t-1)))    N0 = memory_s * rate
    lambda    clipped to [lambda_min, lambda_max]

While the error is at the sensor-noise level (s ~ sigma^2 (1 + x^2 P)) the memory is
N0 samples; when the error grows the memory shrinks in proportion, so the estimate
follows the ramp-to-hold transition quickly and is quiet again once the force settles.
`law: fixed` uses lambda = 1 - 1/N0 throughout (the classic exponentially weighted RLS).

Windup: with x ~ 0 the update P <- P/lambda grows without bound, so updates are frozen
out of contact and P is capped at its initial value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class RlsStep:
    """What one update produced; `error_N` is the a-priori error f(t) - k(t-1) x(t-1)."""

    stiffness_N_per_m: float
    force_pred_N: float
    error_N: float
    forgetting: float
    updated: bool


class StiffnessRLS:
    """The online stiffness estimate: f(t) = k x(t-1) + e(t) by recursive least squares with the
    forgetting law of the module's docstring. `update` takes one tick's previous position and
    force; `k` and `stiffness_std_N_per_m` are the estimate and its standard error (N/m)."""

    def __init__(self, *, rate_Hz: float, law: str = "constant_information", memory_s: float = 0.3,
                 smoothing_s: float = 0.1, lambda_min: float = 0.8, lambda_max: float = 0.9999,
                 noise_N: float = 0.08, initial_stiffness_N_per_m: float = 0.0,
                 initial_std_N_per_m: float = 1000.0, contact_mm: float = 0.2,
                 contact_N: float = 0.05) -> None:
        if law not in ("constant_information", "fixed"):
            raise ValueError(f"unknown forgetting law '{law}'")
        self.law = law
        self.n0 = max(memory_s * rate_Hz, 1.0)
        self.lambda_fixed = 1.0 - 1.0 / self.n0
        self.alpha = math.exp(-1.0 / max(smoothing_s * rate_Hz, 1e-9))
        self.lambda_min = lambda_min
        self.lambda_max = lambda_max
        self.sigma2 = max(noise_N, 1e-6) ** 2
        self.p_max = (initial_std_N_per_m ** 2) / self.sigma2  # P is covariance / sigma^2
        self.k = initial_stiffness_N_per_m
        self.p = self.p_max
        self.s = self.sigma2
        self.contact_m = contact_mm / 1000.0
        self.contact_N = contact_N

    @classmethod
    def from_config(cls, est, rate_Hz: float) -> StiffnessRLS:
        """From an `EstimatorConfig` (the `estimator:` section of a rig config)."""
        return cls(rate_Hz=rate_Hz, law=est.law, memory_s=est.memory_s, smoothing_s=est.smoothing_s,
                   lambda_min=est.lambda_min, lambda_max=est.lambda_max, noise_N=est.noise_N,
                   initial_stiffness_N_per_m=est.initial_stiffness_N_per_m,
                   initial_std_N_per_m=est.initial_std_N_per_m, contact_mm=est.contact_mm,
                   contact_N=est.contact_N)

    def update(self, x_prev_m: float, force_N: float) -> RlsStep:
        """One sample: predict from x(t-1), then update if the probe is in contact."""
        pred = self.k * x_prev_m
        e = force_N - pred
        if x_prev_m <= self.contact_m or force_N <= self.contact_N:
            return RlsStep(self.k, pred, e, 1.0, False)
        phi, p = x_prev_m, self.p
        info = phi * p * phi
        self.s = self.alpha * self.s + (1.0 - self.alpha) * e * e
        if self.law == "fixed":
            lam = self.lambda_fixed
        else:
            lam = 1.0 - self.s / (self.sigma2 * self.n0 * (1.0 + info))
            lam = min(self.lambda_max, max(self.lambda_min, lam))
        gain = p * phi / (lam + info)
        self.k += gain * e
        self.p = min((p - gain * phi * p) / lam, self.p_max)
        return RlsStep(self.k, pred, e, lam, True)

    @property
    def stiffness_std_N_per_m(self) -> float:
        return math.sqrt(self.p * self.sigma2)


def excitation_order(u: np.ndarray, resolution: float, max_order: int = 4) -> int:
    """Order of sufficient richness of input `u` in the paper's sense.

    The largest n for which the information matrix of the lagged inputs
    [u(t-1) ... u(t-n)] is positive definite, where "positive" means the weakest
    direction carries motion the instrument can resolve: smallest eigenvalue per
    sample above `resolution`^2 (e.g. the position quantum). Ramp-and-hold gives 1,
    a sine 2, all zeros 0.
    """
    u = np.asarray(u, dtype=float)
    order = 0
    for n in range(1, max_order + 1):
        if len(u) <= n + 1:
            break
        lags = np.column_stack([u[n - i: len(u) - i] for i in range(1, n + 1)])
        info = lags.T @ lags / len(lags)
        if np.linalg.eigvalsh(info)[0] <= resolution ** 2:
            break
        order = n
    return order
