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
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    x_mean, y_mean = float(x.mean()), float(y.mean())
    dx = x - x_mean
    sxx = float(dx @ dx)
    slope = float(dx @ (y - y_mean)) / sxx if sxx > 0 else 0.0
    return slope, y_mean - slope * x_mean


def off_line(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """y less its least-squares line in x; each row of a 2-D y less its own, all at once."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    dx = x - float(x.mean())
    dy = y - y.mean(axis=-1, keepdims=True)
    sxx = float(dx @ dx)
    if not sxx > 0:
        return dy
    return dy - ((dy @ dx) / sxx)[..., None] * dx
