"""What a fit found, and how far to trust it (`FitResult`): the values with their errors and
correlations, the residual and the error by phase, the noise it was judged against, the verdict,
the warnings, and the result as a readable report (lmfit's `fit_report`) and as plain data
(`as_dict`). The fit itself is `rig.analysis.fitting.fit`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from rig.analysis.stats import criterion
from rig.analysis.stats.adequacy import ADEQUATE_PHASE, ADEQUATE_RMSE, ADEQUATE_WHITE, Limits, whitened_scale
from rig.analysis.stats.adequacy import limits as adequacy_limits
from rig.analysis.stats.noise import Noise
from rig.analysis.stats.uncertainty import correlation, notable_correlations
from rig.analysis.trials.data import PHASES, Scales, TrialData
from rig.models.catalogue import CONTACT_POINT, RECORD_ZERO
from rig.models.core import Model

CORRELATION_FLOOR = 0.1  # parameter correlations reported from this size up (lmfit's default)


@dataclass
class ErrorStats:
    """The residual (measured - model) summarised over a set of samples: RMSE, mean, standard
    deviation and count, in newtons."""

    rmse_N: float
    mean_N: float
    std_N: float
    n: int

    @classmethod
    def of(cls, r: np.ndarray) -> ErrorStats | None:
        if len(r) == 0:
            return None
        return cls(float(np.sqrt(np.mean(r ** 2))), float(np.mean(r)), float(np.std(r)), len(r))

    def as_dict(self) -> dict:
        return {"rmse_N": self.rmse_N, "mean_N": self.mean_N, "std_N": self.std_N, "n": self.n}


@dataclass
class FitResult:
    """What `fit` found: the values with their errors, the residual, and how far to trust them.

    - ``model``, ``trials``: what was fitted to what; ``values`` and ``stderr`` per parameter in
      SI (a standard error is None where the record does not determine it), ``covariance`` (SI,
      allowing for correlated residuals) and ``correlations()``.
    - ``predictions`` and ``residuals`` (measured minus model), per trial; ``overall`` and
      ``phases``: the error table; ``per_trial``: the same per record.
    - ``noise_N`` and ``noise``: the sensor noise measured from the record (``noise_source`` says
      where); ``noise_L`` and ``white_L``: the noise's and the residual's correlation times
      (samples); ``n_eff``: the independent residuals (samples over the residual's correlation
      time), the count every comparison of models uses.
    - ``bic`` on ``bic_samples`` effective samples (`rig.analysis.stats.criterion`); ``adequate``
      and ``limits``: whether the residual is at the noise's level, and how far a right model's
      may go.
    - ``warnings``: what the user should read before the numbers (a bound hit, parameters the
      record cannot tell apart, too few independent residuals); ``error_noise``: the noise model
      the standard errors were given; ``zero_variance``: the share of each variance that comes
      from the records' tared zeros.
    - ``nfev`` and ``seconds``: the fit's cost; ``z``: its internal (order-one) variables.
    """

    model: Model
    trials: list[TrialData]
    values: dict[str, float]
    stderr: dict[str, float | None]
    predictions: list[np.ndarray]
    residuals: list[np.ndarray]  # measured - model
    overall: ErrorStats
    phases: dict[str, ErrorStats | None]
    noise_N: float
    noise_source: str
    bic: float
    warnings: list[str]
    seconds: float
    nfev: int
    per_trial: list[dict] = field(default_factory=list)
    white_L: float = 1.0  # integral time scale of the residual, samples
    noise_L: float = 1.0  # integral time scale of the noise, samples
    scales: Scales | None = None
    z: dict[str, float] = field(default_factory=dict)  # the fit variables (order one)
    covariance: np.ndarray | None = None  # of the parameters in SI, allowing for correlated residuals
    n_eff: float = 0.0  # independent residuals: samples over the residual's correlation time
    noise: Noise | None = None  # as measured (rig.analysis.stats.noise)
    bic_samples: float = 0.0  # the effective count `bic` is on: the records' (rig.analysis.stats.criterion)
    # per parameter, the share of its variance that comes from the records' tared zeros
    # (`_zero_variances`): what no residual shows, and a profile's cost cannot see
    zero_variance: dict[str, float] = field(default_factory=dict)
    error_noise: str = ""  # the noise model the standard errors were given (rig.analysis.stats.uncertainty)

    @property
    def correlation(self) -> np.ndarray | None:
        return None if self.covariance is None else correlation(self.covariance)

    def correlations(self, floor: float = 0.1) -> list[tuple[str, str, float]]:
        """Parameter pairs correlated by at least `floor`, largest first."""
        c = self.correlation
        return [] if c is None else notable_correlations(self.model.param_names, c, floor)

    @cached_property
    def limits(self) -> Limits:
        """How far a perfect model's residual may go on these records (rig.analysis.stats.adequacy)."""
        if self.noise is None:
            return Limits(ADEQUATE_RMSE, dict.fromkeys(PHASES, ADEQUATE_PHASE), ADEQUATE_WHITE)
        return adequacy_limits(self.noise, self.predictions, [t.phase for t in self.trials], PHASES)

    @cached_property
    def whitened_L(self) -> float:
        """The residual's correlation time (samples) with the noise's own taken out: on held
        samples (creep form) the position's noise's own (`TrialData.held_noise_ar`)."""
        if self.noise is None:
            return 1.0
        if not any(t.creep for t in self.trials):
            return whitened_scale(self.residuals, self.noise)
        scales, weights = [], []
        for t, r in zip(self.trials, self.residuals, strict=True):
            held = t.held if t.creep else np.zeros(t.n, dtype=bool)
            edges = np.flatnonzero(np.diff(held.astype(np.int8))) + 1
            for piece, h in zip(np.split(r, edges), np.split(held, edges), strict=True):
                if len(piece) < 32:
                    continue
                ar = t.held_noise_ar if h[0] else self.noise.ar
                scales.append(whitened_scale([piece], replace(self.noise, ar=tuple(ar))))
                weights.append(len(piece))
        return float(np.average(scales, weights=weights)) if scales else 1.0

    def _failed(self) -> list[tuple[str, float, float]]:
        """The tests the residual fails: (what, its value, its limit), in the order they are told."""
        noise = max(self.noise_N, 1e-300)
        ratio = self.overall.rmse_N / noise
        if (ratio <= ADEQUATE_RMSE and self.whitened_L <= ADEQUATE_WHITE
                and all(s.rmse_N / noise <= ADEQUATE_PHASE for s in self.phases.values() if s is not None)):
            # within the tolerances themselves, which a perfect model's simulated tail only
            # widens (`Limits` are never below them): passed, without simulating it (a sixth of
            # a map's time a curve, where most curves pass)
            return []
        lim = self.limits
        out = []
        if ratio > lim.rmse:
            out.append(("rmse", ratio, lim.rmse))
        worst = [(s.rmse_N / noise / lim.phase.get(ph, ADEQUATE_PHASE), ph, s.rmse_N / noise,
                  lim.phase.get(ph, ADEQUATE_PHASE)) for ph, s in self.phases.items() if s is not None]
        if worst:
            excess, ph, value, limit = max(worst)
            if excess > 1.0:
                out.append((ph, value, limit))
        if self.whitened_L > lim.white:
            out.append(("correlation", self.whitened_L, lim.white))
        return out

    @property
    def adequate(self) -> bool:
        return not self._failed()

    @property
    def force_unit(self) -> tuple[float, str]:
        return self.trials[0].force_unit

    def force_text(self, value_N: float, signed: bool = False) -> str:
        """A force in the record's own unit (nN for a cell, N for a stomach)."""
        k, u = self.force_unit
        return f"{value_N / k:{'+' if signed else ''}.4g} {u}"

    def _whose(self, name: str) -> str:
        """For a record's own parameter (name@i), the record it belongs to."""
        base, _, i = name.rpartition("@")
        if base and i.isdigit() and int(i) < len(self.trials):
            return f"  ({self.trials[int(i)].name})"
        return ""

    def verdict(self) -> str:
        """"adequate", or which of the three tests failed: the overall RMSE, a phase's, or the
        residual's correlation."""
        failed = self._failed()
        if not failed:
            return "adequate"
        what, value, limit = failed[0]
        ratio = self.overall.rmse_N / max(self.noise_N, 1e-300)
        if what == "rmse":
            return f"NOT adequate (RMSE {ratio:.2g}x the noise, above {limit:.3g}x)"
        if what != "correlation":
            return (f"NOT adequate (RMSE {ratio:.2g}x the noise overall, but {value:.2g}x in {what}, "
                    f"above {limit:.3g}x)")
        return f"NOT adequate (RMSE {ratio:.2g}x the noise, but {self.inadequate_because()})"

    def inadequate_because(self) -> str:
        """What fails a fit whose overall error passes: a phase's error or the residual's correlation
        ("" when the fit is adequate or its overall error is what fails). A residual at or below the
        noise can still hold a shape the model misses, and a verdict must say so, not only the RMSE."""
        failed = self._failed()
        if not failed or failed[0][0] == "rmse":
            return ""
        what, value, limit = failed[0]
        if what != "correlation":
            return f"{value:.2g}x the noise in {what}, above {limit:.3g}x"
        return (f"the residual is correlated over {value:.1f} samples beyond the noise's own correlation, "
                f"where a perfect model's is within {limit:.2g}: a shape the model misses")

    def report(self) -> str:
        """lmfit-style text report, forces in the record's own unit."""
        lines = [f"model      {self.model.name}  ({', '.join(self.model.effect_names)})",
                 f"trials     {', '.join(t.name for t in self.trials)}",
                 f"fit        RMSE {self.force_text(self.overall.rmse_N)}, "
                 f"mean {self.force_text(self.overall.mean_N, True)}, "
                 f"std {self.force_text(self.overall.std_N)}; "
                 f"noise {self.force_text(self.noise_N)} ({self.noise_source}); "
                 f"residual correlation {self.white_L:.1f} samples (noise {self.noise_L:.1f}); "
                 f"{self.verdict()}",
                 f"errors     +/- below: statistical, the noise's given the model (its noise: "
                 f"{self.error_noise or 'white'}); N_eff {self.bic_samples:.4g} of {self.overall.n} samples "
                 "for the BIC and the profile",
                 "parameters (SI)"]
        for p in self.model.params:
            err = self.stderr.get(p.name)
            e = f" +/- {err:.4g}" if err is not None and math.isfinite(err) else ""
            e = "  (not determined)" if err == math.inf else e
            lines.append(f"  {p.name:<18} {self.values[p.name]:>12.5g}{e}  {p.unit}{self._whose(p.name)}")
        pairs = self.correlations(CORRELATION_FLOOR)
        if pairs:
            lines.append(f"correlations (|C| >= {CORRELATION_FLOOR:g}, largest first)")
            lines += [f"  C({a}, {b}) = {c:+.3f}" for a, b, c in pairs]
        lines.append(f"error by phase (RMSE, {self.force_unit[1]})")
        lines.append("  " + "  ".join(f"{ph} {s.rmse_N / self.force_unit[0]:.4g}" if s else f"{ph} -"
                                      for ph, s in self.phases.items()))
        for w in self.warnings:
            lines.append(f"WARNING    {w}")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        """The result as plain data (the JSON of `rig analyze --json` less what the command adds):
        the model, every parameter with its error and unit, the correlations, the fit's figures,
        the scales, each record with where its contact was placed, the error by phase and per
        record, the verdict and the warnings. Non-finite numbers are None."""
        units = {p.name: p.unit for p in self.model.params}
        return {
            "model": self.model.name,
            "effects": self.model.effect_names,
            "parameters": {k: {"value": v, "stderr": _finite(self.stderr.get(k)), "unit": units[k],
                               "determined": self.stderr.get(k) != math.inf}
                           for k, v in self.values.items()},
            "correlations": self.correlations_by_name(),
            "fit": {"rmse_N": self.overall.rmse_N, "mean_N": self.overall.mean_N, "std_N": self.overall.std_N,
                    "noise_N": self.noise_N, "noise_source": self.noise_source, "bic": self.bic,
                    "effective_samples": self.bic_samples, "bic_definition": criterion.DEFINITION,
                    "residual_effective_samples": self.n_eff,
                    # the +/- ("stderr") are statistical: the noise's, given the model, this noise model's
                    "stderr_noise_model": self.error_noise,
                    "rmse_over_noise": self.overall.rmse_N / self.noise_N if self.noise_N > 0 else None,
                    "residual_correlation_samples": self.white_L, "noise_correlation_samples": self.noise_L,
                    "seconds": self.seconds},
            "scales": {"length_m": self.scales.length_m, "force_N": self.scales.force_N,
                       "time_s": self.scales.time_s},
            "fit_variables": self.z,
            "records": [{"trial": t.name, "source": t.source, "samples": t.n, "dt_s": t.motion.dt_s,
                         "force_unit": t.force_unit[1], "length_unit": t.length_unit[1], "notes": t.notes,
                         **placed}
                        for t, placed in zip(self.trials, self.placements(), strict=True)],
            "phases": {ph: (s.as_dict() if s else None) for ph, s in self.phases.items()},
            "per_trial": self.per_trial,
            "adequate": self.adequate,
            "warnings": self.warnings,
        }

    def contact_m(self, k: int) -> float:
        """Where the fit put record `k`'s contact, in its position's frame (0 when it was not fitted)."""
        v = self.values
        for name in (f"x_c_m@{k}", "x_c_m"):
            if name in v:
                return float(v[name])
        return float(v.get("x0_mm", 0.0)) / 1000.0

    def placements(self) -> list[dict]:
        """Per record, where the fit put its contact (``contact_point_m``, in its travel from its
        first sample) and, when the record's zero was fitted, its force at rest (``zero_N``), each
        with its standard error; empty where the model has neither."""
        out = []
        for i, t in enumerate(self.trials):
            row: dict = {}
            for effect, key, to in ((CONTACT_POINT, "contact_point_m", t.contact_m or 0.0),
                                    (RECORD_ZERO, "zero_N", 0.0)):
                (p,) = effect.params
                name = self.model.key(p, i)
                if self.model.has(effect.name) and name in self.values:
                    row[key] = to + self.values[name]
                    row[f"{key}_stderr"] = _finite(self.stderr.get(name))
            out.append(row)
        return out

    def correlations_by_name(self) -> dict[str, dict[str, float | None]] | None:
        """The parameters' correlation matrix by name (None where a variance is zero)."""
        c = self.correlation
        if c is None:
            return None
        names = self.model.param_names
        return {a: {b: (float(c[i, j]) if np.isfinite(c[i, j]) else None) for j, b in enumerate(names)}
                for i, a in enumerate(names)}


def _finite(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None
