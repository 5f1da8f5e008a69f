"""The systematic error of a contact fit: how far the parameters move over the choices a
researcher would otherwise make by hand.

A standard error is the noise's, given the model. When the model misses the curve's shape (a
thin layer, a substrate underneath, a tip that is not the paraboloid it is taken for), the
modulus depends on how much of the curve is fitted: on real AFM curves dropping the deepest
18 of 4141 samples moved E by 55 standard errors, and keeping less of a tilted baseline by
more. No standard error can show that, since it is not noise. So the fit is repeated over the
defensible choices (the approach up to 50 % and up to 75 % of its peak force, and the
baseline's first half left out) and each parameter's systematic error is the largest shift
those refits show beyond what their own noise explains:

    shift_c = value_c - value;  its noise sd_c = sqrt(SE_c^2 - SE^2)

(a refit on part of the same samples: the difference of two nested estimates has the variance
of the difference of their variances; floored at a third of SE_c, where the two noise models
differ). A choice counts when |shift_c| > SIGNIFICANT sd_c, and then adds |shift_c| + 1.96 sd_c
(its own noise on top: what is wanted is the value the choice gives on the noiseless curve).
Where the model fits, the shifts are the noise's and the systematic error is nought (a curve
counts a choice by chance about once in a hundred, at 3 sd); where it does not, the interval

    value +/- (1.96 stat + sys)

holds the value each of the fits would give on the noiseless curve. The two are added, not
combined in quadrature: the systematic error is a range over choices, not a standard deviation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from rig.analysis.fitting.fit import FitResult, fit_estimates
from rig.analysis.trials.data import TrialData
from rig.models.core import Motion

# a choice's shift counts beyond this many of its own noise's SD: at 2 about one curve in seven that
# the model fits counted a choice by chance over the three, and its interval grew three- to
# fourfold; at 3 one in a hundred or so, while a misfit that matters moves E by tens of SDs
SIGNIFICANT = 3.0
FLOOR = 1.0 / 3.0  # the shift's noise is at least this share of the refit's standard error
MIN_SAMPLES = 20  # a refit on fewer samples than this (or a baseline shorter) is not made
DEPTH_SHARES = (0.5, 0.75)  # of the peak force: where the shallower fits end
Z95 = 1.959964

__all__ = ["Choice", "Systematic", "interval", "systematic"]


@dataclass
class Choice:
    """One refit: what was chosen, its values and standard errors, and which shifts counted."""

    name: str
    samples: int
    values: dict[str, float]
    stderr: dict[str, float | None]
    counted: dict[str, bool] = field(default_factory=dict)

    def as_dict(self, base: dict[str, float]) -> dict:
        return {"choice": self.name, "samples": self.samples,
                "values": {k: v for k, v in self.values.items() if k in base},
                "shifts": {k: self.values[k] - base[k] for k in base if k in self.values},
                "stderr": {k: _finite(v) for k, v in self.stderr.items() if k in base},
                "counted": self.counted}


@dataclass
class Systematic:
    """Per parameter, the systematic error (0 where no choice moved it beyond its noise), and
    the refits it comes from."""

    error: dict[str, float]
    choices: list[Choice]
    values: dict[str, float]
    not_made: list[str] = field(default_factory=list)  # refits the curve did not allow, and why

    def as_dict(self) -> dict:
        return {"rule": f"the largest shift over the choices that exceeds {SIGNIFICANT:g} times its own "
                        "noise's SD, plus 1.96 times that SD; "
                        "interval: value +/- (1.96 stat + sys)",
                "error": self.error, "choices": [c.as_dict(self.values) for c in self.choices],
                "not_made": self.not_made}

    def why(self, name: str) -> str:
        """The choices that set `name`'s systematic error, in words ('' when none counted)."""
        return ", ".join(c.name for c in self.choices if c.counted.get(name))


def _finite(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


def interval(value: float, stat: float | None, sys: float | None) -> tuple[float, float] | None:
    """The reported interval: value +/- (1.96 stat + sys)."""
    if stat is None or not math.isfinite(stat):
        return None
    half = Z95 * stat + (sys or 0.0)
    return value - half, value + half


def cut(t: TrialData, start: int, end: int) -> TrialData:
    """Samples [start, end) of a prepared trial, its baseline kept where it is still the record's
    own first samples."""
    m = t.motion
    sl = slice(start, end)
    motion = Motion(m.t_s[sl], m.x_m[sl], m.v_m_s[sl], m.dt_s, m.record)
    q = t.quiet_n
    base = t.baseline_N
    if q and start:
        base = t.force_N[start:q] if q - start >= 2 else None
    return replace(t, motion=motion, force_N=t.force_N[sl], phase=t.phase[sl], scales=t.scales,
                   baseline_N=base, baseline_n=len(base) if base is not None else 0,
                   held=t.held[sl] if t.held is not None else None,
                   held_force_N=t.held_force_N[sl] if t.held_force_N is not None else None,
                   contact_m=(t.contact_m or 0.0) + float(m.x_m[start] - m.x_m[0]) if start else t.contact_m)


def _choices(res: FitResult, not_made: list[str] | None = None) -> list[tuple[str, int, int]]:
    """(what, start, end) of each refit this curve allows; each one it does not, with why, to
    `not_made`."""
    t = res.trials[0]
    f = t.force_N
    pred = res.predictions[0]
    zero = float(pred[0])
    peak = int(np.argmax(f - zero))
    rise = f[:peak + 1] - zero
    contact = _contact_index(res)
    out = []
    for share in DEPTH_SHARES:
        what = f"to {share * 100:.0f} % of peak"
        end = int(np.argmax(rise >= share * rise[-1])) + 1 if rise[-1] > 0 else 0
        # before the contact the fit has nothing to say about the modulus
        if end - contact >= MIN_SAMPLES and end < t.n:
            out.append((what, 0, end))
        elif not_made is not None and end < t.n:
            not_made.append(f"{what} ({max(end - contact, 0)} samples in contact, fewer than {MIN_SAMPLES})")
    if contact >= 2 * MIN_SAMPLES:
        out.append(("baseline halved", contact // 2, t.n))
    elif not_made is not None and contact:
        not_made.append(f"baseline halved ({contact} samples before contact, fewer than "
                        f"{2 * MIN_SAMPLES})")
    return out


def _contact_index(res: FitResult) -> int:
    """The first sample past the fitted contact point (0 when the model has none)."""
    t = res.trials[0]
    x_c = next((v for k, v in res.values.items() if k.partition("@")[0] == "x_c_m"), None)
    if x_c is None:
        return 0
    return int(np.searchsorted(np.maximum.accumulate(t.motion.x_m), x_c))


def systematic(res: FitResult) -> Systematic | None:
    """The refits over `CHOICES` of a one-curve fit and each parameter's systematic error, or
    None when the fit is not one curve's."""
    if len(res.trials) != 1 or res.trials[0].creep:
        return None
    names = [k for k in res.values if res.stderr.get(k) is not None and math.isfinite(res.stderr[k])]
    error = dict.fromkeys(names, 0.0)
    choices: list[Choice] = []
    not_made: list[str] = []
    for what, start, end in _choices(res, not_made):
        part = cut(res.trials[0], start, end)
        try:
            got = fit_estimates(res.model, [part], starts=1, initial=res.values)
        except (ValueError, np.linalg.LinAlgError, FloatingPointError):
            continue
        c = Choice(what, part.n, got.values, got.stderr)
        for k in names:
            if k not in got.values:
                continue
            se, se_c = res.stderr[k], got.stderr.get(k)
            if se_c is None or not math.isfinite(se_c):
                continue
            shift = got.values[k] - res.values[k]
            sd = math.sqrt(max(se_c ** 2 - se ** 2, (FLOOR * se_c) ** 2))
            c.counted[k] = abs(shift) > SIGNIFICANT * sd
            if c.counted[k]:
                # the refit's own noise on top: the interval must hold what the refit would give on
                # the noiseless curve, not only the value it gave on this one
                error[k] = max(error[k], abs(shift) + Z95 * sd)
        choices.append(c)
    return Systematic(error, choices, {k: res.values[k] for k in names}, not_made)
