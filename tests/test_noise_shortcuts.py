"""The noise's statistics taken the quick way are the ones the plain definitions give: the
structure function over all lags at once, the integral scale from its first lags, and one row's
AR fit in plain floats."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from rig.analysis.stats.noise import ar_fit, ar_fit_rows, autocovariance, integral_scales, structure_function


def _series(kind: str, n: int, seed: int) -> np.ndarray:
    w = np.random.default_rng(seed).standard_normal(n)
    if kind == "ar":
        return lfilter([1.0], [1.0, -0.95], w)
    if kind == "boxcar":
        return np.convolve(w, np.ones(10) / 10.0, "same")
    if kind == "walk":
        return np.cumsum(w)
    return w


def _structure_by_lag(residuals: list[np.ndarray], K: int) -> np.ndarray:
    return np.array([np.mean(np.concatenate([(r[k:] - r[:-k]) ** 2 for r in residuals if len(r) > k]))
                     for k in range(1, K + 1)])


def _scales_by_transform(r: np.ndarray) -> np.ndarray:
    n = r.shape[1]
    lag = n // 4
    acf = autocovariance(r, lag)
    acf = acf / np.maximum(acf[:, :1], 1e-300)
    below = acf < 0.05
    cut = np.where(below.any(axis=1), below.argmax(axis=1), lag)
    csum = np.concatenate([np.zeros((len(r), 1)), np.cumsum(acf[:, 1:], axis=1)], axis=1)
    return np.clip(1.0 + 2.0 * csum[np.arange(len(r)), np.maximum(cut - 1, 0)], 1.0, n / 20.0)


@pytest.mark.parametrize("lengths", [(1100,), (300, 20, 5), (40000,), (30, 9)])
def test_the_structure_function_is_the_mean_over_each_lag_s_pairs(lengths):
    residuals = [_series("ar", n, seed) for seed, n in enumerate(lengths)]
    K = 40 if lengths == (30, 9) else 27
    want = _structure_by_lag(residuals, min(K, max(lengths) - 1))
    got = structure_function(residuals, K)
    np.testing.assert_allclose(got[:len(want)], want, rtol=1e-12)
    assert np.all(np.isnan(got[len(want):]))


def test_integral_scales_agree_with_the_whole_transform_whether_rows_drop_early_or_not():
    kinds = ["white", "ar", "boxcar", "walk"] * 3
    rows = np.vstack([_series(kind, 1100, seed) for seed, kind in enumerate(kinds)])
    np.testing.assert_allclose(integral_scales(rows), _scales_by_transform(rows), rtol=1e-12)
    np.testing.assert_allclose(integral_scales(rows[:3, :40]), _scales_by_transform(rows[:3, :40]), rtol=1e-12)


@pytest.mark.parametrize("kind", ["white", "ar", "boxcar", "walk"])
@pytest.mark.parametrize("max_order", [24, 5, 1])
def test_one_row_s_ar_fit_is_the_rows_fit(kind, max_order):
    for seed, n in enumerate([60, 400, 2500]):
        gamma = autocovariance(_series(kind, n, seed), min(24, n // 4))[0]
        want = ar_fit_rows(gamma[None, :], n, max_order)[0]
        got = ar_fit(gamma, n, max_order)
        assert len(got) == len(want)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    assert len(ar_fit(np.zeros(5), 100)) == 0
