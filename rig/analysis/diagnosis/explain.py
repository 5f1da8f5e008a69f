"""Which effect is missing? Refit with each candidate and rank by an honest criterion.

Residuals at 100 Hz are strongly autocorrelated whenever a model misses something, so a
BIC over all samples counts the same misfit hundreds of times and rewards any extra
parameter. The criterion here is the one BIC every fit reports (`rig.analysis.stats.uncertainty`),
on the effective number of independent residuals, both models at the base model's N_eff:

    N_eff = N / L,   L = 1 + 2 * sum of the base residual's autocorrelation (up to its first
                         drop below 0.05): the residual's integral time scale in samples
    delta_BIC = N_eff * ln(RSS_with / RSS_without) + delta_k * ln(N_eff)

A white residual (an adequate model) keeps N_eff = N and the full ln(N) penalty; a smooth
misfit shrinks N_eff, so only a large error reduction counts. A suggestion also needs its
RMSE to fall by at least MIN_DROP, and when the base model is already adequate its
delta_BIC must be decisive (below DECISIVE_BIC). The thresholds are set from the
calibration benchmark (tests/bench/calibrate_explain.py): on simulated trials the model
matches only to its discretisation, so an adequate model's residual is white and its N_eff
large, and a candidate that absorbs a sliver of that discrepancy reaches delta_BIC of -100
and below on clean controls; the error drop is what separates a hidden effect from that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rig.analysis.diagnosis.residual_shape import describe, not_the_answer
from rig.analysis.fitting.fit import FEW_PER_PARAM, UNPHYSICAL_SE, FitResult, evaluate, fit, negative
from rig.analysis.stats.criterion import delta_bic
from rig.analysis.trials.data import PHASES, TrialData, decimate
from rig.models.catalogue import CONTACT, instrument_effects
from rig.models.core import Effect, Model
from rig.models.instrument import BOTTOM_EFFECTS

MIN_DROP = 0.05  # calibrated: docs/explanation/verdict.md (tests/bench/calibrate_explain.py)
SCREEN_SAMPLES = 2000  # per trial
SCREEN_NFEV = 60  # iterations of a screen (each one a Jacobian)
REFIT_NFEV = 20  # a leader's refit at full rate, from the screen's answer
REFIT_LEADERS = 3
SWAP_LEADERS = 3  # the best candidates by the criterion whose swaps are tried (each a few refits)
DECISIVE_BIC = -10.0
SUGGEST_BIC = 0.0  # the same, for a model that is not adequate
ABSORBED_BIC = 3 * DECISIVE_BIC  # very strong support, negligible error change: a look-alike
ABSORBED_MOVE = 0.5  # ... if one of the model's own effects reshapes (a parameter moves by half) to mimic it
# Pairs that one family of trials often cannot separate, and the protocol that would.
SEPARATE_BY = {
    frozenset({"compliance", "poly_elastic"}): "a second depth (the frame's share grows with force, the "
                                               "tissue's with depth) or a richer motion (a sine: order 2)",
    frozenset({"compliance", "relaxation2"}): "a hold at a second depth",
    frozenset({"delay", "viscous"}): "another speed (a delay's error scales with df/dt, damping's with v)",
    frozenset({"delay", "friction"}): "another speed",
    frozenset({"drift", "relaxation2"}): "a longer hold, or a stretch without contact (drift shows there)",
    frozenset({"offset", "drift"}): "a longer pre-contact baseline and a rest after the return",
    frozenset({"offset", "contact_offset"}): "an approach step that finds the surface",
    frozenset({"fractional_relaxation", "relaxation2"}): "a longer hold (a power law keeps relaxing over "
                                                         "every decade of time; one exponential settles)",
    frozenset({"speed_relaxation", "relaxation2"}): "a third speed (the relaxation time follows the speed)",
}
# what gives a record the independent residuals a richer model needs
BEYOND_DESIGN = "a longer hold, another speed or another depth would give the record more to tell"
GENERIC_SEPARATION = "another speed, another depth, or a richer motion (a sine gives excitation order 2)"


@dataclass
class Suggestion:
    """One candidate effect as `explain` scored it: the error with it (``rmse_N``, and the share
    of the base's removed), its ``delta_bic`` against the base model, why it helps (``why``:
    where the error fell), its ``fit``, and why it cannot be the answer if it cannot
    (``meaningless``, ``unsupported``). ``dropped``: effects of the base a swap removes."""

    effect: str
    rmse_N: float
    rmse_drop: float  # fraction of the base RMSE removed
    delta_bic: float
    why: str
    fit: FitResult
    meaningless: str = ""  # why the best fit with it is physically meaningless, if it is
    full_rate: bool = True  # scored on every sample (else on the screen's decimated copy)
    # against the other passing candidates, at the better fits' N_eff (`_among_passing`): its BIC
    # over the best one's (0 for the best); None when it was not compared
    pair_bic: float | None = None
    # effects of the base model this suggestion drops (a swap: `_swapped`), empty for an addition
    dropped: tuple[str, ...] = ()
    unsupported: str = ""  # why the record cannot support the model with it (`richness`), if it cannot

    @property
    def label(self) -> str:
        """The effect, and any effect of the base it drops: "drift, with nonlinear_damping dropped"."""
        return f"{self.effect}, with {' and '.join(self.dropped)} dropped" if self.dropped else self.effect

    def as_dict(self) -> dict:
        return {"effect": self.effect, "dropped": list(self.dropped), "rmse_N": self.rmse_N,
                "rmse_drop": self.rmse_drop, "delta_bic": self.delta_bic,
                "criterion": "BIC on effective samples", "why": self.why,
                # named on decisive evidence below the richness floor: why its errors rest on too little
                "unsupported": self.unsupported or None}


@dataclass
class Explanation:
    """What `explain` found on a fit: every candidate ranked (``ranked``), those that pass
    (``suggestions``, best first), the best one's name (``best``), pairs of effects these
    records cannot tell apart (``lookalikes``), what the best addition still leaves
    (``unexplained``, ``closest``), candidates the record is too poor to support (``beyond``),
    and the verdict as one text (``summary``, ``verdict()``)."""

    base: FitResult
    n_eff: float
    ranked: list[Suggestion]  # every candidate, best first
    suggestions: list[Suggestion]  # the ones that pass
    indistinguishable: list[dict]
    adequate: bool
    summary: str
    best: str | None = None  # the best-supported addition, if any passes
    lookalikes: list[dict] = field(default_factory=list)  # pairs these trials cannot separate
    unexplained: bool | str = False  # what the best addition (or the base) still leaves
    # the best addition when it still leaves a structured residual: the nearest the catalogue
    # comes, not the answer
    closest: str | None = None
    # candidates that pass the criterion on a model richer than the record supports (`richness`):
    # a design question, not a suggestion
    beyond: list[Suggestion] = field(default_factory=list)

    def verdict(self) -> dict:
        """The verdict as fields (the `diagnosis` of `rig analyze --explain --json`)."""
        return {"best": self.best, "lookalikes": self.lookalikes, "unexplained": self.unexplained,
                "closest": self.closest, "text": self.summary}


def candidates(model: Model, registry: dict[str, Effect],
               trials: list[TrialData] | None = None) -> list[Effect]:
    """The effects `explain` tries on `model`: the catalogue's (and the plugins') not already in it, the
    instrument's own for an AFM record, and a rate that follows the loading speed only where the trials ran
    at several speeds."""
    speeds = sorted(t.motion.loading_speed_m_s for t in trials) if trials else []
    # a rate that follows the loading speed is told from a plain change of the lag only by
    # trials at different speeds: on one speed it is a second name for the same fit
    several_speeds = bool(speeds) and speeds[-1] > 1.2 * max(speeds[0], 1e-300)
    out = []
    for e in instrument_effects(model, registry).values():
        if model.has(e.name):
            continue
        if e.stage in ("rate", "lag", "delay") and any(x.stage == e.stage for x in model.effects):
            continue
        if e.stage == "rate" and not any(x.stage == "lag" for x in model.effects):
            continue  # a rate speeds up a lag: without one it has nothing to act on
        if e.stage == "rate" and trials is not None and not several_speeds:
            continue
        if {e.name, *model.effect_names} >= {"contact_point", "contact_offset"}:
            continue  # one contact point: the other is a second name for it
        if e.name in BOTTOM_EFFECTS and not model.has(CONTACT):
            continue  # a correction of the indenter's contact (a known thickness puts it in the registry)
        out.append(e)
    return out


def explain(base: FitResult, registry: dict[str, Effect], trials: list[TrialData] | None = None) -> Explanation:
    """Which effect `base`'s model most likely misses: every candidate of `registry` the model
    can take (`candidates`) is fitted in turn, screened on a decimated copy and the leaders refitted
    on every sample, and ranked by the BIC on the residual's independent samples. A candidate
    is suggested when it passes the criterion (decisively, for an adequate model), is not
    physically meaningless beyond its own error, and the record supports the richer model; a
    leader that makes one of the model's own effects unneeded is offered as a swap. The
    `Explanation` holds the ranking, the suggestions, the look-alikes these records cannot
    separate, and the verdict as the user reads it (``summary``).
    """
    trials = trials or base.trials
    r_all = np.concatenate(base.residuals)
    n_eff = base.n_eff
    rss0 = float(np.sum(r_all ** 2))
    # Screen every candidate on a decimated copy (a few thousand samples per trial: the
    # effects live on time scales of many samples), then refit the leaders at full rate.
    stride = max(1, min(t.n for t in trials) // SCREEN_SAMPLES)
    coarse = [decimate(t, stride) for t in trials]
    base_coarse = fit(base.model, coarse, starts=1, initial=base.values, tol=1e-8, max_nfev=SCREEN_NFEV,
                      polish=False)
    rss0_c = float(np.sum(np.concatenate(base_coarse.residuals) ** 2))
    screened = []
    for e in candidates(base.model, registry, trials):
        # a screen, not the final word: a candidate that has not converged by then is not the answer.
        # Two starts: the base's values, and the start a fresh fit of the richer model takes. From
        # the base's alone, effects that bent to stand in for the missing one hold the fit where
        # it is (a drift hidden in an oocyte relaxation: from the base's values the drift took 5 %
        # of the error away, from a fresh start 56 %, as it did from the clean record's values).
        rss, res = min(((_rss(r), r) for r in (
            fit(base.model + e, coarse, starts=1, initial=start, tol=1e-6, max_nfev=SCREEN_NFEV, polish=False)
            for start in (base_coarse.values, None))), key=lambda x: x[0] if np.isfinite(x[0]) else np.inf)
        screened.append((rss / max(rss0_c, 1e-300), e, res))
    screened.sort(key=lambda x: x[0])

    def score(e: Effect, res_c: FitResult, full: bool, dropped: tuple[str, ...] = (),
              fitted: FitResult | None = None) -> Suggestion:
        model = without(base.model, dropped) + e
        if full:
            # from the screen's answer a few steps settle it on every sample (`fitted`: that fit,
            # already made, as a swap's slimmer model is)
            res = fitted if fitted is not None else fit(model, trials, starts=1, initial=res_c.values, tol=1e-8,
                                                        max_nfev=REFIT_NFEV, polish=False)
            ratio = float(np.sum(np.concatenate(res.residuals) ** 2)) / max(rss0, 1e-300)
            before = base
        else:
            res, before = res_c, base_coarse
            ratio = float(np.sum(np.concatenate(res.residuals) ** 2)) / max(rss0_c, 1e-300)
        if not np.isfinite(ratio):
            # the candidate's fit ends where its model cannot be evaluated (creep form: no position
            # solves the held force): last, never a NaN that would leave the ranking unsorted
            ratio = np.inf
        dk = len(model.params) - len(base.model.params)
        dbic = delta_bic(ratio, dk, n_eff)
        rmse = base.overall.rmse_N * float(np.sqrt(ratio))
        drop = 1.0 - float(np.sqrt(ratio))
        sug = Suggestion(e.name, rmse, drop, float(dbic), _why(e, before, res), res, full_rate=full,
                         dropped=dropped)
        if dropped:
            sug.why += f"; with {' and '.join(dropped)} dropped from the model (fit it: {options(model)})"
        # without `dropped`, the fit `before` is the candidate's own model with its amplitude at
        # nought, on the same samples: the sign of a negative amplitude is judged on that too
        needed = None if dropped else (e, -n_eff * float(np.log(ratio)) if ratio > 0 else np.inf)
        bad = meaningless(res, base, needed)
        if bad:
            sug.meaningless = bad
            sug.why += f"; but {bad}"
        elif (slight := within(res, base)):
            sug.why += f"; {slight}"
        return sug

    ranked = [score(e, res_c, i < REFIT_LEADERS) for i, (_, e, res_c) in enumerate(screened)]
    by_name = {e.name: (e, res_c) for _, e, res_c in screened}
    while True:
        # the answer is scored on every sample: a candidate screened only on the decimated copy
        # that would come first is refitted before it can (the copy's score is not the same)
        ranked.sort(key=lambda s: s.delta_bic)
        top = next((s for s in ranked if not s.meaningless), None)
        if top is None or top.full_rate:
            break
        ranked[ranked.index(top)] = score(*by_name[top.effect], True)
    # a leader that explains the residual while it turns one of the model's own effects
    # significantly negative, or makes one unnecessary, is offered with that effect dropped
    for s in sorted(ranked, key=lambda s: s.delta_bic)[:SWAP_LEADERS]:
        if s.full_rate and (swap := _swapped(s, base, by_name[s.effect][0], score)) is not None:
            ranked[ranked.index(s)] = swap
    ranked.sort(key=lambda s: s.delta_bic)
    ranked_ok = [s for s in ranked if not s.meaningless]
    passing = [s for s in ranked_ok if passes(s.delta_bic, s.rmse_drop, base.adequate)]
    for s in passing:
        s.unsupported = richness(s.fit)
    # a model richer than the record supports is compared on too little: there only decisive
    # evidence counts (a friction that takes 95 % of the error away, not a 10 % gain at N_eff 20)
    beyond = [s for s in passing if s.unsupported and s.delta_bic >= DECISIVE_BIC]
    passing = [s for s in passing if s not in beyond]
    # with an answer, only a candidate that could stand in for it is a look-alike worth naming; a
    # strongly supported effect that barely changes the error is news only when nothing passes
    twins = _indistinguishable(passing, trials) if passing else _absorbed(base, ranked_ok)
    passing = _among_passing(passing, base)
    best = passing[0] if passing else None
    unexplained = _unexplained(base, best)
    closest, partial = None, ""
    if best is not None and unexplained:
        partial = not_the_answer(base.overall.rmse_N, best.fit.overall.rmse_N, best.fit.noise_N,
                                 best.fit.trials, best.fit.residuals)
        if partial:
            # no effect in the catalogue explains the residual: the nearest one is named as such,
            # never as the answer
            closest, best = best, None
    ranked_pair = best is not None and len(passing) > 1 and passing[1].pair_bic is not None
    runner_up = passing[1] if ranked_pair else None
    summary = _summary(base, best, twins, unexplained, closest, partial, runner_up,
                       beyond[0] if beyond and best is None else None)
    return Explanation(base, n_eff, ranked, passing, twins, base.adequate, summary,
                       best.effect if best else None, twins, unexplained,
                       closest.effect if closest else None, beyond)


def richness(res: FitResult) -> str:
    """Why the record cannot support `res`'s model, or "" when it can: fewer than FEW_PER_PARAM
    independent residuals (the residual's N_eff) per fitted parameter. Below that the standard
    errors rest on too little, and a further effect compared at that count is chasing the
    residual's few independent features, not the physics (a creep record's --auto model once held
    eleven parameters on 20 independent residuals, and an effect it did not need turned negative
    when a hidden drift was named)."""
    free = sum(1 for e in res.stderr.values() if e is not None and math.isfinite(e))
    if not free or res.n_eff >= FEW_PER_PARAM * free:
        return ""
    return (f"{free} fitted parameters on {res.n_eff:.0f} independent residuals (fewer than {FEW_PER_PARAM} "
            "each)")


def without(model: Model, names: tuple[str, ...] | list[str]) -> Model:
    """`model` with the effects `names` dropped."""
    return Model([e for e in model.effects if e.name not in names], records=model.records) if names else model


def options(model: Model) -> str:
    """The `rig analyze` options that fit `model` (the terms every curve has, one value per record,
    come with it)."""
    names = [e.name for e in model.effects if not e.of_record]
    first = "hertz" if names[0] == CONTACT else names[0]  # the contact law: its indenter as given
    return " ".join([f"--model {first}", *(f"--add {n}" for n in names[1:])])


def droppable(model: Model) -> list[str]:
    """The effects a swap may drop: not the elastic law (the model's first effect) and not a term
    with one value per record (the contact point, the record's zero), which every curve has."""
    return [e.name for e in model.effects[1:] if not e.of_record]


def _swapped(s: Suggestion, base: FitResult, e: Effect, score) -> Suggestion | None:
    """`s` with an effect of the base dropped, when that is the better model, else None.

    Two ways an addition leaves an effect of the base behind: its fit turns that effect's
    parameter significantly negative (the addition explains what the effect stood in for, and
    the effect, still there, bends the other way: `meaningless`), or the fit without the effect
    is as good by the one criterion (compared at the slimmer model's N_eff, as `auto` drops).
    A meaningless fit is offered with the effects that went negative dropped, if that fit is
    physical; a sound one with the effect whose drop the criterion prefers most."""
    can = [n for n in droppable(base.model) if n != e.name]
    if s.meaningless:
        owners = tuple(dict.fromkeys(o for o, _, bad in _negatives(s.fit, base) if bad and o in can))
        if not owners:
            return None
        swap = score(e, s.fit, True, owners)
        return None if swap.meaningless else swap
    best, best_dbic = None, 0.0
    for name in can:
        # the swapped model itself (the base without `name`, plus `e`), fitted as `score` fits it
        slim = fit(without(s.fit.model, (name,)), s.fit.trials, starts=1, initial=s.fit.values, tol=1e-8,
                   max_nfev=REFIT_NFEV, polish=False)
        dk = len(s.fit.model.params) - len(slim.model.params)
        dbic = -delta_bic(_rss(s.fit) / max(_rss(slim), 1e-300), dk, slim.n_eff)
        if dbic < best_dbic and not meaningless(slim, base):
            best, best_dbic = (name, slim), dbic
    return score(e, s.fit, True, (best[0],), fitted=best[1]) if best else None


def _among_passing(passing: list[Suggestion], base: FitResult) -> list[Suggestion]:
    """The passing candidates ordered among themselves by the same criterion at the N_eff of
    the best of their fits, not the base model's.

    Each passes against the base at the base's N_eff. But the base's residual, far from the
    noise, is correlated over its misfit: when it reads many times the noise, N_eff is a few
    dozen and candidates that differ well beyond the noise tie there. A second relaxation hidden
    in a creep trial left the paper's model 3.5x the noise with N_eff 20; a second relaxation,
    a damping and a contact offset each brought it to 0.88-0.89x, and the extra parameter of the
    first lost it the ranking by 2.4 at N_eff 20. The better fits' residual, at the noise, is
    what tells them apart: their N_eff, and the candidates' own BIC there, rank them."""
    full = [s for s in passing if s.full_rate]
    if len(full) < 2:
        return passing
    rss = {id(s): _rss(s.fit) for s in full}
    lead = min(full, key=lambda s: rss[id(s)])
    n_ref = max(base.n_eff, lead.fit.n_eff)
    score = {id(s): n_ref * np.log(max(rss[id(s)], 1e-300)) + len(s.fit.model.params) * np.log(n_ref)
             for s in full}
    best = min(score.values())
    for s in full:
        s.pair_bic = float(score[id(s)] - best)
    return sorted(full, key=lambda s: score[id(s)]) + [s for s in passing if not s.full_rate]


def meaningless(res: FitResult, base: FitResult, needed: tuple[Effect, float] | None = None) -> str:
    """Why the fit `res` of a model with an added effect is physically meaningless, or "".

    Every parameter of the model counts, not only the added effect's: an effect that fits only
    by turning one of the model's own terms negative (a damping, a stiffness) is not the
    answer. Negative means significantly so: below zero by more than UNPHYSICAL_SE of its own
    standard errors (`rig.analysis.fitting.fit.negative`); a value slightly negative within its error
    is said (`within`) and does not reject. A parameter already negative in `base`, the fit
    without the effect, is the base model's own problem (its fit says so) and is left out.

    `needed`: the added effect and the likelihood ratio of `res` over the fit without it, on the
    same samples and N_eff: N_eff ln(RSS without / RSS with). The added effect's amplitude (every
    parameter that must not be negative is one: at nought its term is gone) is also significantly negative
    when that ratio passes the same two-sigma level: a standard error is a curvature at the
    optimum, and where the amplitude trades off with the effect's own shape (Hunt-Crossley's b
    with its exponent n) it spans zero while the term's sign is settled (a damping of
    b = -1.1e6 +/- 1.9e6 that took 90 % of an AFM curve's ramp error)."""
    return next((said for _, said, bad in _negatives(res, base, needed) if bad), "")


def unneeded_ratio(effect: Effect) -> float:
    """The likelihood ratio that a fit with `effect` passes over the fit without it at two sigma:
    UNPHYSICAL_SE squared for a one-parameter effect, the chi-squared level of the same
    probability for an effect of more parameters (its shape is free when its amplitude is not)."""
    from scipy.special import gammaincinv  # here: a one-curve Hertz analysis imports no scipy

    k = len(effect.params)
    return 2.0 * float(gammaincinv(k / 2.0, math.erf(UNPHYSICAL_SE / math.sqrt(2.0))))


def within(res: FitResult, base: FitResult) -> str:
    """The parameters of `res` negative within their errors (not meaningless: `meaningless`), said."""
    return "; ".join(said for _, said, bad in _negatives(res, base) if not bad)


def _negatives(res: FitResult, base: FitResult,
               needed: tuple[Effect, float] | None = None) -> list[tuple[str, str, bool]]:
    """Each parameter of `res` below zero that must not be (and is not in `base`): its effect, what
    `negative` says of it (or, for the added effect's amplitude, the likelihood ratio `needed`: see
    `meaningless`), and whether it is meaningless."""
    out = []
    for p in res.model.params:
        if not (p.warn_negative and res.values[p.name] < 0) or base.values.get(p.name, 0.0) < 0:
            continue
        owner = next((e.name for e in res.model.effects if any(q.name == p.name for q in e.params)), "model")
        v, name = res.values[p.name], f"{owner}.{p.name}"
        said, bad = negative(name, v, p.unit, res.stderr.get(p.name))
        if not bad and needed is not None and owner == needed[0].name:
            ratio, level = needed[1], unneeded_ratio(needed[0])
            if ratio > level:
                said, bad = (f"{name} is negative ({v:.4g} {p.unit}) and its term is needed (likelihood ratio "
                             f"{ratio:.3g} over the fit without it, beyond {level:.3g}, two sigma): "
                             "physically meaningless, whatever its standard error"), True
        out.append((owner, said, bad))
    return out


def passes(delta_bic: float, rmse_drop: float, base_adequate: bool) -> bool:
    """Whether a candidate is suggested: the thresholds the calibration benchmark sets."""
    if rmse_drop < MIN_DROP:
        return False
    return delta_bic < (DECISIVE_BIC if base_adequate else SUGGEST_BIC)


def _phase_drops(base: FitResult, res: FitResult) -> list[tuple[str, float, float]]:
    out = []
    for ph in PHASES:
        a, b = base.phases.get(ph), res.phases.get(ph)
        if a and b:
            out.append((ph, a.rmse_N, b.rmse_N))
    return sorted(out, key=lambda x: x[2] - x[1])


def _why(e: Effect, base: FitResult, res: FitResult) -> str:
    """Where the evidence is: the phase whose error falls most, what the new term looks like."""
    drops = _phase_drops(base, res)
    parts = []
    if drops:
        ph, before, after = drops[0]
        parts.append(f"{ph} error {base.force_text(before)} -> {base.force_text(after)}")
    vals = ", ".join(f"{p.name} ~ {res.values[p.name]:.3g} {p.unit}" for p in e.params)
    shape = _shape(e, base, res)
    text = shape or e.signature
    return f"{text} ({'; '.join([*parts, vals])})"


def _shape(e: Effect, base: FitResult, res: FitResult) -> str:
    v = res.values
    name = e.name
    # a relaxation shows in a hold; on records with none (an AFM approach) it bends the ramp
    held = any(res.phases.get(ph) for ph in ("hold_early", "hold_late"))
    if name in ("relaxation", "relaxation2", "fractional_relaxation") and not held:
        tau = v.get({"relaxation": "tau1_s", "relaxation2": "tau_m_s"}.get(name, "tau_f_s"))
        many = "over many time scales, " if name == "fractional_relaxation" else ""
        return ("ramp residual bends with time, not depth: the force relaxes while it is loaded "
                f"({many}tau about {tau:.3g} s)")
    if name == "relaxation2":
        return f"hold residual still decaying with tau about {v['tau_m_s']:.3g} s"
    if name == "relaxation":
        return f"hold residual decaying with tau about {v['tau1_s']:.3g} s: the force relaxes, the model holds"
    if name == "speed_relaxation" and "tau1_s" in v:
        taus = sorted({1.0 / (1.0 / v["tau1_s"] + 1000.0 * v["relax_rate_per_speed_1_per_mm"]
                              * t.motion.loading_speed_m_s) for t in res.trials}, reverse=True)
        return ("hold residual decays faster after faster loading: one tau1 cannot serve every speed "
                f"(tau1 about {', '.join(f'{x:.3g}' for x in taus)} s from the slowest speed to the fastest)")
    if name == "fractional_relaxation":
        return (f"hold residual decaying over many time scales at once: a power law t^-{v['alpha_f']:.2g} "
                f"after about {v['tau_f_s']:.3g} s")
    if name == "drift":
        return "error grows linearly with time, also before contact and after the return"
    if name == "offset":
        return "a constant error, also out of contact"
    if name == "friction":
        return "residual steps at ramp start and end with the sign of velocity"
    if name == "delay":
        return ("residual follows the force's rate of change: the reading lags by about "
                f"{v['delay_s'] * 1000:.3g} ms")
    if name == "contact_offset":
        k, u = base.trials[0].length_unit
        x0 = v["x0_mm"] * 1e-3
        return (f"model force rises too {'early' if x0 > 0 else 'late'}: contact starts about "
                f"{abs(x0) / k:.3g} {u} {'later' if x0 > 0 else 'earlier'}")
    if name == "compliance":
        return (f"ramp residual grows with force: the frame gives way (k_frame about "
                f"{v['k_frame_N_per_m']:.3g} N/m)")
    return ""


def _indistinguishable(passing: list[Suggestion], trials: list[TrialData]) -> list[dict]:
    """Top candidates that explain the same residual equally well."""
    if len(passing) < 2:
        return []
    a, b = passing[0], passing[1]
    close_rmse = abs(a.rmse_N - b.rmse_N) <= 0.05 * a.rmse_N
    if not close_rmse or (b.delta_bic - a.delta_bic) > 0.1 * abs(a.delta_bic) + 10:
        return []
    # they must also predict the same thing: their fitted curves nearly coincide on every
    # sample (a candidate outside the refitted leaders was fitted on the decimated copy)
    diff = np.concatenate([p - q for p, q in zip(evaluate(a.fit.model, a.fit.values, trials),
                                                 evaluate(b.fit.model, b.fit.values, trials), strict=True)])
    if np.sqrt(np.mean(diff ** 2)) > 0.5 * a.fit.noise_N:
        return []
    key = frozenset({a.effect, b.effect})
    return [{"effects": [a.effect, b.effect],
             "why": "both explain the same residual on these trials",
             "separate_with": SEPARATE_BY.get(key, GENERIC_SEPARATION)}]


def _absorbed(base: FitResult, ranked: list[Suggestion]) -> list[dict]:
    """An effect the criterion supports strongly although it barely changes the error: the
    model's own terms mimic it on these trials. Name the term that moves to absorb it."""
    for s in ranked:
        if s.delta_bic >= ABSORBED_BIC or s.rmse_drop >= MIN_DROP:
            continue
        moves: dict[str, float] = {}
        for e in base.model.effects:
            if e.name in s.dropped:  # a swap's dropped effect is gone, not reshaped
                continue
            for p in e.params:
                a, b = base.values[p.name], s.fit.values[p.name]
                moves[e.name] = max(moves.get(e.name, 0.0), abs(b - a) / max(abs(a), 1e-12))
        twin = max(moves, key=moves.get)
        if moves[twin] < ABSORBED_MOVE:
            continue  # the model barely reshapes: a small real gain on a long record, not a mimic
        return [{"effects": [s.effect, twin],
                 "why": f"{s.effect} is strongly supported (dBIC {s.delta_bic:.0f}) yet changes the error by "
                        f"only {s.rmse_drop * 100:.1f} %: {twin} takes its shape on these trials "
                        f"({twin}'s parameters move by up to {moves[twin] * 100:.0f} %)",
                 "separate_with": SEPARATE_BY.get(frozenset({s.effect, twin}), GENERIC_SEPARATION)}]
    return []


def _unexplained(base: FitResult, best: Suggestion | None) -> bool | str:
    """False when the best addition (or, with none, the base model) leaves only noise; else
    where the structured residual remains."""
    res = best.fit if best else base
    if res.adequate:
        return False
    worst = max(((ph, s.rmse_N) for ph, s in res.phases.items() if s), key=lambda x: x[1])
    what = f"with {base.model.name} alone"
    if best:
        what = f"with {best.effect}" + (f", without {' and '.join(best.dropped)}," if best.dropped else "")
    text = (f"{what} the error is still {res.overall.rmse_N / max(res.noise_N, 1e-300):.2f}x the noise "
            f"(worst in {worst[0]}: {res.force_text(worst[1])}; residual correlated over "
            f"{res.white_L:.0f} samples, "
            f"noise {res.noise_L:.0f})")
    shape = describe(res.trials, res.residuals, res.noise_N, res.force_text)
    return f"{text}; the residual is {shape}" if shape else text


def _summary(base: FitResult, best: Suggestion | None, twins: list[dict], unexplained: bool | str,
             closest: Suggestion | None = None, partial: str = "", runner_up: Suggestion | None = None,
             beyond: Suggestion | None = None) -> str:
    """Best-supported effect first with its evidence, then any look-alike and the protocol that
    would separate them, then what is left unexplained: the answer is never replaced by a note.
    An addition that still leaves a structured residual and explains only part of it (or leaves
    the trials disagreeing) is the closest the catalogue comes, not the answer; one the record
    cannot support (`beyond`, when nothing else passes) is a design question."""
    parts = []
    if best is not None:
        parts.append(f"most likely missing: {best.label} (dBIC {best.delta_bic:.1f}, RMSE "
                     f"{base.force_text(base.overall.rmse_N)} -> {base.force_text(best.rmse_N)}, error down "
                     f"{best.rmse_drop * 100:.0f} %)")
        if best.unsupported:
            parts.append(f"with it {best.unsupported}: named on decisive evidence, its standard errors rest "
                         "on too little")
        if runner_up is not None and runner_up.delta_bic < best.delta_bic:
            parts.append(f"ranked above {runner_up.effect} (dBIC {runner_up.delta_bic:.1f} against the base) "
                         f"by {runner_up.pair_bic:.1f} at the better fits' effective samples")
    elif base.adequate:
        parts.append("the model is adequate: its residual is at the sensor-noise level; nothing to add")
    else:
        worst = max(((ph, s.rmse_N) for ph, s in base.phases.items() if s), key=lambda x: x[1])
        # a residual within the noise overall fails on a phase or on its shape: which one is said
        because = f"; {why}" if (why := base.inadequate_because()) else ""
        parts.append(f"the model is NOT adequate (RMSE {base.force_text(base.overall.rmse_N)} vs noise "
                     f"{base.force_text(base.noise_N)}; worst in {worst[0]}: {base.force_text(worst[1])}"
                     f"{because}) and "
                     + ("the record cannot support a richer model" if beyond else
                        "no effect in the catalogue explains it"))
        if beyond is not None:
            parts.append(f"{_beyond(beyond)}; whether it is there is a design question, not a fit: "
                         f"{BEYOND_DESIGN}")
        if closest is not None:
            parts.append(f"closest: {closest.label} (dBIC {closest.delta_bic:.1f}, RMSE "
                         f"{base.force_text(closest.rmse_N)}, error down {closest.rmse_drop * 100:.0f} %), "
                         "which "
                         f"still leaves a structured residual: {partial}")
        if unexplained:
            parts.append(f"unexplained: {unexplained}")
    for t in twins:
        a, b = t["effects"]
        if best is not None and best.effect in (a, b):
            other = b if a == best.effect else a
            parts.append(f"look-alike: {other} (on these trials {best.effect} and {other} cannot be told "
                         f"apart: {t['why']}); to separate them, try: {t['separate_with']}")
        else:
            parts.append(f"look-alikes: {a} and {b} cannot be told apart on these trials ({t['why']}); "
                         f"to separate them, try: {t['separate_with']}")
    if best is not None and unexplained:
        parts.append(f"still unexplained: {unexplained}")
    return "; ".join(parts)


def _beyond(b: Suggestion) -> str:
    """What a candidate beyond the richness floor would do, and why it is not fitted."""
    return (f"{b.label} would lower the error by {b.rmse_drop * 100:.0f} % (dBIC {b.delta_bic:.1f}), "
            f"but with it {b.unsupported}")


AUTO_STEPS = 5  # --auto's steps unless --auto-steps says otherwise


def auto(base: FitResult, registry: dict[str, Effect], max_steps: int = AUTO_STEPS) -> list[dict]:
    """Stepwise selection: add the best effect and refit, then drop any earlier addition the
    criterion no longer supports (effects hidden together can make a proxy look best first);
    repeat while `explain` suggests an effect: for a model that is not adequate any that passes
    the criterion, for an adequate one only a decisive one (the same rule `--explain` applies, so
    the search never ends where `--explain` on its final model would still name an effect: it
    stopped at "adequate" on a real QI curve whose drift `--explain` then named at dBIC -14.8,
    the error down 6 %). A step may be a swap:
    the best suggestion drops an effect of the model it made unneeded or unphysical
    (`explain`'s `_swapped`), and the step adds the one and drops the other.

    Every step's model is refitted from several starts (`refit`): the previous step's
    solution and the catalogue's own, so a step is not bound to the basin the first one found
    and is no worse than the same model fitted alone (`rig analyze --add`). Whether an earlier
    addition is dropped is judged from the fuller model's solution without it (the nearest
    fit of the slimmer model, and a cheap one); a drop is then refitted from several starts
    too. Two models are compared at the simpler one's N_eff, as every delta_BIC is."""
    steps = [{"step": 0, "added": None, "removed": None, "fit": base, "delta_bic": 0.0, "why": ""}]
    current = base
    added: list[str] = []
    for i in range(1, max_steps + 1):
        ex = explain(current, registry)
        if not ex.suggestions:
            steps[-1]["explanation"] = ex  # of the final model: a caller that shows it need not redo it
            if ex.beyond:  # a richer model is a design question: say so where the search stopped
                steps[-1]["stopped"] = (f"stopped: the record cannot support a richer model "
                                        f"({_beyond(ex.beyond[0])}); {BEYOND_DESIGN}")
            break
        best = ex.suggestions[0]
        before = current
        current = refit(best.fit)
        dk = len(current.model.params) - len(before.model.params)
        # at the simpler model's N_eff: the previous one for an addition, the new one for a swap
        # (which removes, as a drop is judged, below)
        simpler = current if best.dropped else before
        dbic = delta_bic(_rss(current) / max(_rss(before), 1e-300), dk, simpler.n_eff)
        added = [n for n in added if n not in best.dropped] + [best.effect]
        # a swap: the step adds one effect and drops those of the model it made unneeded
        steps.append({"step": i, "added": best.effect, "removed": " ".join(best.dropped) or None,
                      "fit": current, "delta_bic": float(dbic), "why": best.why,
                      "indistinguishable": ex.indistinguishable})
        for name in list(added[:-1]):
            slim = fit(without(current.model, (name,)), current.trials, starts=1, initial=current.values,
                       tol=1e-8, max_nfev=REFIT_NFEV, polish=False)
            dk = len(current.model.params) - len(slim.model.params)
            # the slimmer model against the current one, at the slimmer one's N_eff
            dbic = -delta_bic(_rss(current) / max(_rss(slim), 1e-300), dk, slim.n_eff)
            if dbic < 0:  # simpler is better: the earlier effect was a stand-in
                slim = refit(slim)
                dbic = -delta_bic(_rss(current) / max(_rss(slim), 1e-300), dk, slim.n_eff)
                added.remove(name)
                current = slim
                steps.append({"step": i, "added": None, "removed": name, "fit": current,
                              "delta_bic": float(dbic), "why": f"{name} no longer needed"})
    else:
        if not current.adequate:  # the bound ended the search, not the record: say so
            steps[-1]["stopped"] = (f"stopped after {max_steps} step{'s' * (max_steps > 1)}, the most allowed "
                                    "(--auto-steps); the model is not adequate yet")
    return steps


def refit(warm: FitResult, starts: int = 3) -> FitResult:
    """`warm`'s model refitted from several starts: `warm`'s own solution (the previous step's,
    carried on) and `starts` from the catalogue's starting values, as `fit` starts the model
    on its own (`rig analyze --add`). The catalogue's starts run on a decimated copy, as
    `explain` screens; the start with the lower error on every sample is refitted there, and the
    model fitted on its own from its catalogue starts at the full rate is kept if it is better."""
    model, trials = warm.model, warm.trials
    stride = max(1, min(t.n for t in trials) // SCREEN_SAMPLES)
    # the model fitted on its own, as `rig analyze --add` fits it, is always a candidate: the decimated
    # copy's best start is not always the record's, and a few unpolished steps from it not always
    # the optimum (a gel's third step stayed 5 % above it; a swap on an AFM approach 0.3 %). On a
    # record short enough not to decimate it is also the screen of the catalogue's starts
    alone = fit(model, trials)
    fresh = fit(model, [decimate(t, stride) for t in trials], starts=starts, tol=1e-8,
                polish=False) if stride > 1 else alone
    rss_fresh = float(sum(np.sum(r ** 2) for r in _residuals(model, fresh.values, trials)))
    start = fresh.values if rss_fresh < _rss(warm) else warm.values
    res = fit(model, trials, starts=1, initial=start, tol=1e-8, max_nfev=REFIT_NFEV, polish=False)
    res = alone if _rss(alone) < _rss(res) else res
    return res if _rss(res) <= _rss(warm) else warm


def _residuals(model: Model, values: dict[str, float], trials: list[TrialData]) -> list[np.ndarray]:
    return [t.force_N - p for t, p in zip(trials, evaluate(model, values, trials), strict=True)]


def _rss(res: FitResult) -> float:
    return float(np.sum(np.concatenate(res.residuals) ** 2))


def format_explain(ex: Explanation, top: int = 6) -> str:
    """The diagnosis as a table: each candidate's RMSE, error drop, dBIC and evidence (best first, `top` of
    them), then the verdict."""
    b = ex.base
    k, u = b.force_unit
    lines = [f"diagnosis of {b.model.name}: RMSE {b.force_text(b.overall.rmse_N)}, "
             f"noise {b.force_text(b.noise_N)}, "
             f"{'adequate' if b.adequate else 'NOT adequate'}; effective samples {ex.n_eff:.0f} of "
             f"{b.overall.n}",
             f"  {'effect':<18}{'RMSE ' + u:>9}{'drop':>8}{'dBIC':>10}  evidence"]
    for s in ex.ranked[:top]:
        mark = "*" if s in ex.suggestions else " "
        lines.append(f"{mark} {s.effect:<18}{s.rmse_N / k:>9.4g}{s.rmse_drop * 100:>7.1f}%"
                     f"{s.delta_bic:>10.1f}  "
                     f"{s.why}")
    lines.append(f"=> {ex.summary}")
    return "\n".join(lines)


def format_auto(steps: list[dict]) -> str:
    """The stepwise search as a table, one row a step: what was added or dropped, the RMSE overall and by
    phase, dBIC; then the final model's verdict."""
    k, u = steps[0]["fit"].force_unit
    # one word a step (a swap: "+drift/-viscous"), so the table splits on its spaces
    labels = ["/".join([*([f"+{s['added']}"] if s["added"] else []),
                        *(f"-{n}" for n in (s.get("removed") or "").split())]) or "(start)" for s in steps]
    width = max(18, max(map(len, labels)) + 1)
    head = (f"{'step':<5}{'added':<{width}}{'RMSE ' + u:>9}" + "".join(f"{p:>12}" for p in PHASES)
            + f"{'dBIC':>10}")
    lines = [head, "-" * len(head)]
    for s, label in zip(steps, labels, strict=True):
        r = s["fit"]
        ph = "".join(f"{(r.phases[p].rmse_N / k if r.phases[p] else float('nan')):>12.4g}" for p in PHASES)
        lines.append(f"{s['step']:<5}{label:<{width}}{r.overall.rmse_N / k:>9.4g}{ph}{s['delta_bic']:>10.1f}")
    last = steps[-1]["fit"]
    lines.append(f"final model {last.model.name}: "
                 + ("adequate (residual at the sensor noise)" if last.adequate else
                    f"NOT adequate (RMSE {last.force_text(last.overall.rmse_N)} vs noise "
                    f"{last.force_text(last.noise_N)}"
                    + (f"; {why})" if (why := last.inadequate_because()) else ")")))
    if steps[-1].get("stopped"):
        lines.append(steps[-1]["stopped"])
    if (rich := richness(last)):
        lines.append(f"the record supports this model only in part: {rich}; its standard errors rest on too "
                     "little (the model it started from was already this rich)" if len(steps) == 1 else
                     f"the record supports this model only in part: {rich}")
    return "\n".join(lines)
