"""Where a record's contact starts and ends, found from its force (nanite's poc.py is the model): a
first placement that the fit refines as a parameter (rig.models.catalogue.CONTACT_POINT), the
end of contact on the way out, and the pull-off that adhesion leaves after it."""

from __future__ import annotations

import numpy as np

from rig.analysis.stats.line import fit_line, off_line
from rig.analysis.stats.noise import MIN_BASELINE, quiet_length
from rig.errors import SpecError
from rig.records.units import FORCE_DISPLAY, LENGTH_DISPLAY, display_unit

LOAD_FRACTION = 0.1  # the force has clearly risen at a tenth of its peak


def find_contact(t, pos, f, where):
    """Loading direction, the force at rest, and the contact point (or a preload).

    Force and position are turned so that loading is positive (compression read as
    negative force, tension, heights that fall as the tip goes in). The force at rest is the
    level before it rises; contact is first placed where the force last left that level before
    rising to a tenth of its peak, a threshold that a soft or stiffening specimen crosses late,
    so each fit refines it. When the force rises with the first motion the specimen was
    preloaded: the position's zero is the start and the model describes the force above the
    preload. Returns the position from contact, the force, the force at rest before contact,
    a note, and the level at rest (None for a preload, which is subtracted).
    """
    n = len(f)
    head = max(5, n // 100)
    f0 = float(np.median(f[:head]))
    # the deepest point of the travel decides the directions (adhesion on the way out can pull
    # harder than the specimen pushed, so the force's own extreme does not)
    excursion = np.abs(pos - pos[0])
    if float(np.max(excursion)) <= 0:
        raise SpecError("no contact: the position never moves", path=where)
    k_deep = int(np.argmax(excursion >= 0.99 * np.max(excursion)))
    near = slice(max(k_deep - head, 0), k_deep + head + 1)
    if float(np.median(f[near])) < f0:
        f = -f
        f0 = -f0
    if pos[k_deep] < pos[0]:
        pos = -pos
    travel = float(np.max(pos) - pos[0])
    k_peak = int(np.argmax(f[: k_deep + head + 1]))
    rise = float(f[k_peak] - f0)
    if rise <= 0:
        raise SpecError("no contact: the force never rises from its starting level", path=where)
    loaded = np.flatnonzero(f - f0 > LOAD_FRACTION * rise)
    i_load = int(loaded[0])
    i_move = _rest_stretch(pos, head)
    f_rest = float(np.median(f[:i_move]))
    rest = f[:i_move] - f_rest
    sigma_rest = 1.4826 * float(np.median(np.abs(rest))) if i_move >= 10 else 0.0
    # the last time before loading that the force sat at its resting level
    level = max(3.0 * sigma_rest, 0.005 * rise)
    still = np.flatnonzero(f[i_move:i_load + 1] - f_rest <= level)
    i_leave = i_move + (int(still[-1]) + 1 if len(still) else 0)
    if pos[i_leave] - pos[i_move] < 0.02 * travel:
        # the force rises with the first motion: the probe starts in contact
        x = pos - pos[i_move - 1]  # from where it stood
        note = (f"starts in contact: the force at rest, {force_words(f_rest)} (a preload, or the sensor's "
                "zero), is subtracted; the model describes the force above it")
        return x, f - f_rest, rest if i_move >= MIN_BASELINE else np.array([]), note, None
    # the resting level (with its slow drift) from the first two thirds of the approach: the
    # last third may already carry the first touch
    i_fit = max(2 * i_load // 3, 1)
    pre = f[:i_fit]
    slope, at_start = fit_line(t[:i_fit] - t[0], pre) if i_fit >= 20 else (0.0, float(np.median(pre)))
    trend = slope * (t - t[0]) + at_start
    resid = pre - trend[:i_fit]
    sigma = 1.4826 * float(np.median(np.abs(resid - np.median(resid)))) if i_fit >= 10 else 0.0
    lifted = (f - trend)[:k_peak + 1]
    # the last time before loading that the force sat at its resting level
    quiet = np.flatnonzero(lifted[:i_load + 1] <= 2.0 * sigma)
    i_quiet = int(quiet[-1]) if len(quiet) else 0
    # a slow creep off the baseline (drag, long-range forces) can leave that level long before
    # the touch: extend the first clear rise (5 % to 15 % of the peak) back to zero force
    i5 = i_quiet + int(np.argmax(lifted[i_quiet:] > 0.5 * LOAD_FRACTION * rise))
    i15 = i5 + int(np.argmax(lifted[i5:] > 1.5 * LOAD_FRACTION * rise))
    i_c = i_quiet
    if i15 > i5 and pos[i15] > pos[i5]:
        slope = (lifted[i15] - lifted[i5]) / (pos[i15] - pos[i5])
        x_touch = pos[i5] - lifted[i5] / slope if slope > 0 else pos[i_quiet]
        if x_touch > pos[i_quiet]:
            i_c = i_quiet + int(np.argmax(pos[i_quiet:i5 + 1] >= x_touch))
    level = f_rest if i_move >= 10 else f0  # before the probe moved, else its first samples
    x = pos - pos[i_c]
    # Nothing is subtracted: every fit places this record's contact point and its zero itself
    # (rig.analysis.fitting.fit.with_record_params), and a drift or friction shows in the residual
    # before contact. The noise is measured on the quiet part of the approach before the first
    # estimate (rig.analysis.stats.noise.quiet_length): a first touch and a slow rise are left out.
    baseline = f[:quiet_length(f[:i_c])]
    note = (f"contact first placed at {length_words(pos[i_c] - pos[0])} of travel, t = {t[i_c] - t[0]:.4g} s "
            f"(the fit refines it); force at rest {force_words(level)}, kept")
    return x, f, baseline, note, level


def end_of_contact(x: np.ndarray, f: np.ndarray) -> int:
    """The first sample where, after the deepest point, the probe is back at the contact point
    or the force back at its baseline (whichever comes first): that sample reads no push, and
    keeping it would pin a fit to where the model's force reaches the no-pull clamp."""
    k_deep = len(x) - 1 - int(np.argmax(x[::-1] >= 0.99 * np.max(x)))  # the last time at depth
    out = np.flatnonzero((x[k_deep:] <= 0.0) | (f[k_deep:] <= 0.0))
    return k_deep + int(out[0]) if len(out) else len(x)


PULL_SIGMA = 5.0  # a dip below the baseline this many noise deviations deep is a pull, not noise


PULL_RUN = 5  # held for at least this many samples below 3 deviations


def end_of_pull(f: np.ndarray, end: int, baseline) -> int:
    """Where a pull on the way out ends (`f` from its baseline; `end` where the push ends): if
    the force dips clearly below its baseline after `end` (the tip stuck to the specimen), the
    sample after it is back, plus as much free travel again as the pull lasted (the baseline
    the pull-off is measured from); else `end`."""
    base = np.asarray(baseline, dtype=float)
    if end >= len(f) or len(base) < MIN_BASELINE:
        return end
    detr = detrend(base)
    sigma = 1.4826 * float(np.median(np.abs(detr - np.median(detr))))
    tail = f[end:]
    if sigma <= 0 or float(np.min(tail)) > -PULL_SIGMA * sigma or np.sum(tail < -3.0 * sigma) < PULL_RUN:
        return end
    k_min = int(np.argmin(tail))
    back = np.flatnonzero(tail[k_min:] > -3.0 * sigma)
    if not len(back):
        return end  # never back at the baseline: not a pull that lets go (drag, a tilted baseline)
    let_go = end + k_min + int(back[0])
    return min(let_go + (let_go - end), len(f))


def _rest_stretch(pos: np.ndarray, head: int) -> int:
    span = float(np.ptp(pos)) or 1.0
    moving = np.flatnonzero(np.abs(pos - pos[0]) > 1e-3 * span)
    return max(int(moving[0]) if len(moving) else head, 1)


def force_words(v: float) -> str:
    """A force in the unit that reads best for its size (nN to N), four figures."""
    k, u = display_unit(abs(v), FORCE_DISPLAY)
    return f"{v / k:.4g} {u}"


def length_words(v: float) -> str:
    """A length in the unit that reads best for its size (nm to mm), four figures."""
    k, u = display_unit(abs(v), LENGTH_DISPLAY)
    return f"{v / k:.4g} {u}"


def detrend(y: np.ndarray) -> np.ndarray:
    """`y` with its least-squares line taken off (for the scatter of a baseline that drifts)."""
    return off_line(np.linspace(-1.0, 1.0, len(y)), y)
