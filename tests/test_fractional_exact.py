"""The fractional Maxwell branch's mode sum against an exact, independent evaluation.

The exact force is the convolution f(t) = integral of G(t - s) v(s) ds, G(t) = k E_a(-(t/tau)^a).
The branch reads its velocity as linear between samples (from rest at t = -dt, as every lag in
the models does), so the history compared here is exactly that one: v = sum_j v_j hat_j(s), hat_j
the unit hat on [t_j - dt, t_j + dt]. Each hat's force is a second difference of the twice
integrated modulus Psi(t) = k t^2 E_{a,3}(-(t/tau)^a), so summing by parts the force is a few
Psi terms at the corners of v: exact, no quadrature. (A history with corners at the samples in x,
i.e. a velocity that jumps at a sample, is not one any sampled velocity describes; the
difference, of order dt / ramp time, would be the sampling's error, not the mode sum's.)

E_{a,b} comes from the inversion of its Laplace transform s^(a-b) / (s^a + z) on Talbot's contour
(Trefethen, Weideman & Schmelzer 2006), independent of the mode construction (which sums the
spectrum of rates on the real axis); it is checked against known values first.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import erfcx

from rig.models.fractional import fractional_maxwell, modes

TALBOT_NODES = 32  # error ~3.89^-N, so round-off (~1e-13) is what limits it


def mittag_leffler(alpha: float, beta: float, z: np.ndarray) -> np.ndarray:
    """E_{alpha,beta}(-z) for z >= 0: the inverse Laplace transform of s^(a-b) / (s^a + z) at t = 1,
    by the trapezoidal rule on the optimised cotangent (Talbot) contour."""
    z = np.atleast_1d(np.asarray(z, dtype=float))
    n = TALBOT_NODES
    theta = -np.pi + (np.arange(n) + 0.5) * 2.0 * np.pi / n
    theta = theta[theta > 0]  # the lower half is the conjugate
    s = n * (0.5017 * theta / np.tan(0.6407 * theta) - 0.6122 + 0.2645j * theta)
    ds = n * (0.5017 / np.tan(0.6407 * theta) - 0.5017 * 0.6407 * theta / np.sin(0.6407 * theta) ** 2
              + 0.2645j)
    transform = s ** (alpha - beta) / (s ** alpha + z[:, None])
    return (2.0 / n) * np.real(np.sum(np.exp(s) * transform * ds / 1j, axis=1))


def _series(alpha: float, beta: float, z: float, terms: int = 80) -> float:
    return sum((-z) ** k / math.gamma(alpha * k + beta) for k in range(terms))


def test_mittag_leffler_reference_matches_known_values():
    t = np.array([0.0, 1e-3, 0.1, 1.0, 5.0, 20.0, 35.0])
    assert np.max(np.abs(mittag_leffler(1.0, 1.0, t) - np.exp(-t))) < 1e-11
    z = np.array([0.0, 1e-3, 0.1, 1.0, 5.0, 40.0, 1e3, 1e4])
    assert np.max(np.abs(mittag_leffler(0.5, 1.0, z) - erfcx(z))) < 1e-11  # exp(z^2) erfc(z)
    zz = t[1:]
    assert np.max(np.abs(mittag_leffler(1.0, 2.0, zz) - -np.expm1(-zz) / zz)) < 1e-11
    zz = t[2:]
    assert np.max(np.abs(mittag_leffler(1.0, 3.0, zz) - (np.exp(-zz) - 1.0 + zz) / zz**2)) < 1e-11
    for alpha in (0.1, 0.3, 0.5, 0.8, 0.95):  # the power series where it converges in floats
        for beta in (1.0, 3.0):
            for x in (0.01, 0.2, 0.5):
                assert mittag_leffler(alpha, beta, x)[0] == pytest.approx(_series(alpha, beta, x), abs=1e-11)
    # far out, E_{a,b}(-z) ~ 1 / (z Gamma(b - a)) - 1 / (z^2 Gamma(b - 2a))
    for alpha in (0.3, 0.8):
        big = 1e6
        approx = 1.0 / (big * math.gamma(3.0 - alpha)) - 1.0 / (big**2 * math.gamma(3.0 - 2 * alpha))
        assert mittag_leffler(alpha, 3.0, big)[0] == pytest.approx(approx, rel=1e-8)


def _psi(t_s: np.ndarray, k_N_per_m: float, tau_s: float, alpha: float) -> np.ndarray:
    """Twice-integrated modulus k t^2 E_{a,3}(-(t/tau)^a), zero before t = 0."""
    out = np.zeros_like(t_s)
    on = t_s > 0
    out[on] = k_N_per_m * t_s[on] ** 2 * mittag_leffler(alpha, 3.0, (t_s[on] / tau_s) ** alpha)
    return out


def exact_force_N(v_m_s: np.ndarray, dt_s: float, k_N_per_m: float, tau_s: float,
                  alpha: float) -> np.ndarray:
    """f_i = sum_j v_j (Psi_{i-j+1} - 2 Psi_{i-j} + Psi_{i-j-1}) / dt, summed by parts over
    the corners c_q = v_{q+1} - 2 v_q + v_{q-1} of v (v = 0 before sample 0)."""
    n = len(v_m_s)
    padded = np.concatenate([[0.0, 0.0], v_m_s, [v_m_s[-1]]])  # v_{-2} .. v_n
    corners = padded[2:] - 2.0 * padded[1:-1] + padded[:-2]  # c_q for q = -1 .. n - 1
    t = np.arange(n) * dt_s
    f = np.zeros(n)
    for q in np.flatnonzero(corners):
        f += corners[q] * _psi(t - (q - 1) * dt_s, k_N_per_m, tau_s, alpha)
    return f / dt_s


def _histories(dt_s: float) -> dict[str, np.ndarray]:
    """Indentation rates (m/s) of a 1 um, 1 s ramp held 5 s, and of a 1 s approach and 1 s
    retract then 4 s apart."""
    speed, ramp, rest = 1e-6, round(1.0 / dt_s), round(4.0 / dt_s)
    return {"ramp-hold": np.concatenate([np.full(ramp, speed), np.zeros(rest + ramp)]),
            "approach-retract": np.concatenate([np.full(ramp, speed), np.full(ramp, -speed), np.zeros(rest)])}


K_N_PER_M = 0.03
CASES = [(alpha, tau, dt) for alpha in (0.1, 0.3, 0.5, 0.8) for tau in (0.005, 0.05, 3.0)
         for dt in (1e-3, 1e-2)]


@pytest.mark.parametrize("alpha, tau_s, dt_s", CASES)
def test_mode_sum_is_exact_to_the_noise(alpha, tau_s, dt_s):
    """Within 0.05 % of the peak (AFM noise is ~0.05-0.1 % of it) for tau far below the 6 s
    record and comparable to it, at 1 and 10 ms; 4 modes a decade missed by 0.1-2.7 %."""
    for name, v in _histories(dt_s).items():
        ref = exact_force_N(v, dt_s, K_N_PER_M, tau_s, alpha)
        f = fractional_maxwell(v, dt_s, K_N_PER_M, tau_s, alpha)
        err = np.max(np.abs(f - ref)) / np.max(np.abs(ref))
        assert err <= 5e-4, f"{name}: {100 * err:.3f} % of the peak"


def test_reference_is_the_history_the_samples_describe():
    """The exact force at the first samples by hand: v rises linearly from 0 at -dt to v_0, so
    f(0) = v_0 Psi(dt) / dt; and a spring (alpha -> 1, tau -> infinity is a spring k) gives k x."""
    dt, tau, alpha = 1e-2, 0.05, 0.5
    v = np.full(5, 2e-6)
    f = exact_force_N(v, dt, K_N_PER_M, tau, alpha)
    assert f[0] == pytest.approx(2e-6 * _psi(np.array([dt]), K_N_PER_M, tau, alpha)[0] / dt, rel=1e-12)
    x = np.cumsum(np.full(200, 1e-6)) * dt - 0.5e-6 * dt  # the integral of the hats from -dt
    spring = exact_force_N(np.full(200, 1e-6), dt, K_N_PER_M, 1e12, 0.999)
    assert spring == pytest.approx(K_N_PER_M * x, rel=1e-6)


def test_modes_keep_the_whole_weight_and_the_far_tails():
    for alpha in (0.05, 0.5, 0.95):
        for tau in (1e-4, 0.05, 1e4):
            rates, weights = modes(10.0, 1e-3, tau, alpha)
            assert abs(weights.sum() - 1.0) < 1e-12 and np.all(weights > 0)
            assert np.all(np.diff(np.sort(rates)) > 0)
            # a mode for each tail: one slower than the record, one faster than a sample
            assert rates.min() < 0.01 / 10.0 and rates.max() > 100.0 / 1e-3


@pytest.mark.parametrize("alpha, tau_s", [(0.05, 1e-4), (0.95, 0.05), (0.3, 1e4)])
def test_mode_sum_is_exact_at_the_bounds_of_the_fit(alpha, tau_s):
    """The catalogue lets alpha run from 0.05 to 0.95 and tau from 0.1 ms to 1e4 s."""
    for dt in (1e-3, 1e-2):
        for v in _histories(dt).values():
            ref = exact_force_N(v, dt, K_N_PER_M, tau_s, alpha)
            err = np.max(np.abs(fractional_maxwell(v, dt, K_N_PER_M, tau_s, alpha) - ref)) / np.max(np.abs(ref))
            assert err <= 5e-4, err
