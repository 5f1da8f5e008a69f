"""A record's velocity, and its phases (ramp, early and late hold, return), from its steps or
from its motion."""

from __future__ import annotations

import numpy as np

EXACT_FRACTION = 1e-3  # a second difference below this share of a moving sample's travel is rounding

HOLD_EARLY_FRACTION = 1.0 / 6.0  # the paper's 10 s of a 60 s hold

MOVING_FRACTION = 0.1  # moving: faster than a tenth of the record's ramp speed


EXACT_CORNERS = 200  # at most one corner per this many samples (and 8 in any record): "a few"


def velocity(x: np.ndarray, dt: float) -> np.ndarray:
    """dx/dt, smoothed over as few samples as the position's own noise allows; a position that is
    exact (piecewise linear: `_exact_rate`) is not smoothed.

    The window w is the shortest that keeps the derivative's noise (sigma_x * sqrt(12) /
    (dt w^1.5) for a quadratic Savitzky-Golay fit) below 2 % of the speed of the moving samples;
    sigma_x comes from the position's second differences, so encoder steps and sensor
    noise set it, not a number of seconds.
    """
    n = len(x)
    if n < 7:
        return np.gradient(x, dt)
    speed = _moving_speed(x, dt)
    exact = _exact_rate(x, dt, speed * dt)
    if exact is not None:
        return exact
    d2 = np.diff(x, 2)
    sigma_x = 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / np.sqrt(6.0)
    if sigma_x == 0.0:  # quantised steps: most second differences are zero; use their spread
        sigma_x = float(np.std(d2)) / np.sqrt(6.0)
    w = (sigma_x * np.sqrt(12.0) / (0.02 * speed * dt)) ** (2.0 / 3.0) if sigma_x > 0 else 5.0
    w = int(np.clip(np.ceil(w), 5, max(5, n // 20))) | 1
    if n <= w:
        return np.gradient(x, dt)
    return savgol_slope(x, w, dt)


def _moving_speed(x: np.ndarray, dt: float) -> float:
    """The speed of the samples that move: a 1 s ramp in a 32 s record is 3 % of it, and a
    percentile of the whole record would read the hold."""
    lag = max(1, len(x) // 400)  # differences over a few hundredths of the record see through the noise
    coarse = np.abs(x[lag:] - x[:-lag]) / (lag * dt)
    top = float(np.max(coarse))
    moving = coarse[coarse > 0.2 * top]
    return float(np.median(moving)) if len(moving) else (top or 1.0)


def _exact_rate(x: np.ndarray, dt: float, step: float) -> np.ndarray | None:
    """The rate of a position that is exact, or None when it is not.

    Exact: its second differences vanish (below EXACT_FRACTION of a moving sample's travel
    `step`: the rounding of the digits written) everywhere but at a few corners, each one sample
    (a corner at a sample) or two bent the same way (a corner between two samples). Sensor noise
    bends every sample; an encoder step bends two neighbours opposite ways (up one count, then
    level). There a smoothing window would only round the corners the protocol put there.

    The models read v as linear between samples (`rig.models.core.lag_coefficients`), from rest,
    and count it only in contact (x > 0). The true rate is constant over each interval and jumps
    at a corner, which no such v describes exactly; the central difference v_i = (x_{i+1} -
    x_{i-1}) / (2 dt), the mean of the two intervals' rates, is the one whose integral between
    samples gives back x at every sample but the corners themselves (x_i - d2_i / 4 there), and
    that, at a jump, gives the fastest parts of the tissue (which follow the rate itself) the
    mean of its two sides. The one-sided (per-interval) rates are worse: the backward difference
    is the ramp's displacement half a sample late for every slower part, the forward half a
    sample early.
    At the sample where x enters contact the models drop the rate (x is 0 there, not > 0): the
    half interval of indentation it carries would be lost, a displacement missing for the rest of
    the record, so it moves to the first sample in contact.
    On an exact fractional Maxwell record (k 0.03 N/m, tau 13 samples, alpha 0.3; 10 um in 1 s
    from rest at the surface, 256 Hz) the model at the truth then misses by 0.26x its 0.07 nN
    noise over the ramp (3.1x at the two corner samples alone) and 0.01x over the hold; without
    the move at contact 2.7x and 1.6x; with either one-sided rate 2.7x over the ramp; with the
    smoothing window 3.8x."""
    d2 = np.diff(x, 2)
    bent = np.flatnonzero(np.abs(d2) > EXACT_FRACTION * step)
    if len(bent) > max(8, len(x) // EXACT_CORNERS):
        return None
    for corner in np.split(bent, np.flatnonzero(np.diff(bent) > 1) + 1):
        if len(corner) > 2 or (len(corner) == 2 and np.sign(d2[corner[0]]) != np.sign(d2[corner[1]])):
            return None
    v = np.gradient(x, dt)
    indent = np.maximum(x, 0.0)
    enter = np.flatnonzero((x[1:-1] <= 0.0) & (x[2:] > 0.0)) + 1
    v[enter + 1] += (indent[enter + 1] - indent[enter - 1]) / (2.0 * dt)
    return v


def savgol_slope(x: np.ndarray, w: int, dt: float) -> np.ndarray:
    """The slope of a quadratic least-squares fit over `w` samples (odd): Savitzky-Golay's
    first derivative, with the edges from the fit to the first and last window, as
    `scipy.signal.savgol_filter(x, w, 2, deriv=1, mode="interp")` gives it. At a window's
    centre a quadratic's slope is the straight line's, so the interior is one convolution;
    written here because importing scipy.signal costs `rig analyze` 0.7 s."""
    h = w // 2
    j = np.arange(-h, h + 1, dtype=float)
    out = np.empty(len(x))
    out[h:len(x) - h] = np.convolve(x, j[::-1] / (float(j @ j) * dt), mode="valid")
    k = np.arange(w, dtype=float)
    for edge, first, at in ((x[:w], 0, k[:h]), (x[-w:], len(x) - h, k[w - h:])):
        c2, c1, _ = np.polyfit(k, edge, 2)
        out[first:first + h] = (2.0 * c2 * at + c1) / dt
    return out


def _drop_short_runs(mask: np.ndarray, k: int, value: bool) -> np.ndarray:
    """`mask` with every run of `value` shorter than `k` samples flipped (not at the ends)."""
    out = mask.copy()
    edges = np.flatnonzero(np.diff(np.concatenate([[False], mask == value, [False]]).astype(np.int8)))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if b - a < k and a > 0 and b < len(mask):
            out[a:b] = not value
    return out


def _split_holds(t: np.ndarray, hold: np.ndarray, phase: np.ndarray) -> None:
    idx = np.flatnonzero(hold)
    if len(idx) == 0:
        return
    breaks = np.flatnonzero(np.diff(idx) > 1)
    for seg in np.split(idx, breaks + 1):
        span = t[seg[-1]] - t[seg[0]]
        early = t[seg] - t[seg[0]] < HOLD_EARLY_FRACTION * span
        phase[seg[early]] = "hold_early"
        phase[seg[~early]] = "hold_late"


def phases_from_steps(t: np.ndarray, kinds: np.ndarray) -> np.ndarray:
    """Each sample's phase from the protocol step it belongs to: ramp (a force ramp too), hold_early and
    hold_late (a force hold too: it creeps as a hold relaxes), return."""
    phase = np.full(len(t), "", dtype=object)
    # a force-controlled ramp loads as a ramp does, a force hold relaxes (creeps) as a hold
    phase[(kinds == "ramp") | (kinds == "ramp_force")] = "ramp"
    phase[kinds == "return"] = "return"
    _split_holds(t, (kinds == "hold") | (kinds == "hold_force"), phase)
    return phase


def phases_from_motion(t: np.ndarray, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Each sample's phase from the motion alone, for records without steps: moving inwards in
    contact a ramp, outwards the return, standing still deeper than 2 % of the deepest a hold (split
    early and late); runs shorter than a hundredth of the record are ignored."""
    contact = x > 0
    vmax = float(np.percentile(np.abs(v[contact]), 99)) if np.any(contact) else float(np.max(np.abs(v)))
    moving = np.abs(v) > MOVING_FRACTION * vmax
    # a blip shorter than a hundredth of the record is noise, not a step: open, then close
    k = max(3, len(t) // 100)
    moving = _drop_short_runs(_drop_short_runs(moving, k, True), k, False)
    phase = np.full(len(t), "", dtype=object)
    phase[moving & (v > 0) & contact] = "ramp"
    phase[moving & (v < 0) & contact] = "return"
    _split_holds(t, ~moving & (x > 0.02 * np.max(x)), phase)
    return phase
