"""Fitting force models to trials: bounded least squares on scaled parameters, several
starts, one trial or several jointly (shared parameters), with a readable result.

Noise: the standard deviation of the force before contact when the log has a baseline,
else from residual differences (std(diff(r)) / sqrt 2, which a smooth misfit barely
touches). `adequate` means the residual is consistent with that noise: overall RMSE
within 1.2x and no phase above 1.5x.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from rig.analysis.data import PHASES, TrialData
from rig.models.core import Model

ADEQUATE_RMSE = 1.2
ADEQUATE_PHASE = 1.5
ADEQUATE_WHITE = 1.5  # the residual's integral time scale, samples: white noise gives about 1


@dataclass
class ErrorStats:
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

    @property
    def adequate(self) -> bool:
        worst = max((s.rmse_N for s in self.phases.values() if s is not None), default=0.0)
        return (self.overall.rmse_N <= ADEQUATE_RMSE * self.noise_N
                and worst <= ADEQUATE_PHASE * self.noise_N and self.white_L <= ADEQUATE_WHITE)

    def report(self) -> str:
        """lmfit-style text report."""
        lines = [f"model      {self.model.name}  ({', '.join(self.model.effect_names)})",
                 f"trials     {', '.join(t.name for t in self.trials)}",
                 f"fit        RMSE {self.overall.rmse_N:.4f} N, mean {self.overall.mean_N:+.4f} N, "
                 f"std {self.overall.std_N:.4f} N; noise {self.noise_N:.4f} N ({self.noise_source}); "
                 f"residual correlation {self.white_L:.1f} samples; "
                 f"{'adequate' if self.adequate else 'NOT adequate'}",
                 "parameters"]
        for p in self.model.params:
            err = self.stderr.get(p.name)
            e = f" +/- {err:.4g}" if err is not None else ""
            lines.append(f"  {p.name:<18} {self.values[p.name]:>12.5g}{e}  {p.unit}")
        lines.append("error by phase (RMSE, N)")
        lines.append("  " + "  ".join(f"{ph} {s.rmse_N:.4f}" if s else f"{ph} -"
                                      for ph, s in self.phases.items()))
        for w in self.warnings:
            lines.append(f"WARNING    {w}")
        return "\n".join(lines)


def integral_scale(r: np.ndarray, max_lag: int = 3000) -> float:
    """Samples per independent residual value."""
    r = r - r.mean()
    n = len(r)
    if n < 10 or not np.any(r):
        return 1.0
    lag = min(max_lag, n // 4)
    f = np.fft.rfft(r, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[: lag + 1]
    acf = acf / acf[0]
    below = np.flatnonzero(acf < 0.05)
    cut = below[0] if len(below) else lag
    return float(np.clip(1.0 + 2.0 * acf[1:cut].sum(), 1.0, n / 20.0))


def evaluate(model: Model, values: dict[str, float], trials: list[TrialData]) -> list[np.ndarray]:
    return [model.predict(values, t.motion) for t in trials]


def error_table(trials: list[TrialData], residuals: list[np.ndarray]) -> tuple[ErrorStats, dict]:
    r_all = np.concatenate(residuals)
    phases = {ph: ErrorStats.of(np.concatenate([r[t.mask(ph)] for t, r in zip(trials, residuals, strict=True)]))
              for ph in PHASES}
    return ErrorStats.of(r_all), phases


def noise_of(trials: list[TrialData], residuals: list[np.ndarray]) -> tuple[float, str]:
    """Sensor noise: a long pre-contact baseline if there is one, else residual differences.

    The differences of a residual that is smooth at the sample scale (any model misfit is)
    keep only the white sensor noise: var(diff) = 2 sigma^2.
    """
    base = [t.baseline_noise_N for t in trials if t.baseline_noise_N is not None and t.baseline_n >= 200]
    if base:
        return float(np.sqrt(np.mean(np.square(base)))), "pre-contact baseline"
    d = np.concatenate([np.diff(r) for r in residuals])
    return float(np.std(d) / np.sqrt(2.0)), "residual differences"


def fit(model: Model, trials: list[TrialData], *, starts: int = 3, seed: int = 0,
        initial: dict[str, float] | None = None, tol: float = 1e-10, max_nfev: int = 400) -> FitResult:
    """Fit `model` to all `trials` jointly (one parameter set)."""
    t0 = time.perf_counter()
    params = model.params
    scale = np.array([p.typical for p in params])
    lo = np.array([p.lo for p in params]) / scale
    hi = np.array([p.hi for p in params]) / scale
    init = np.array([(initial or {}).get(p.name, p.init) for p in params]) / scale
    init = _inside(init, lo, hi)
    f_meas = [t.force_N for t in trials]
    def resid(z: np.ndarray) -> np.ndarray:
        vals = dict(zip(model.param_names, z * scale, strict=True))
        out = [model.predict(vals, t.motion) - f for t, f in zip(trials, f_meas, strict=True)]
        r = np.concatenate(out)
        return np.nan_to_num(r, nan=1e6, posinf=1e6, neginf=-1e6)

    rng = np.random.default_rng(seed)
    candidates = [init]
    for _ in range(max(starts - 1, 0)):
        # log-uniform spread around the initial guess, kept inside the bounds
        jitter = init * np.exp(rng.uniform(-1.5, 1.5, len(init)))
        candidates.append(_inside(jitter, lo, hi))
    best = None
    nfev = 0
    for z0 in candidates:
        sol = least_squares(resid, z0, bounds=(lo, hi), method="trf", x_scale=1.0, max_nfev=max_nfev,
                            ftol=tol, xtol=tol, gtol=tol)
        nfev += sol.nfev
        if best is None or sol.cost < best.cost:
            best = sol
    z = best.x
    values = dict(zip(model.param_names, z * scale, strict=True))
    predictions = evaluate(model, values, trials)
    residuals = [f - p for f, p in zip(f_meas, predictions, strict=True)]
    overall, phases = error_table(trials, residuals)
    noise, noise_src = noise_of(trials, residuals)
    stderr = _stderr(best, model.param_names, scale, overall)
    n = overall.n
    bic = n * np.log(max(overall.rmse_N ** 2, 1e-300)) + len(params) * np.log(n)
    warnings = _warnings(model, values, z, lo, hi)
    per_trial = []
    for t, r in zip(trials, residuals, strict=True):
        o, ph = error_table([t], [r])
        per_trial.append({"trial": t.name, **o.as_dict(),
                          "phases": {k: (v.rmse_N if v else None) for k, v in ph.items()}})
    white = float(np.mean([integral_scale(r) for r in residuals]))
    return FitResult(model, trials, values, stderr, predictions, residuals, overall, phases, noise,
                     noise_src, float(bic), warnings, time.perf_counter() - t0, nfev, per_trial, white)


def _inside(z: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """`z` moved strictly inside finite bounds (least_squares refuses a start on a bound)."""
    with np.errstate(invalid="ignore"):
        span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    lo_in = np.where(np.isfinite(lo), lo + 1e-6 * span, -np.inf)
    hi_in = np.where(np.isfinite(hi), hi - 1e-6 * span, np.inf)
    return np.clip(z, lo_in, hi_in)


def _stderr(sol, names: list[str], scale, overall: ErrorStats) -> dict[str, float | None]:
    """Standard errors from the Jacobian (white-noise assumption: optimistic for 100 Hz data)."""
    J = sol.jac
    dof = max(overall.n - len(names), 1)
    s2 = 2.0 * sol.cost / dof
    try:
        err = np.sqrt(np.clip(np.diag(np.linalg.inv(J.T @ J)) * s2, 0.0, None)) * scale
    except np.linalg.LinAlgError:
        return dict.fromkeys(names)
    return {n: (float(e) if np.isfinite(e) else None) for n, e in zip(names, err, strict=True)}


def _warnings(model: Model, values: dict[str, float], z, lo, hi) -> list[str]:
    out = []
    for p, zi, low, h in zip(model.params, z, lo, hi, strict=True):
        v = values[p.name]
        owner = next(e.name for e in model.effects if p in e.params)
        if p.warn_negative and v < 0:
            out.append(f"{owner}.{p.name} is negative ({v:.4g} {p.unit}): physically meaningless")
        span = (h - low) if np.isfinite(h - low) else None
        near = 1e-3 * (span if span else max(abs(zi), 1.0))
        if (np.isfinite(low) and zi - low <= near) or (np.isfinite(h) and h - zi <= near):
            out.append(f"{owner}.{p.name} = {v:.4g} {p.unit} sits at its bound: the data push it "
                       "out of the physical range")
    return out
