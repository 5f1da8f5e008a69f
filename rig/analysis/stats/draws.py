"""Gaussian draws for the analysis's simulations, without numpy.random.

numpy.random costs about 9 ms to import, as much as the rest of a one-curve fit's statistics,
and the adequacy limits (rig.analysis.stats.adequacy) run on every fit. The draws here are
SplitMix64 (Steele, Lea & Flood 2014: the seeding generator of Java's SplittableRandom and of
xoshiro) over a counter, turned Gaussian by Box and Muller: vectorised, reproducible from a
seed, and statistically sound for a few million draws.
"""

from __future__ import annotations

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


class Draws:
    """A stream of standard normal draws from `seed`; each call continues the stream."""

    def __init__(self, seed: int = 0) -> None:
        self._next = np.uint64(seed) * np.uint64(1 << 32)

    def _uniform(self, n: int) -> np.ndarray:
        """n uniform numbers in (0, 1)."""
        with np.errstate(over="ignore"):
            z = (self._next + np.arange(1, n + 1, dtype=np.uint64)) * _GOLDEN
            z = (z ^ (z >> np.uint64(30))) * _M1
            z = (z ^ (z >> np.uint64(27))) * _M2
            z ^= z >> np.uint64(31)
        self._next += np.uint64(n)
        return ((z >> np.uint64(11)).astype(np.float64) + 0.5) * (1.0 / (1 << 53))

    @property
    def position(self) -> int:
        """Where the stream is: the same position gives the same draws."""
        return int(self._next)

    def skip(self, n: int) -> None:
        """Move the stream on past `n` standard normal draws, as `standard_normal` would."""
        self._next += np.uint64(2 * ((n + 1) // 2))

    def standard_normal(self, shape: tuple[int, ...]) -> np.ndarray:
        n = int(np.prod(shape))
        half = (n + 1) // 2
        u = self._uniform(2 * half)
        radius = np.sqrt(-2.0 * np.log(u[:half]))
        angle = 2.0 * np.pi * u[half:]
        return np.concatenate([radius * np.cos(angle), radius * np.sin(angle)])[:n].reshape(shape)
