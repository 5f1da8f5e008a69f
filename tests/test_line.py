"""The straight line from centred sums is np.polyfit's, to rounding."""

from __future__ import annotations

import numpy as np
import pytest

from rig.analysis.stats.line import fit_line, off_line


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("n", [2, 7, 300, 20000])
def test_the_line_is_polyfits(seed, n):
    rng = np.random.default_rng(seed)
    x = np.sort(rng.uniform(-5.0, 50.0, n)) + 1e3 * seed  # far from zero: centring matters
    y = rng.normal(0.0, 1e-9, n) + 3e-7 * x - 2e-4
    ref = np.polyfit(x, y, 1)
    slope, intercept = fit_line(x, y)
    assert slope == pytest.approx(ref[0], rel=1e-9)
    assert intercept == pytest.approx(ref[1], rel=1e-9, abs=1e-15)
    np.testing.assert_allclose(off_line(x, y), y - np.polyval(ref, x), rtol=0, atol=1e-6 * np.std(y))


def test_a_line_over_one_x_is_flat_through_the_mean():
    assert fit_line(np.full(4, 2.0), np.array([1.0, 2.0, 3.0, 6.0])) == (0.0, 3.0)
    np.testing.assert_array_equal(off_line(np.full(3, 2.0), np.array([1.0, 2.0, 3.0])), [-1.0, 0.0, 1.0])


def test_each_row_is_taken_off_its_own_line():
    rng = np.random.default_rng(7)
    x = np.linspace(-1.0, 1.0, 500)
    rows = rng.normal(size=(6, 500)) + rng.normal(size=(6, 1)) * x + rng.normal(size=(6, 1))
    got = off_line(x, rows)
    for row, out in zip(rows, got, strict=True):
        # to rounding: the rows' products go through one matrix product, a row's through a dot
        np.testing.assert_allclose(out, off_line(x, row), rtol=0, atol=1e-14 * np.abs(row).max())
