"""Profile-likelihood intervals for parameters that trade off.

Where two parameters trade off (the cubic's three terms, a fractional branch's k, tau and alpha)
the cost is a curved valley, and +/-1.96 standard errors (its curvature at the bottom) can be
far from where the valley actually rises: the interval is lopsided, or reaches a bound. The
profile walks along the valley: the parameter is held at a value, every other one refitted,
and the interval is where the cost has risen by the 95 % point of chi-square with one degree
of freedom, counted on the fit's one effective sample count: the records' samples over the
noise's correlation time (rig.analysis.stats.criterion, the count the BIC is on), so a correlated
noise widens it as it does the standard error, and a misfit does not: like the statistical
error it is the noise's, given the model; how far the model's misses move a value is the
systematic error's (rig.analysis.intervals.systematic). Counted on the residual's own correlation, a
misfitting curve's profile was 4-140x wider than its +/-1.96 SE on real AFM curves.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from rig.analysis.fitting.fit import FitResult, fit
from rig.models.core import Model, Param

CHI2_95 = 3.841459  # one degree of freedom
TRADE_OFF = 0.9  # |correlation| with another parameter from which an interval is profiled
MAX_STEPS = 12  # outward steps per side before the interval is called open


@dataclass
class Interval:
    """A profile-likelihood interval: where the cost, the other parameters refitted, has risen by chi-square
    3.84 on each side (None where it does not before the parameter's bound), beside the Wald interval, and
    the fits it took."""

    name: str
    value: float
    low: float | None  # None: the cost does not rise that far before the parameter's bound
    high: float | None
    wald: tuple[float, float]  # +/-1.96 standard errors, for comparison
    fits: int

    def as_dict(self) -> dict:
        return {"value": self.value, "low": self.low, "high": self.high, "wald_low": self.wald[0],
                "wald_high": self.wald[1]}


def trading(res: FitResult) -> list[str]:
    """The model's own parameters correlated with another by at least TRADE_OFF."""
    own = {p.name for p in res.model.params if not p.per_record}
    names = {a for a, b, c in res.correlations(TRADE_OFF) if a in own} | \
        {b for a, b, c in res.correlations(TRADE_OFF) if b in own}
    return [p.name for p in res.model.params if p.name in names]


def _held(model: Model, name: str, value: float) -> Model:
    def hold(p: Param) -> Param:
        if p.name != name:
            return p
        tol = max(abs(value) * 1e-9, 1e-300)
        return replace(p, init=value, lo=value - tol, hi=value + tol, relative=False)

    return Model([replace(e, params=tuple(map(hold, e.params))) for e in model.effects], model.name,
                 model.records)


def interval(res: FitResult, name: str) -> Interval:
    """The 95 % profile-likelihood interval of `name`."""
    v0 = res.values[name]
    rss0 = res.overall.n * res.overall.rmse_N ** 2
    se = res.stderr.get(name)
    step0 = se if se and math.isfinite(se) and se > 0 else max(abs(v0) * 0.1, 1e-12)
    p = next(q for q in res.model.params if q.name == name)
    lo_bound, hi_bound = _si_bounds(res, p)
    fits = 0
    # the records' tared zeros add a variance no cost shows (`FitResult.zero_variance`): the
    # threshold grows by the standard error's share from them, as the Wald interval does
    share = res.zero_variance.get(name, 0.0)
    widen = se ** 2 / (se ** 2 - share) if se and math.isfinite(se) and se ** 2 > share > 0.0 else 1.0
    threshold = CHI2_95 * widen

    def rise(v: float) -> float:
        nonlocal fits
        fits += 1
        b = fit(_held(res.model, name, v), res.trials, starts=1, initial=res.values)
        return res.bic_samples * math.log(max(b.overall.n * b.overall.rmse_N ** 2, 1e-300) / rss0) - threshold

    def side(sign: float) -> float | None:
        inside, step = v0, step0
        for _ in range(MAX_STEPS):
            v = v0 + sign * step
            if not lo_bound < v < hi_bound:
                v = (lo_bound if sign < 0 else hi_bound) - sign * 1e-9 * max(abs(v0), 1e-300)
                if rise(v) < 0:
                    return None
                return _crossing(rise, inside, v)
            if rise(v) >= 0:
                return _crossing(rise, inside, v)
            inside, step = v, 2.0 * step
        return None

    low, high = side(-1.0), side(1.0)
    wald = (v0 - 1.959964 * step0, v0 + 1.959964 * step0)
    return Interval(name, v0, low, high, wald, fits)


def _crossing(rise: Callable[[float], float], inside: float, outside: float, steps: int = 8) -> float:
    """Where `rise` crosses zero between a point below (inside) and one above (outside): bisection,
    to about 1/256 of the bracket (the interval's ends are read to two or three digits)."""
    a, b = inside, outside
    for _ in range(steps):
        m = 0.5 * (a + b)
        if rise(m) < 0:
            a = m
        else:
            b = m
    return 0.5 * (a + b)


def _si_bounds(res: FitResult, p: Param) -> tuple[float, float]:
    """The parameter's bounds in SI (relative ones scaled by the record's own units)."""
    from rig.analysis.fitting.scaling import ParamScaling

    ps = ParamScaling(res.model, res.scales)
    i = res.model.param_names.index(p.name)
    scale = ps.scale_vector(res.values.get("n", 0.0))[i]
    lo, hi = (p.lo * scale, p.hi * scale) if p.relative else (p.lo, p.hi)
    return (lo if np.isfinite(lo) else -math.inf), (hi if np.isfinite(hi) else math.inf)


def intervals(res: FitResult, names: list[str] | None = None,
              progress: Callable[[str], None] | None = None) -> list[Interval]:
    """Profile intervals of the parameters `names` (None: those that trade off, |correlation| >= 0.9);
    `progress` is told each name as it starts."""
    out = []
    for name in names if names is not None else trading(res):
        if progress:
            progress(name)
        out.append(interval(res, name))
    return out


def format_intervals(found: list[Interval], res: FitResult, asked: bool = False) -> str:
    """The profile intervals beside +/-1.96 SE, one line a parameter in its unit; says so when no parameter
    trades off."""
    if not found:
        return ("profile: no parameters trade off (|correlation| >= 0.9); --profile NAME profiles any of them "
                f"(here: {', '.join(p.name for p in res.model.params)})")
    units = {p.name: p.unit for p in res.model.params}
    which = "the parameters asked for" if asked else "parameters that trade off"
    lines = [f"profile 95 % intervals ({which}; each end where the cost has risen by chi-square 3.84 with the "
             "others refitted), beside +/-1.96 SE (stat):"]
    for iv in found:
        low = f"{iv.low:.4g}" if iv.low is not None else "(its bound)"
        high = f"{iv.high:.4g}" if iv.high is not None else "(its bound)"
        lines.append(f"  {iv.name:<20} {iv.value:>11.4g}  [{low}, {high}]   +/-1.96 SE: "
                     f"[{iv.wald[0]:.4g}, {iv.wald[1]:.4g}]  {units[iv.name]}")
    return "\n".join(lines)
