"""A straight line by least squares, from centred sums.

`np.polyfit(x, y, 1)` gives the same line to rounding, through a scaled Vandermonde matrix and an
SVD: a few hundred microseconds of call overhead, taken several times on every curve of a map
(a baseline's trend, a quiet stretch's scatter, the noise's detrending).
"""

from __future__ import annotations

import numpy as np

__all__ = ["fit_line", "off_line"]


def fit_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Slope and intercept of the least-squares line through (x, y), as `np.polyfit(x, y, 1)`
    orders them; a flat line through the mean when x does not vary."""
    x_mean, y_mean, _, _, slope = _centred(x, y)
    return slope, y_mean - slope * x_mean


def off_line(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """y less its least-squares line in x."""
    _, _, dx, dy, slope = _centred(x, y)
    return dy - slope * dx


def _centred(x: np.ndarray, y: np.ndarray) -> tuple[float, float, np.ndarray, np.ndarray, float]:
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    x_mean, y_mean = float(x.mean()), float(y.mean())
    dx, dy = x - x_mean, y - y_mean
    sxx = float(dx @ dx)
    return x_mean, y_mean, dx, dy, (float(dx @ dy) / sxx if sxx > 0 else 0.0)
