"""Fitting force models to trials: bounded least squares on parameters expressed in the
record's own scales (each of order one), several starts, one trial or several jointly
(shared parameters); what it finds is a `FitResult` (`rig.analysis.fitting.result`).

Long records are fitted in two passes: the starts run on a decimated copy (a few thousand
samples per trial: the effects live on time scales of many samples), and only the best
is polished on every sample.

Noise: the quiet part of the approach when the record has enough of it, else the
residual's short-lag structure (`rig.analysis.stats.noise`), as a level, a spectrum and a
correlation time. `adequate` means the residual is consistent with that noise: overall RMSE
within 1.2x, no phase above 1.5x, and no more correlated than the noise itself (1.5x its
integral time scale), each widened by what a perfect model would show on this record
(`rig.analysis.stats.adequacy`).

Standard errors and the parameters' correlations come from a sandwich that allows for the
residual's correlation in time (`rig.analysis.stats.uncertainty`); `bic` is the one BIC the tool
uses, on the records' effective number of independent samples (`rig.analysis.stats.criterion`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from warnings import catch_warnings, simplefilter

import numpy as np

from rig.analysis.fitting import contact_fit, separable
from rig.analysis.fitting.lean import predictor
from rig.analysis.fitting.result import ErrorStats, FitResult
from rig.analysis.fitting.scaling import ParamScaling
from rig.analysis.stats.criterion import bic as effective_bic
from rig.analysis.stats.criterion import noise_count
from rig.analysis.stats.noise import Noise, integral_scale, measure
from rig.analysis.stats.uncertainty import correlation, hac_covariance, notable_correlations, zero_meat
from rig.analysis.trials.data import PHASES, Scales, TrialData, decimate
from rig.models.catalogue import CONTACT_POINT, RECORD_ZERO
from rig.models.core import Effect, Model
from rig.models.frame import NotConverged

FEW_PER_PARAM = 5  # independent residuals per parameter below which the errors are not trusted
SCREEN_SAMPLES = 4000  # per trial, for the starts of a long record
AT_BOUND = 1e-4  # fit units (order one): closer than this to a bound is "at" it

__all__ = ["ErrorStats", "Estimates", "FitResult", "error_table", "evaluate", "fit", "fit_estimates",
           "integral_scale", "noise_of"]


def evaluate(model: Model, values: dict[str, float], trials: list[TrialData]) -> list[np.ndarray]:
    """`model`'s prediction of each trial's force at `values` (SI), one array per trial
    (`predict_trial`; each trial is told its position among them for per-record parameters)."""
    for i, t in enumerate(trials):
        t.motion.record = i
    return [predict_trial(model, values, t) for t in trials]


def predict_trial(model: Model, values: dict[str, float], t: TrialData) -> np.ndarray:
    """The model's prediction of the record's force. Where a controller held the force (creep
    form, `rig.models.creep`) the model predicts the position instead, and the prediction
    given here is the measured force less the position's miss times the record's creep weight
    (`TrialData.creep_weight_N_per_m`): measured - prediction is then the length residual in
    force units, weighed by its own noise against the force's."""
    if not t.creep:
        return model.predict(values, t.motion)
    force, x = model.predict_held(values, t.motion, t.held, t.held_force_N)
    out = np.array(force, dtype=float)
    h = t.held
    out[h] = t.force_N[h] - t.creep_weight_N_per_m * (t.motion.x_m[h] - x[h])
    return out


def predict_position(model: Model, values: dict[str, float], t: TrialData) -> np.ndarray | None:
    """The position the model predicts on the record's held samples (the measured one elsewhere),
    or None for a record in force form throughout."""
    if not t.creep:
        return None
    return model.predict_held(values, t.motion, t.held, t.held_force_N)[1]


def error_table(trials: list[TrialData], residuals: list[np.ndarray]) -> tuple[ErrorStats, dict]:
    """The residuals' `ErrorStats` over every sample, and per phase (None for a phase no trial has)."""
    r_all = np.concatenate(residuals)
    phases = {ph: ErrorStats.of(np.concatenate([r[t.mask(ph)] for t, r in zip(trials, residuals, strict=True)]))
              for ph in PHASES}
    return ErrorStats.of(r_all), phases


def noise_of(trials: list[TrialData], residuals: list[np.ndarray]) -> Noise:
    """The sensor noise a perfect model's residual would show on these trials, measured from
    their force at rest and the residuals (`rig.analysis.stats.noise.measure`)."""
    return measure([t.baseline_N for t in trials], residuals)


def with_record_params(model: Model, trials: list[TrialData], scales: Scales | None = None) -> Model:
    """`model` as fitted to `trials`, and each record told its position among them.

    A record whose contact the preparation only estimated from its force (an approach) says
    neither where the surface is nor what its force reads at rest: both are its own
    parameters, one value per record, fitted with the rest (the contact point, and the
    offset as the record's zero). A zero taken as known would leave its error, a tare's
    sigma/sqrt(n) at the least, to be absorbed by the contact point, with a standard error
    that does not allow for it."""
    if any(t.contact_estimated for t in trials):
        effects = [e for e in model.effects if e.name not in (RECORD_ZERO.name, CONTACT_POINT.name)]
        if model.has(CONTACT_POINT.name) or not model.has("contact_offset"):
            # anywhere from the start of the travel: a slow rise (a soft surface layer, drag) can
            # put the first touch far before the threshold's estimate
            start = min(float(np.min(t.motion.x_m)) for t in trials) / (scales or Scales.joint(trials)).length_m
            (p,) = CONTACT_POINT.params
            effects.append(replace(CONTACT_POINT, params=(replace(p, lo=min(start, p.lo)),)))
        model = Model([*effects, RECORD_ZERO], model.name, model.records)
    if model.has_record_params and model.records != len(trials):
        model = model.for_records(len(trials))
    for i, t in enumerate(trials):
        t.motion.record = i
    return model


def fit(model: Model, trials: list[TrialData], *, starts: int = 3, seed: int = 0,
        initial: dict[str, float] | None = None, tol: float = 1e-10, max_nfev: int = 400,
        scales: Scales | None = None, polish: bool = True) -> FitResult:
    """Fit `model` to all `trials` jointly (one parameter set). `polish`: a last pass with
    central differences (the fit a user reads; a screen can skip it)."""
    with catch_warnings():
        # a frame solve that stalls while the fit explores is judged once, at the result
        simplefilter("ignore", NotConverged)
        return _fit(model, trials, starts, seed, initial, tol, max_nfev, scales, polish)


@dataclass
class Estimates:
    """A fit's parameters and their standard errors (SI), without the rest of a `FitResult`: what
    a refit asks when only its values and errors are compared (`rig.analysis.intervals.systematic`)."""

    values: dict[str, float]
    stderr: dict[str, float | None]


def fit_estimates(model: Model, trials: list[TrialData], *, starts: int = 3, seed: int = 0,
                  initial: dict[str, float] | None = None, tol: float = 1e-10, max_nfev: int = 400,
                  scales: Scales | None = None) -> Estimates:
    """`fit(...)`'s values and standard errors, the same numbers, without the error tables, the
    noise's report and the warnings a reader of one fit needs: a map's curve makes three such
    refits, and those parts cost each a fifth of its time."""
    with catch_warnings():
        simplefilter("ignore", NotConverged)
        return _fit(model, trials, starts, seed, initial, tol, max_nfev, scales, True, _estimates)


def _fit(model, trials, starts, seed, initial, tol, max_nfev, scales, polish, finish=None) -> FitResult:
    finish = finish or _result
    t0 = time.perf_counter()
    for t in trials:
        t.motion.forget_solutions()
    scales = scales or Scales.joint(trials)
    model = with_record_params(model, trials, scales)
    ps = ParamScaling(model, scales)
    init, lo, hi = ps.start_and_bounds(initial)
    init = _inside(init, lo, hi)
    creep = any(t.creep for t in trials)
    # the same forces as model.predict, checked on these records (rig.analysis.fitting.lean); creep form
    # solves for the position, through the general model
    predict = model.predict if creep else predictor(
        model, [t.motion for t in trials], dict(zip(model.param_names, ps.to_si(init), strict=True)))
    resid = _residual_fn(model, ps, trials, scales, predict)
    guessed = _guessed(model, ps, trials, init)
    also = None  # the data's start as well as the caller's, when the caller gave those parameters
    if guessed:
        start, lo, hi = ps.start_and_bounds({**(initial or {}), **guessed})
        if set(guessed) <= set(initial or ()):
            also = _inside(start, lo, hi)
        else:
            init = _inside(start, lo, hi)
    # creep form is no longer linear in the force's amplitudes
    form = separable.split(model) if not creep else None
    # the commonest AFM model solved from sums (rig.analysis.fitting.contact_fit): the same optimum, the
    # Jacobian there exact, at a fraction of the cost a map's thousands of curves would pay
    best = contact_fit.solve(predict, resid, model.param_names, ps.to_si, init, lo, hi, trials[0].motion.x_m,
                             trials[0].force_N, 1.0 / scales.force_N) if form and len(trials) == 1 else None
    if best is not None:
        return finish(model, ps, trials, scales, best, lo, hi, best.nfev, t0)
    best = _separable(model, ps, trials, scales, resid, init, lo, hi, form, predict) if form else None
    x_c = CONTACT_POINT.params[0].name
    kinked = [i for i, p in enumerate(model.params) if p.name.partition("@")[0] == x_c]
    if best is not None:
        if polish and tol <= 1e-8:
            best = _newton_polish(resid, best, lo, hi, kinked=kinked)
        best.jac = _central_jacobian(resid, best.x, range(len(best.x)))
        return finish(model, ps, trials, scales, best, lo, hi, best.nfev, t0)
    rng = np.random.default_rng(seed)
    candidates = [init] if also is None else [init, also]
    if creep and initial is None:
        candidates.append(_force_form_start(model, trials, scales, lo, hi, ps))
    # a parameter that starts at zero inside finite bounds (the contact point) is not moved by a
    # factor: its starts are spaced evenly across its range instead. Evenly, not at random: where
    # the cost moves in steps with it (a model whose force follows the velocity only, switched on
    # at contact) the solver cannot move it, and the best of the starts is the answer
    shifted = np.flatnonzero((init == 0) & np.isfinite(lo) & np.isfinite(hi))
    span_lo, span_hi = np.maximum(lo[shifted], -1.0), np.minimum(hi[shifted], 0.5)
    for j in range(1, max(starts, 1)):
        # log-uniform spread around the starting point, kept inside the bounds
        z = init * np.exp(rng.uniform(-1.5, 1.5, len(init)))
        if len(shifted):
            z[shifted] = span_lo + (span_hi - span_lo) * j / starts
        candidates.append(_inside(z, lo, hi))
    stride = max(1, min(t.n for t in trials) // SCREEN_SAMPLES)
    nfev = 0
    if stride > 1 and len(candidates) > 1:
        coarse = [decimate(t, stride) for t in trials]
        best_c, n = _best_start(model, ps, coarse, scales, candidates, lo, hi, tol, max_nfev)
        nfev += n
        candidates = [_inside(best_c.x, lo, hi)]
    best, n = _best_start(model, ps, trials, scales, candidates, lo, hi, tol, max_nfev)
    nfev += n
    if polish and tol <= 1e-8:
        # Newton steps on a central-difference Jacobian: the solver's forward-difference
        # Jacobian (its own error ~ sqrt of machine precision) would otherwise decide the last
        # digits, and a record in other units (the same problem up to rounding) must land on the
        # same parameters
        best = _newton_polish(resid, best, lo, hi, kinked=kinked)
    return finish(model, ps, trials, scales, best, lo, hi, nfev, t0)


def _force_form_start(model, trials, scales: Scales, lo, hi, ps: ParamScaling) -> np.ndarray:
    """A creep fit's start from the same model fitted in force form to the same records.

    Solved for the position, a model can be asked for a force it never reaches (no position
    solves it), and from the catalogue's values alone the solver may never find its way out:
    on a simulated creep trial held 60 s at 1.6 N the paper's model ended 50x the noise, or not
    finite at all. Fitted the other way round (force from position: always defined) the same
    model lands where the tissue's response is, a biased but physical start."""
    forced = [replace(t, held=None) for t in trials]
    pre = _fit(model, forced, 1, 0, None, 1e-6, 100, scales, False)
    for t in trials:
        t.motion.forget_solutions()
    return _inside(ps.to_z(np.array([pre.values[k] for k in model.param_names])), lo, hi)


def _guessed(model, ps: ParamScaling, trials, init: np.ndarray) -> dict[str, float]:
    """Starting values an effect reads off the data (Effect.guess), from the misfit of the model
    at its starting point without it."""
    out: dict[str, float] = {}
    for e in model.effects:
        own = [p.name for p in e.params if not p.per_record]
        if e.guess is None or not own:
            continue
        vals = dict(zip(model.param_names, ps.to_si(init), strict=True))
        without = Model([x for x in model.effects if x is not e], model.name, model.records)
        for t in trials:
            known = {k: vals[k] for k in without.param_names}
            predicted = without.predict(known, t.motion)
            here = {p.name: vals[model.key(p, t.motion.record)] for p in e.params}
            got = e.guess(t.motion, t.force_N - predicted, here, predicted)
            if got:
                out.update({k: v for k, v in got.items() if k in own})
                break
    return out


def _best_start(model, ps: ParamScaling, trials, scales: Scales, starts, lo, hi, tol, max_nfev):
    """The lowest-cost solution from several starting points, and the evaluations spent."""
    sols = [_solve(model, ps, trials, scales, z0, lo, hi, tol, max_nfev) for z0 in starts]
    return min(sols, key=lambda sol: sol.cost), sum(sol.nfev for sol in sols)


def _residual_fn(model, ps: ParamScaling, trials, scales: Scales, predict=None):
    """Residual in units of the record's force, as a function of the fit variables."""
    f_meas = [t.force_N for t in trials]
    names = model.param_names
    inv_F = 1.0 / scales.force_N
    predict = predict or model.predict

    def resid(z: np.ndarray) -> np.ndarray:
        vals = dict(zip(names, ps.to_si(z), strict=True))
        r = np.concatenate([(predict_trial(model, vals, t) if t.creep else predict(vals, t.motion)) - f
                            for t, f in zip(trials, f_meas, strict=True)])
        return np.nan_to_num(r * inv_F, nan=1e6, posinf=1e6, neginf=-1e6)

    return resid


def _separable(model, ps: ParamScaling, trials, scales: Scales, resid, init, lo, hi,
               form, predict) -> separable.Solution | None:
    """The global optimum of a model linear in all but its contact point (rig.analysis.fitting.separable),
    or None when the general solver must do it."""
    inv_F = 1.0 / scales.force_N
    names = model.param_names
    target = np.concatenate([t.force_N for t in trials]) * inv_F

    def predict_z(z: np.ndarray) -> np.ndarray:
        vals = dict(zip(names, ps.to_si(z), strict=True))
        return np.concatenate([predict(vals, t.motion) for t in trials]) * inv_F

    def predict_many(zs: np.ndarray) -> np.ndarray | None:
        # every row at once: a parameter that differs between rows is given as a column
        si = np.array([ps.to_si(z) for z in zs])
        vals = {k: (float(col[0]) if np.all(col == col[0]) else col[:, None])
                for k, col in zip(names, si.T, strict=True)}
        try:
            with np.errstate(all="ignore"):
                return np.concatenate([np.broadcast_to(predict(vals, t.motion), (len(zs), t.n))
                                       for t in trials], axis=1) * inv_F
        except (TypeError, ValueError, IndexError):
            return None

    return separable.solve(resid, predict_z, init, lo, hi, target, form, predict_many)


def _solve(model, ps: ParamScaling, trials, scales: Scales, z0, lo, hi, tol, max_nfev, jac="2-point"):
    # imported here: scipy.optimize costs a one-curve `rig analyze` more than its fit
    from scipy.optimize import least_squares

    return least_squares(_residual_fn(model, ps, trials, scales), z0, bounds=(lo, hi), method="trf",
                         x_scale=1.0, max_nfev=max_nfev, ftol=tol, xtol=tol, gtol=tol, jac=jac)


def _newton_polish(resid, sol, lo, hi, steps: int = 30, kinked: list[int] | None = None):
    """Newton steps with a central-difference Jacobian from an interior optimum.

    A trust-region solver stops when the cost stops falling, which along a nearly flat
    direction (terms that trade off) leaves the last digits to chance. Gauss-Newton alone
    converges only linearly when the model misses the data by many times the noise (the
    curvature of the residuals themselves is left out), so the Hessian carries a secant
    correction for that term (the structured update of Dennis, Gay and Welsch, as in NL2SOL):
    the same problem posed in other units then lands on the same parameters.

    `kinked`: variables where the cost may have a corner (the contact point: a sample's step
    enters contact piecewise linearly). An optimum there stops Newton's steps on all the
    others; when a step fails, those are held where they are and the rest go on.
    """
    z = sol.x.copy()
    with np.errstate(invalid="ignore"):
        free = ((~np.isfinite(lo) | (z - lo > 1e-6 * np.maximum(1.0, np.abs(lo))))
                & (~np.isfinite(hi) | (hi - z > 1e-6 * np.maximum(1.0, np.abs(hi)))))
    if not np.any(free):
        return sol
    idx = np.flatnonzero(free)

    def jacobian(z: np.ndarray) -> np.ndarray:
        return _central_jacobian(resid, z, idx)

    r = resid(z)
    cost = 0.5 * float(r @ r)
    J = jacobian(z)
    g = J.T @ r
    A = np.zeros((len(idx), len(idx)))  # the residuals' own curvature, learnt from the steps
    for _ in range(steps):
        JTJ = J.T @ J
        try:
            s = np.linalg.solve(JTJ + A, -g)
        except np.linalg.LinAlgError:
            break
        if not float(s @ g) < 0.0:  # the correction made the model of the cost indefinite
            A[:] = 0.0
            s = np.linalg.lstsq(J, -r, rcond=None)[0]
        trial = z.copy()
        trial[idx] += s
        trial = np.clip(trial, lo, hi)
        r_new = resid(trial)
        cost_new = 0.5 * float(r_new @ r_new)
        # near the optimum the cost no longer resolves the step (rounding): a step that does not
        # make it worse beyond that is taken, since it is where the gradient vanishes
        if not cost_new <= cost * (1.0 + 1e-12):
            held = [i for i in idx if i in (kinked or ())]
            if not held or len(held) == len(idx):
                break
            idx = np.array([i for i in idx if i not in held])
            kinked = None
            J = jacobian(z)
            g = J.T @ r
            A = np.zeros((len(idx), len(idx)))
            continue
        J_new = jacobian(trial)
        g_new = J_new.T @ r_new
        step = trial[idx] - z[idx]
        y = g_new - g
        y_sharp = g_new - J.T @ r_new  # what the residuals' curvature alone changed
        ys = float(y @ step)
        if ys > 0.0:
            w = y_sharp - A @ step
            A = A + (np.outer(w, y) + np.outer(y, w)) / ys - float(w @ step) * np.outer(y, y) / ys ** 2
        z, r, cost, J, g = trial, r_new, cost_new, J_new, g_new
        # a looser stop (1e-9) left the gel record's hidden delay ranked below a second
        # relaxation branch (tests/bench/test_bench_realdata_explain.py): the fits behind a
        # verdict still move at that size
        if np.max(np.abs(step) / np.maximum(1.0, np.abs(z[idx]))) < 1e-12:
            break
    if cost <= sol.cost * (1.0 + 1e-12):
        sol.x, sol.cost, sol.fun = z, cost, r
    return sol


def _central_jacobian(resid, z: np.ndarray, idx) -> np.ndarray:
    """d(residual)/dz for the variables `idx`, by central differences."""
    h = 6e-6 * np.maximum(1.0, np.abs(z))
    cols = []
    for i in idx:
        dz = np.zeros_like(z)
        dz[i] = h[i]
        cols.append((resid(z + dz) - resid(z - dz)) / (2 * h[i]))
    return np.column_stack(cols)


def _result(model, ps: ParamScaling, trials, scales, best, lo, hi, nfev, t0) -> FitResult:
    z = best.x
    si = ps.to_si(z)
    values = {k: float(v) for k, v in zip(model.param_names, si, strict=True)}
    with catch_warnings(record=True) as caught:
        simplefilter("always", NotConverged)
        predictions = evaluate(model, values, trials)
    residuals = [t.force_N - p for t, p in zip(trials, predictions, strict=True)]
    overall, phases = error_table(trials, residuals)
    noise = noise_of(trials, residuals)
    lengths = [t.n for t in trials]
    to_si = ps.jacobian(z)
    doubts: list[str] = []
    used: list[str] = []
    blocks_of = noise_blocks(trials)
    blocks, quiet, still, _ = blocks_of
    cov, zeros = _sandwich(best, to_si, blocks_of, scales, lambda: noise, doubts, used)
    zero_variance = _zero_share(best.jac, to_si, blocks, zeros, model.param_names)
    stderr = _stderr(cov, model.param_names)
    bound = ps.at_bound(z, lo, hi, AT_BOUND)
    lag, drive = ps.rate_form
    # a rate below half a loading time's is only slow; at its bound the lag has become an integrator
    integrator = ps.integrator(z) and bool(bound[lag])
    warnings = _warnings(model, values, bound, integrator, stderr)
    if integrator:
        # the lag's time constant and the amplitudes over it run off together; their ratios
        # are the model at this limit, and what the record determines
        warnings.append(_integrator_rates(model, ps, best, si, to_si, blocks, quiet, still))
        stderr_named = {k: e for i, (k, e) in enumerate(stderr.items()) if i != lag and i not in drive}
        warnings += _undetermined(model, values, stderr_named)
    else:
        warnings += _undetermined(model, values, stderr)
    warnings += physics(model, values, trials)
    if noise.note:
        warnings.append(f"noise: {noise.note}")
    unsolved = [w.message.residual_N for w in caught if isinstance(w.message, NotConverged)]
    if unsolved:
        worst = max(unsolved)
        warnings.append(f"frame compliance: the force equation holds only to {worst:.3g} N "
                        f"({worst / max(noise.std_N, 1e-300):.2g} of the noise) where the solve stalled")
    per_trial = []
    for t, r in zip(trials, residuals, strict=True):
        o, ph = error_table([t], [r])
        per_trial.append({"trial": t.name, **o.as_dict(),
                          "phases": {k: (v.rmse_N if v else None) for k, v in ph.items()}})
    scales_r = [integral_scale(r) for r in residuals]
    white = float(np.mean(scales_r))
    n = overall.n
    # independent residuals, record by record (--explain compares candidates at this count)
    n_eff = max(sum(len(r) / L for r, L in zip(residuals, scales_r, strict=True)), 10.0)
    counted = noise_count(lengths, noise)
    bic = effective_bic(n * overall.rmse_N ** 2, n, len(model.params), counted)
    free = sum(1 for e in stderr.values() if e is not None and math.isfinite(e))
    few = bool(free) and n_eff < FEW_PER_PARAM * free
    if few:
        warnings.append(f"only {n_eff:.0f} independent residuals for {free} fitted parameters (fewer than "
                        f"{FEW_PER_PARAM} each): the standard errors rest on too little to be trusted "
                        "(--bootstrap N shows how they hold if the model is right)")
    warnings += combinations(model, values, cov)
    # the sandwich's own doubts (a bound or a clip hit, a drift allowed for); its count of
    # independent samples is said once, above, when it is the residual's
    warnings += [f"standard errors: {d}" for d in doubts if not (few and "independent sample" in d)]
    return FitResult(model, trials, values, stderr, predictions, residuals, overall, phases, noise.std_N,
                     noise.source, bic, warnings, time.perf_counter() - t0, nfev, per_trial, white,
                     noise.scale_samples, scales, dict(zip(model.param_names, map(float, z), strict=True)),
                     cov, n_eff, noise, counted, zero_variance, _one_phrase(used))


def _estimates(model, ps: ParamScaling, trials, scales, best, lo, hi, nfev, t0) -> Estimates:
    """`_result`'s values and standard errors alone, computed as it computes them: the covariance
    reads the noise only for a record's tare (`_zero_variances`), and its notes change nothing."""
    si = ps.to_si(best.x)
    values = {k: float(v) for k, v in zip(model.param_names, si, strict=True)}

    def noise() -> Noise:
        residuals = [t.force_N - p for t, p in zip(trials, evaluate(model, values, trials), strict=True)]
        return noise_of(trials, residuals)

    cov, _ = _sandwich(best, ps.jacobian(best.x), noise_blocks(trials), scales, noise)
    return Estimates(values, _stderr(cov, model.param_names))


def _sandwich(best, to_si: np.ndarray, blocks_of: tuple, scales: Scales, noise: Callable[[], Noise],
              doubts: list[str] | None = None, used: list[str] | None = None
              ) -> tuple[np.ndarray | None, list[float]]:
    """The covariance both `_result` and `_estimates` report, and the zeros' variances it holds,
    on the trials' `noise_blocks`. `noise` is called only for a record tared before its push, the
    one whose zero's error needs it (`_zero_variances`): a refit that reads no table skips it."""
    blocks, quiet, still, tared = blocks_of
    zeros = _zero_variances(tared, noise(), scales) if any(tared) else [0.0] * len(tared)
    return _covariance(best, to_si, blocks, doubts, quiet, still, zeros, used), zeros


def _one_phrase(used: list[str]) -> str:
    """The noise models the standard errors were given, each once, with the blocks that had it
    when the blocks differ."""
    if len(set(used)) <= 1:
        return used[0] if used else ""
    return "; ".join(f"block {i + 1}: {u}" for i, u in enumerate(used))


def noise_blocks(trials: list[TrialData]) -> tuple[list[int], list[int], list[bool], list[int]]:
    """The residual's blocks of independent noise, in order (samples each), the samples at rest at
    the start of each, whether each is in creep form, and the samples of the tare its zero is the
    mean of (0: none, or a zero the fit finds: `_zero_variances`): one block per trial, and within
    a trial with held samples one per run of creep form and of force form (a length residual's
    noise is not the force's), the rest before contact with the first.

    A creep-form block's noise is the position's jitter under the force loop (the slider follows
    the loop's reading, the model the smoothed force): correlated over the loop's response time
    and bounded by it, never a walk from the trial's start, so its noise model is the AR alone
    (`rig.analysis.stats.uncertainty.hac_covariance`): white noise plus a walk, which fitted such a
    residual better at short lags, made the paper's model's standard errors on a simulated
    creep trial about 18x the AR's (tau1: 6.9 s against 0.39 s; its spread over five seeds,
    0.26 s)."""
    lengths, quiet, still, tared = [], [], [], []
    for t in trials:
        if not t.creep:
            lengths.append(t.n)
            quiet.append(t.quiet_n)
            still.append(False)
            # a tare recorded apart from the record's samples (quiet_n 0): the zero is its mean
            tared.append(t.baseline_n if not t.contact_estimated and t.quiet_n == 0 else 0)
            continue
        edges = np.flatnonzero(np.diff(t.held.astype(np.int8))) + 1
        starts = np.r_[0, edges]
        runs = np.diff(np.r_[starts, t.n]).tolist()
        lengths += runs
        quiet += [min(t.quiet_n, runs[0])] + [0] * (len(runs) - 1)
        still += [bool(t.held[a]) for a in starts]
        tared += [0] * len(runs)
    return lengths, quiet, still, tared


def _inside(z: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """`z` moved strictly inside finite bounds (least_squares refuses a start on a bound)."""
    with np.errstate(invalid="ignore"):
        span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    lo_in = np.where(np.isfinite(lo), lo + 1e-6 * np.minimum(span, 1.0), -np.inf)
    hi_in = np.where(np.isfinite(hi), hi - 1e-6 * np.minimum(span, 1.0), np.inf)
    return np.clip(z, lo_in, hi_in)


def _zero_variances(tared: list[int], noise: Noise, scales: Scales) -> list[float]:
    """Per noise block, the variance of the error in its record's zero, in the fit's units of
    force: a record tared on the mean of `tared` samples at rest before the push (the rig's
    trials, a CSV with a tare step; `noise_blocks`) carries that mean's noise, sigma^2 L / n, as
    a constant under every sample, which no residual shows (the record's zero is its own).

    Left out, it made the standard errors of long, informative trials too small: over six seeds
    of a designed campaign's three trials, each tared on 50 samples (0.011 N of error at 0.08 N
    noise), the estimates spread 1.1-1.7x their standard errors, the largest 6.4 standard errors
    from the truth, and the residual at the true parameters held each trial's zero error as a
    constant (0.005-0.021 N). A record whose zero is fitted (`contact_estimated`) or in creep form
    (the held force's zero enters the position) has none here."""
    per_sample = (noise.std_N / scales.force_N) ** 2 * max(noise.scale_samples, 1.0)
    return [per_sample / n if n > 0 else 0.0 for n in tared]


def _zero_share(J: np.ndarray, to_si: np.ndarray, lengths: list[int], zeros: list[float],
                names: list[str]) -> dict[str, float]:
    """Each parameter's variance from the zeros' errors alone (SI): the same term the sandwich
    holds, B^-1 (sum_k v_k s_k s_k^T) B^-1, s_k block k's summed Jacobian."""
    if not any(zeros):
        return {}
    Z = zero_meat(J, lengths, zeros)
    bread = np.linalg.pinv(J.T @ J)
    var = np.diag(to_si @ (bread @ Z @ bread) @ to_si.T)
    return {n: float(v) for n, v in zip(names, var, strict=True) if np.isfinite(v)}


def _covariance(sol, to_si: np.ndarray, lengths: list[int], doubts: list[str] | None = None,
                quiet: list[int] | None = None, still: list[bool] | None = None,
                zeros: list[float] | None = None, used: list[str] | None = None) -> np.ndarray | None:
    """Covariance of the parameters in SI: the correlated-residual sandwich
    (`rig.analysis.stats.uncertainty`) in the fit variables, with each block's zero error (`zeros`, a
    variance), carried to SI through `to_si` = d(SI)/dz; why it may be doubtful appended to
    `doubts`."""
    try:
        cov = hac_covariance(sol.jac, sol.fun, lengths, doubts, quiet, still, zeros, used)
    except (np.linalg.LinAlgError, ValueError):
        return None
    # a direction the data do not determine (infinite variance) leaves every SI parameter
    # built on it undetermined; carried through the product it would make all of them NaN
    dead = np.isinf(np.diag(cov))
    cov = to_si @ np.where(dead[:, None] | dead[None, :], 0.0, cov) @ to_si.T
    lost = np.any(to_si[:, dead] != 0.0, axis=1)
    cov[lost, :] = np.nan
    cov[:, lost] = np.nan
    cov[lost, lost] = np.inf
    return cov


def _stderr(cov: np.ndarray | None, names: list[str]) -> dict[str, float | None]:
    if cov is None:
        return dict.fromkeys(names)
    err = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    # inf: the data do not determine it (kept, so it is never read as exact); NaN: unknown
    return {n: (None if np.isnan(e) else float(e)) for n, e in zip(names, err, strict=True)}


def _owner(model: Model, p) -> Effect:
    base = p.name.rpartition("@")[0] if p.per_record else p.name
    return next(e for e in model.effects if any(q.name in (p.name, base) for q in e.params))


def _integrator_rates(model: Model, ps: ParamScaling, sol, si: np.ndarray, to_si: np.ndarray,
                      lengths: list[int], quiet: list[int], still: list[bool] | None = None) -> str:
    """The model at the integrator limit, df/dt = sum of (amplitude / tau) x term: those ratios
    with their standard errors (the sandwich covariance in the fit variables, carried through
    `to_si` = d(SI)/dz by the quotient rule, the rate held at its bound)."""
    lag, drive = ps.rate_form
    params = model.params
    value = si[drive] / si[lag]
    free = [j for j in range(len(si)) if j != lag]
    try:
        cov_z = hac_covariance(sol.jac[:, free], sol.fun, lengths, quiet=quiet, stationary=still)
        J = (to_si[drive][:, free] * si[lag] - np.outer(si[drive], to_si[lag, free])) / si[lag] ** 2
        err = np.sqrt(np.clip(np.diag(J @ cov_z @ J.T), 0.0, None))
    except (np.linalg.LinAlgError, ValueError):
        err = np.full(len(drive), np.nan)
    tau = params[lag].name
    parts = [f"{params[i].name}/{tau} = {v:.4g} +/- {e:.2g} {params[i].unit} per s"
             + (" (not determined either)" if not e <= abs(v) else "")
             for i, v, e in zip(drive, value, err, strict=True)]
    return (f"at this limit the model reads df/dt = drive / {tau}, and the record can determine only "
            f"each amplitude over {tau}: " + ", ".join(parts))


def _undetermined(model: Model, values: dict[str, float], stderr: dict[str, float | None]) -> list[str]:
    """Parameters the trials do not pin down: a standard error larger than the value itself."""
    out = []
    for p in model.params:
        err, v = stderr.get(p.name), values[p.name]
        if err == math.inf:
            out.append(f"{_owner(model, p).name}.{p.name} = {v:.4g} {p.unit}: not determined by these "
                       "trials (the fit's error does not depend on it)")
        elif err is not None and err > abs(v) and not _owner(model, p).of_record:
            out.append(f"{_owner(model, p).name}.{p.name} = {v:.4g} +/- {err:.3g} {p.unit}: not determined "
                       "by these trials (its standard error exceeds its value)")
    return out


ELASTIC = ("linear_elastic", "poly_elastic", "power_elastic")  # drive terms of the depth alone
NEGATIVE_SHARE = 0.05  # of the indentation: an elastic force below nought over more is flagged
COMBINED = 0.99  # |correlation| from which a pair is reported as the combination the data determine


def physics(model: Model, values: dict[str, float], trials: list[TrialData]) -> list[str]:
    """An elastic term that pulls: its force below nought over more than NEGATIVE_SHARE of the
    indentation the records reach. The tissue cannot pull, so the model's no-pull clamp holds the
    force at nought there and, where that is at the start, sets the contact instead of the
    model's own zero: a fit that is not physical however small its error."""
    out = []
    depth = 0.0
    for i, t in enumerate(trials):
        x = t.motion.x_m
        for e in model.effects:
            if e.name == CONTACT_POINT.name:
                x = x - values[model.key(e.params[0], i)]
        depth = max(depth, float(np.max(x, initial=0.0)))
    if not depth > 0.0:
        return out
    d = np.linspace(0.0, depth, 401)[1:]
    for e in model.effects:
        if e.name not in ELASTIC or e.stage != "drive":
            continue
        kw = {p.name: values[p.name] for p in e.params}
        f = np.asarray(e.fn(d, np.zeros_like(d), **kw), dtype=float)
        share = float(np.mean(f < 0.0))
        if share <= NEGATIVE_SHARE:
            continue
        rises = np.flatnonzero((f[:-1] < 0.0) & (f[1:] >= 0.0))
        where = (f"; its force first rises from nought at {d[rises[0] + 1]:.4g} m of indentation, which the "
                 "no-pull clamp makes the contact" if len(rises) and f[0] < 0.0 else "")
        params = ", ".join(f"{k} = {v:.4g}" for k, v in kw.items())
        out.append(f"physics: {e.name} ({e.equation}) is negative over {share * 100:.0f} % of the indentation "
                   f"the records reach ({params}){where}: the tissue cannot pull, so this fit is not "
                   "physical, whatever its error (a model that misses a shape bends its elastic term to "
                   "follow it)")
    return out


def combinations(model: Model, values: dict[str, float], cov: np.ndarray | None) -> list[str]:
    """Pairs of parameters correlated beyond COMBINED, said as what the data determine: with
    correlation rho, a - beta b (beta = rho sd_a / sd_b) has the standard error
    sd_a sqrt(1 - rho^2), a fraction of either alone."""
    if cov is None:
        return []
    names = model.param_names
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out = []
    for a, b, rho in notable_correlations(names, correlation(cov), COMBINED):
        i, j = names.index(a), names.index(b)
        if not (np.isfinite(sd[i]) and np.isfinite(sd[j]) and sd[j] > 0):
            continue
        beta = rho * sd[i] / sd[j]
        value = values[a] - beta * values[b]
        se = sd[i] * math.sqrt(max(1.0 - rho ** 2, 0.0))
        out.append(f"{a} and {b} trade off (correlation {rho:+.4f}): the records determine "
                   f"{a} - {beta:.4g} x {b} = {value:.4g} +/- {se:.2g} (stat), not each alone; "
                   f"--profile {a} shows the range each takes")
    return out


# a parameter that must not be negative is meaningless only when it is below zero by more than
# this many of its standard errors (one-sided, about 2 %): a value slightly negative within its
# error is a physical value the noise moved, and rejecting a candidate for it threw right answers away
UNPHYSICAL_SE = 2.0


def negative(name: str, v: float, unit: str, se: float | None) -> tuple[str, bool]:
    """What a fit says of a parameter that must not be negative at value `v` < 0 with standard error
    `se`, and whether that is physically meaningless (beyond UNPHYSICAL_SE of its errors)."""
    known = se is not None and math.isfinite(se)
    if known and v + UNPHYSICAL_SE * se >= 0.0:
        return (f"{name} is negative ({v:.4g} +/- {se:.2g} {unit}), within {UNPHYSICAL_SE:g} standard "
                "errors of zero: consistent with a physical value"), False
    beyond = f", beyond {UNPHYSICAL_SE:g} standard errors" if known else ""
    return f"{name} is negative ({v:.4g} {unit}{beyond}): physically meaningless", True


def _warnings(model: Model, values: dict[str, float], at_bound: np.ndarray, integrator: bool,
              stderr: dict[str, float | None]) -> list[str]:
    out = []
    for p, bound in zip(model.params, at_bound, strict=True):
        v = values[p.name]
        effect = _owner(model, p)
        owner = effect.name
        if p.warn_negative and v < 0:
            out.append(negative(f"{owner}.{p.name}", v, p.unit, stderr.get(p.name))[0])
        if bound and effect.stage == "lag" and v > 0 and integrator:
            out.append(f"{owner}.{p.name} = {v:.4g} {p.unit}: the force does not relax on this record; "
                       f"the lag acts as an integrator (its rate 1/{p.name} sits at its bound, zero)")
        elif bound:
            out.append(f"{owner}.{p.name} = {v:.4g} {p.unit} sits at its bound: the data push it "
                       "out of the physical range")
    return out
