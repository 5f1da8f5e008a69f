"""Rest-to-rest trapezoidal moves: how long they take and where they are at time t."""

from __future__ import annotations

import math

import numpy as np


def _profile(d: float, speed: float, accel: float) -> tuple[float, float, float]:
    """(accel time, cruise time, peak speed) for distance d; triangular when d is short."""
    t_acc = speed / accel
    if accel * t_acc ** 2 > d:
        t_acc = math.sqrt(d / accel)
        speed = accel * t_acc
    return t_acc, (d - accel * t_acc ** 2) / speed, speed


def move_time(x0: float, x1: float, speed: float, accel: float) -> float:
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
