"""A parametric bootstrap through the whole pipeline: what the analysis would report on records
that are the fitted model plus the measured noise.

Each draw is a record written anew: the fitted model's force on the record's own motion, the
noise drawn from the measured spectrum (rig.analysis.stats.noise) and quantised on the record's own
lattice, and, for a record that sat at rest before contact, a new tare. It then goes through
everything a record goes through: the contact found again (for a record that does not know
its surface), the noise measured again, the model fitted again from the catalogue's starts,
the verdict judged again. Over the draws that gives what no single fit can: each parameter's
bias, the scatter of its estimates against the standard error reported, how often
+/-1.96 SE held the value the draws were made from, and how often the verdict stayed the same.

The draws are made from the fitted model, so they answer "if the model were right": for a
model that is not adequate, the draws are adequate and the verdict does not stay (that is the
answer: the misfit is not noise).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from rig.analysis.fitting.fit import FitResult, fit
from rig.analysis.stats.adequacy import quantise, simulate
from rig.analysis.trials.data import TrialData, prepare
from rig.errors import RigError
from rig.models.catalogue import CONTACT_POINT
from rig.records.record import Record
from rig.specs.frames import Frame

Z95 = 1.959964


@dataclass
class ParamSummary:
    """One parameter over the bootstrap's draws: the fitted value (each draw's truth), the estimates' mean
    and scatter, the standard error the fits reported on average, and how often +/-1.96 SE held the truth."""

    value: float  # as fitted to the record: the draws' truth
    mean: float
    sd: float  # scatter of the estimates over the draws
    mean_stderr: float  # the standard error the fits reported, on average
    coverage: float  # fraction of draws whose +/-1.96 SE held `value`

    @property
    def bias(self) -> float:
        return self.mean - self.value

    def as_dict(self) -> dict:
        return {"value": self.value, "mean": self.mean, "bias": self.bias, "sd": self.sd,
                "mean_stderr": self.mean_stderr, "coverage_95": self.coverage}


@dataclass
class Bootstrap:
    """What the parametric bootstrap found: the draws, each parameter's summary, how often the verdict came
    out as it did on the record, and why any draw could not be fitted."""

    draws: int
    params: dict[str, ParamSummary]
    verdict_kept: float  # fraction of draws judged as the record was (adequate or not)
    adequate: float  # fraction of draws judged adequate
    failed: list[str] = field(default_factory=list)  # why a draw could not be fitted

    def as_dict(self) -> dict:
        return {"draws": self.draws, "fitted": self.draws - len(self.failed), "failed": self.failed,
                "verdict_kept": self.verdict_kept, "adequate": self.adequate,
                "parameters": {k: p.as_dict() for k, p in self.params.items()}}


def redraw(trial: TrialData, prediction: np.ndarray, res: FitResult, rng: np.random.Generator) -> Record:
    """The record as it would read if `prediction` were the truth, with a fresh draw of the noise."""
    noise = res.noise
    m = trial.motion
    force = quantise(prediction + simulate(noise, trial.n, 1, rng)[0], noise)
    tare = None
    known = trial.contact_m is None
    if known and trial.baseline_N is not None:  # the tare before the record
        level = float(np.mean(trial.baseline_N))
        tare = quantise(level + simulate(noise, len(trial.baseline_N), 1, rng)[0], noise)
    # a record that did not know its surface gets its travel from the first sample back
    position = m.x_m if known else m.x_m - m.x_m[0]
    return Record(trial.name, trial.source, m.t_s.copy(), position.copy(), force,
                  Frame.SURFACE if known else None, baseline_force_N=tare)


def bootstrap(res: FitResult, draws: int, seed: int = 0,
              progress: Callable[[int, int], None] | None = None) -> Bootstrap:
    """`draws` records redrawn from `res` and analysed as `res`'s were."""
    if res.noise is None or res.noise.std_N <= 0:
        raise RigError("--bootstrap: the record's noise could not be measured: there is nothing to draw from")
    rng = np.random.default_rng(seed)
    values: dict[str, list[float]] = {k: [] for k in res.values}
    errors: dict[str, list[float]] = {k: [] for k in res.values}
    kept = adequate = 0
    failed = []
    for i in range(draws):
        try:
            trials = [prepare(redraw(t, p, res, rng)) for t, p in zip(res.trials, res.predictions, strict=True)]
            b = fit(res.model, trials)
        except RigError as exc:
            failed.append(f"draw {i + 1}: {exc}")
        else:
            for k in values:
                values[k].append(b.values.get(k, math.nan) + _origin(k, b))
                e = b.stderr.get(k)
                errors[k].append(math.nan if e is None else e)
            kept += b.adequate == res.adequate
            adequate += b.adequate
        if progress:  # a draw that failed is done too
            progress(i + 1, draws)
    n = draws - len(failed)
    if n == 0:
        raise RigError(f"--bootstrap: no draw could be fitted ({failed[0]})")
    params = {}
    for k, v in values.items():
        v_arr, e_arr = np.array(v), np.array(errors[k])
        truth = res.values[k] + _origin(k, res)
        ok = np.isfinite(e_arr)
        held = np.abs(v_arr[ok] - truth) <= Z95 * e_arr[ok]
        sd = float(np.std(v_arr, ddof=1)) if n > 1 else math.nan
        se = float(np.mean(e_arr[ok])) if ok.any() else math.nan
        cover = float(np.mean(held)) if ok.any() else math.nan
        params[k] = ParamSummary(truth, float(np.mean(v_arr)), sd, se, cover)
    return Bootstrap(draws, params, kept / n, adequate / n, failed)


def _origin(name: str, res: FitResult) -> float:
    """A contact point is fitted from its record's first estimate, which each draw finds anew:
    compared in the travel from the record's first sample instead."""
    base, _, i = name.partition("@")
    if base != CONTACT_POINT.params[0].name:
        return 0.0
    return res.trials[int(i) if i else 0].contact_m or 0.0


def format_bootstrap(b: Bootstrap, res: FitResult) -> str:
    """The bootstrap in words: the verdict's stability, then each parameter's bias, scatter and reported
    error beside it."""
    fitted = b.draws - len(b.failed)
    lines = [f"bootstrap: {fitted} records redrawn from the fitted model and the measured noise, each analysed "
             "as this one (contact, noise, fit, verdict)",
             f"  verdict the same in {100 * b.verdict_kept:.0f} % of draws "
             f"({'adequate' if res.adequate else 'NOT adequate'} here; "
             f"adequate in {100 * b.adequate:.0f} % of draws)",
             f"  {'parameter':<20}{'fitted':>12}{'bias':>12}{'scatter':>12}{'mean SE':>12}{'SE/scatter':>11}"
             f"{'95% held':>10}"]
    for name, p in b.params.items():
        ratio = p.mean_stderr / p.sd if p.sd and p.sd > 0 else math.nan
        lines.append(f"  {name:<20}{p.value:>12.5g}{p.bias:>+12.3g}{p.sd:>12.3g}{p.mean_stderr:>12.3g}"
                     f"{ratio:>11.2f}{100 * p.coverage:>9.0f}%")
    if b.failed:
        lines.append(f"  {len(b.failed)} draw(s) could not be analysed: {b.failed[0]}")
    noise = res.noise.describe() if res.noise is not None else "unmeasured"
    lines.append(f"  the draws' noise: {noise}")
    if not res.adequate:
        # redrawn from the fitted model, every draw is a record the model fits: what the model
        # misses is in none of them, so "held" cannot speak for this record's own errors
        lines.append("  the model is NOT adequate here: the draws come from it, so they check the statistical "
                     "errors as if it were right; what it misses (the systematic error, sys) is in no draw, "
                     "and this coverage cannot be checked on this record")
    return "\n".join(lines)
