"""Rest-to-rest trapezoidal moves: how long they take and where they are at time t."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np


def _profile(d: float, speed: float, accel: float) -> tuple[float, float, float]:
    """(accel time, cruise time, peak speed) for distance d; triangular when d is short."""
    t_acc = speed / accel
    if accel * t_acc ** 2 > d:
        t_acc = math.sqrt(d / accel)
        speed = accel * t_acc
    return t_acc, (d - accel * t_acc ** 2) / speed, speed


def move_time(x0: float, x1: float, speed: float, accel: float) -> float:
    """How long a trapezoidal move from `x0` to `x1` takes at `speed` and `accel` (0 for no move)."""
    d = abs(x1 - x0)
    if d == 0 or speed <= 0:
        return 0.0
    t_acc, t_cruise, _ = _profile(d, speed, accel)
    return 2 * t_acc + t_cruise


def position_at(x0: float, x1: float, speed: float, accel: float, t: float) -> float:
    """Position `t` seconds after the start of a move from x0 to x1."""
    d = abs(x1 - x0)
    if t <= 0 or d == 0:
        return x0 if t <= 0 else x1
    t_acc, t_cruise, v = _profile(d, speed, accel)
    total = 2 * t_acc + t_cruise
    if t >= total:
        return x1
    if t < t_acc:
        s = 0.5 * accel * t * t
    elif t < t_acc + t_cruise:
        s = 0.5 * accel * t_acc ** 2 + v * (t - t_acc)
    else:
        s = d - 0.5 * accel * (total - t) ** 2
    return x0 + math.copysign(s, x1 - x0)


def sample_move(x0: float, x1: float, speed: float, accel: float, rate_Hz: float) -> np.ndarray:
    """The move sampled at `rate_Hz`, first sample one period after the start, last at x1."""
    n = max(math.ceil(move_time(x0, x1, speed, accel) * rate_Hz), 1)
    return np.array([position_at(x0, x1, speed, accel, (i + 1) / rate_Hz) for i in range(n)])


# ------------------------------------------------------------------ lagged sums, streamed

def _power_sum(k: int, n: int) -> int:
    """sum_{j=0}^{n-1} j^k for k <= 4, exact (Faulhaber)."""
    m = n - 1
    if n <= 0:
        return 0
    if k == 0:
        return n
    if k == 1:
        return m * n // 2
    if k == 2:
        return m * n * (2 * m + 1) // 6
    if k == 3:
        return (m * n // 2) ** 2
    return m * n * (2 * m + 1) * (3 * m * m + 3 * m - 1) // 30


def _times(x: float, count: int) -> float:
    """x * count, where count may be past a float's range while the product is not (a move of
    1e80 samples: its j^4 sums overflow, its coefficients are as small)."""
    if count.bit_length() < 1000:
        return x * float(count)
    return float(Fraction(x) * count)


def _poly_at(c: tuple[float, float, float], j: float) -> float:
    return c[0] + j * (c[1] + j * c[2])


class LaggedSums:
    """The information a signal's lagged copies carry, without keeping the signal.

    A protocol's commanded position is a chain of pieces, each a polynomial of degree two at
    most in the sample index (holds constant, a trapezoidal move's three phases): its lagged
    products sum_s u[s] u[s-d] have closed forms, so a plan of any length is summed in time
    proportional to its number of pieces, not samples (a 60 s hold repeated 10,000 times is
    6e7 samples). Only the first and last few samples are kept, for the edges the lagged
    matrix of each order leaves out. `information(n)` equals `lags.T @ lags` of the sampled
    signal's first n lags (`rig.control.estimator.excitation_order`), up to rounding.
    """

    EDGE = 8  # samples kept at each end: lags up to 4, products up to 3 apart

    def __init__(self, max_lag: int = 4) -> None:
        self.max_lag = max_lag
        self.count = 0
        self.sums = [0.0] * max_lag  # sums[d] = sum_{s>=d} u[s] u[s-d]
        self.first: list[float] = []
        self.last: list[float] = []

    def push(self, x: float) -> None:
        """One sample."""
        for d in range(min(self.max_lag, len(self.last) + 1)):
            self.sums[d] += x * (self.last[-d] if d else x)
        if len(self.first) < self.EDGE:
            self.first.append(x)
        self.last.append(x)
        if len(self.last) > self.EDGE:
            del self.last[0]
        self.count += 1

    def push_poly(self, coeffs: tuple[float, float, float], n: int) -> None:
        """`n` samples c0 + c1 j + c2 j^2, j = 0 .. n-1."""
        head = min(n, max(self.max_lag, self.EDGE - self.count))
        if n - head < self.EDGE:  # short: sample it
            for j in range(n):
                self.push(_poly_at(coeffs, j))
            return
        for j in range(head):  # the products that reach back into the previous piece
            self.push(_poly_at(coeffs, j))
        c0, c1, c2 = coeffs
        for d in range(self.max_lag):
            # sum_{j=head}^{n-1} q(j) q(j-d): a polynomial of degree 4 in j
            e0, e1, e2 = c0 - d * c1 + d * d * c2, c1 - 2 * d * c2, c2  # q(j - d)
            prod = (c0 * e0, c0 * e1 + c1 * e0, c0 * e2 + c1 * e1 + c2 * e0, c1 * e2 + c2 * e1, c2 * e2)
            self.sums[d] += sum(_times(p, _power_sum(k, n) - _power_sum(k, head))
                                for k, p in enumerate(prod) if p)
        self.last = [_poly_at(coeffs, j) for j in range(n - self.EDGE, n)]
        self.count += n - head

    def push_move(self, x0: float, x1: float, speed: float, accel: float, rate_Hz: float) -> None:
        """The samples of `sample_move(x0, x1, speed, accel, rate_Hz)`, phase by phase."""
        n = max(math.ceil(move_time(x0, x1, speed, accel) * rate_Hz), 1)
        d = abs(x1 - x0)
        if d == 0 or speed <= 0 or n <= 4 * self.EDGE:
            for i in range(n):
                self.push(position_at(x0, x1, speed, accel, (i + 1) / rate_Hz))
            return
        t_acc, t_cruise, v = _profile(d, speed, accel)
        total = 2 * t_acc + t_cruise
        sign = math.copysign(1.0, x1 - x0)
        h = 1.0 / rate_Hz

        def before(t_end: float) -> int:
            """How many samples (t = (i+1)/rate) fall before `t_end`, as position_at decides (a
            step or two either side of the estimate; at magnitudes where a float no longer tells
            i from i + 1, the estimate stands)."""
            i = max(min(math.ceil(t_end * rate_Hz) - 1, n), 0)
            for _ in range(4):
                if i > 0 and not i / rate_Hz < t_end:
                    i -= 1
                elif i < n and (i + 1) / rate_Hz < t_end:
                    i += 1
            return i

        c_total = before(total)
        c_acc, c_cruise = min(before(t_acc), c_total), min(before(t_acc + t_cruise), c_total)
        i0 = 0
        for end, phase in ((c_acc, "accel"), (c_cruise, "cruise"), (c_total, "decel")):
            m = end - i0
            if m > 0:
                tau0 = (i0 + 1) * h  # the phase's first sample time
                if phase == "accel":
                    s = (0.5 * accel * tau0 * tau0, accel * tau0 * h, 0.5 * accel * h * h)
                elif phase == "cruise":
                    s = (0.5 * accel * t_acc ** 2 + v * (tau0 - t_acc), v * h, 0.0)
                else:
                    back = total - tau0
                    s = (d - 0.5 * accel * back * back, accel * back * h, -0.5 * accel * h * h)
                self.push_poly((x0 + sign * s[0], sign * s[1], sign * s[2]), m)
            i0 = max(i0, end)
        if n > i0:
            self.push_poly((x1, 0.0, 0.0), n - i0)

    def _at(self, s: int) -> float:
        if s < len(self.first):
            return self.first[s]
        return self.last[s - (self.count - len(self.last))]

    def information(self, order: int) -> np.ndarray:
        """sum over t = order .. count-1 of the outer product of (u[t-1], ..., u[t-order])."""
        out = np.empty((order, order))
        for i in range(1, order + 1):
            for j in range(i, order + 1):
                d = j - i
                # rows t = order .. count-1 give s = t - i from order - i to count - 1 - i
                total = self.sums[d]
                total -= sum(self._at(s) * self._at(s - d) for s in range(d, order - i))
                total -= sum(self._at(s) * self._at(s - d) for s in range(self.count - i, self.count))
                out[i - 1, j - 1] = out[j - 1, i - 1] = total
        return out

    def excitation_order(self, resolution: float) -> int:
        """`rig.control.estimator.excitation_order` of the pushed signal: the largest n for which
        the information of n lags, per sample, has its weakest direction above resolution^2."""
        order = 0
        for n in range(1, self.max_lag + 1):
            if self.count <= n + 1:
                break
            if np.linalg.eigvalsh(self.information(n) / (self.count - n))[0] <= resolution ** 2:
                break
            order = n
        return order
