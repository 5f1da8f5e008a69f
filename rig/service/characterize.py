"""A specimen characterised by the rig itself: run a trial, fit every trial so far jointly,
diagnose, choose the next trial, until the model is right and its parameters are determined.

    start     the protocol given, or an exploratory ramp-hold inside the rig's limits
    each turn run the trial (an ordinary trial: every limit, stop and estop as for `rig run`);
              fit the model to every trial so far; add what the diagnosis names (`--auto`'s
              stepwise selection); then decide:
                look-alikes left   the protocol that best separates them (`--design`)
                adequate, some parameter's relative standard error above the target
                                   the candidate protocol that most reduces the largest one
                                   (expected information: the fit's covariance plus the
                                   candidate's Fisher information at the fitted values)
    stop      the model adequate and every parameter determined to the target ("done"); no
              candidate separating or informing better within the limits ("nothing better"); the
              trials or the time budget spent ("budget"); a trial that did not complete
              ("stopped": the trial's own stop returned the probe, the journal says so)

Every decision goes to a journal (JSON lines, beside the trial logs): what was fitted, what was
suspected, which protocols were considered and why one was chosen. Candidates come from the
same generator `--design` uses (other speeds, depths, holds, staircases, cycles, a triangle
wave at depth), each checked against the rig's limits and the specimen's force budget before
it is considered.
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rig.analysis.analyze import load_inputs
from rig.analysis.design import (
    SLOWEST,
    Candidate,
    design,
    inadmissible,
    protocol_text,
    rig_candidates,
    shape_of,
    slowed,
)
from rig.analysis.explain import Explanation, auto, explain
from rig.analysis.fit import FitResult, fit
from rig.control.trial import TrialResult
from rig.errors import RigError
from rig.models.catalogue import build_model
from rig.records import ReadOptions
from rig.service.run import RunOptions, run_trial
from rig.specs.config import RigConfig
from rig.specs.protocol import Protocol, check_limits, parse_protocol, plan

TARGET_RSE = 0.05
MAX_TRIALS = 6
BUDGET_MIN = 30.0
REST_S = 60.0  # between trials: the specimen recovers (counted in the budget; waited at speed 1)
SEPARATES = 2.0  # a designed trial must leave the wrong model this many noise levels off
TRIAL_MARGIN_S = 5.0  # a trial's tare and settling beyond its candidate's motion
INFORMATION_GAIN = 0.9  # a candidate must bring the largest relative error below this share of today's


@dataclass
class Turn:
    """One trial of the campaign and what followed from it."""

    protocol: str
    why: str
    log: str = ""
    outcome: str = ""
    model: str = ""
    adequate: bool = False
    rmse_over_noise: float = math.nan
    max_rse: float = math.nan
    worst: str = ""
    lookalikes: list[list[str]] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in vars(self).items()}


@dataclass
class Campaign:
    specimen: str
    status: str = "running"  # done, nothing better, budget, stopped
    reason: str = ""
    turns: list[Turn] = field(default_factory=list)
    final: FitResult | None = None
    journal: Path | None = None
    elapsed_s: float = 0.0  # specimen time: the trials and the rests between them
    trial_ended: float | None = None  # time.monotonic() when the last trial ended

    def summary(self) -> dict:
        out = {"specimen": self.specimen, "status": self.status, "reason": self.reason,
               "journal": str(self.journal) if self.journal else None, "specimen_time_s": self.elapsed_s,
               "trials": [t.as_dict() for t in self.turns]}
        if self.final is not None:
            f = self.final
            out["model"] = {"name": f.model.name, "effects": f.model.effect_names, "adequate": f.adequate,
                            "parameters": {k: {"value": v, "stderr": _finite(f.stderr.get(k)),
                                               "rse": _finite(_rse(f, k))} for k, v in f.values.items()}}
        return out


@dataclass
class Request:
    specimen: str
    config: RigConfig
    out_dir: Path
    model: str = "proposed"
    indenter: str | None = None
    first: str | None = None  # protocol file of the first trial; None: exploratory
    first_text: str | None = None  # or its text (the daemon receives the file's contents)
    max_trials: int = MAX_TRIALS
    budget_min: float = BUDGET_MIN
    target_rse: float = TARGET_RSE
    rest_s: float = REST_S
    speed: float = 1.0
    seed_per_trial: bool = True  # the simulated rig: a new noise draw for every trial
    say: Callable[[str], None] = print
    # more RunOptions for trial n (on_start, on_tick: a watcher, a stop button)
    trial_options: Callable[[int], dict] | None = None
    # runs trial n on devices someone else holds (the daemon's): (protocol, n, log path) -> result
    runner: Callable[[Protocol, int, Path], TrialResult] | None = None
    stop: threading.Event | None = None  # set: no further trial (a rest in progress ends at once)
    on_event: Callable[[str, dict], None] | None = None  # each journal event as written (a live view)
    warned: set[str] = field(default_factory=set)


def _finite(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _rse(f: FitResult, name: str) -> float:
    err, v = f.stderr.get(name), f.values[name]
    if err is None or not math.isfinite(err):
        return math.inf
    return abs(err) / max(abs(v), 1e-300)


def _tissue_params(f: FitResult) -> list[str]:
    """The parameters the campaign must determine: the specimen's, not a record's own zero."""
    own = {p.name for e in f.model.effects if e.of_record for p in e.params}
    return [p.name for p in f.model.params if p.name.partition("@")[0] not in own]


def exploratory(config: RigConfig) -> str:
    """A ramp-hold-return well inside the limits: two thirds of the travel at 15 % of the speed
    limit, a 30 s hold, the return at half the speed limit."""
    lim = config.limits
    start = config.sim.slider.start_mm if config.slider.backend == "sim" else 0.0
    depth = round(2.0 / 3.0 * (lim.travel_mm[1] - start), 1)
    speed = round(0.15 * lim.max_speed_mm_s, 2)
    back = round(0.5 * lim.max_speed_mm_s, 2)
    return ("name: exploratory ramp-hold\ndescription: >-\n  the campaign's first look at the specimen: one "
            "ramp, a hold, the return\nsteps:\n"
            f"  - ramp:   {{to_mm: {depth:g}, speed_mm_s: {speed:g}}}\n"
            "  - hold:   {duration_s: 30}\n"
            f"  - return: {{to_mm: 0, speed_mm_s: {back:g}}}\n")


class Journal:
    """JSON lines, one per event, flushed as written (a stopped campaign keeps all of it)."""

    def __init__(self, path: Path, on_event: Callable[[str, dict], None] | None = None) -> None:
        self.path = path
        self.on_event = on_event
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(path, "a", encoding="utf-8")  # noqa: SIM115 - held for the campaign

    def write(self, event: str, **data) -> None:
        self._fh.write(json.dumps({"t": time.time(), "event": event, **data}, default=_plain) + "\n")
        self._fh.flush()
        if self.on_event is not None:
            self.on_event(event, data)

    def close(self) -> None:
        self._fh.close()


def _plain(o):
    if isinstance(o, float | np.floating):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, np.integer):
        return int(o)
    return str(o)


def characterize(req: Request) -> Campaign:
    camp = Campaign(req.specimen)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    camp.journal = req.out_dir / f"characterize-{req.specimen}-{stamp}.jsonl"
    journal = Journal(camp.journal, req.on_event)
    journal.write("start", journal=str(camp.journal), specimen=req.specimen, model=req.model,
                  indenter=req.indenter, target_rse=req.target_rse, max_trials=req.max_trials,
                  budget_min=req.budget_min, limits=vars(req.config.limits))
    try:
        _run(req, camp, journal)
    finally:
        journal.write("end", status=camp.status, reason=camp.reason, summary=camp.summary())
        journal.close()
    return camp


def _run(req: Request, camp: Campaign, journal: Journal) -> None:
    text = req.first_text or (Path(req.first).read_text() if req.first else exploratory(req.config))
    why = (f"given ({req.first or 'with the request'})" if req.first or req.first_text else
           "exploratory: the first look inside the rig's limits")
    logs: list[str] = []
    model_name, extra = req.model, []
    last: FitResult | None = None
    budget_s = 60.0 * req.budget_min
    while True:
        proto = parse_protocol(text, "<campaign>")
        check_limits(proto, req.config)
        duration = plan(proto, req.config).duration_s
        if len(camp.turns) >= req.max_trials:
            camp.status, camp.reason = "budget", f"{req.max_trials} trials run (--max-trials)"
            break
        rest, wait = _rest_before_next(req, camp)
        if camp.elapsed_s + rest + duration > budget_s:
            camp.status = "budget"
            camp.reason = (f"the next trial ({duration:.0f} s after a {rest:.0f} s rest) would pass the "
                           f"{req.budget_min:g} min budget")
            break
        if wait and req.speed:  # the specimen recovers before the next trial
            if req.stop is not None:
                req.stop.wait(wait / req.speed)
            else:
                time.sleep(wait / req.speed)
        if req.stop is not None and req.stop.is_set():
            camp.status, camp.reason = "stopped", f"stopped on request after {len(camp.turns)} trials"
            journal.write("decision", kind="stopped", why=camp.reason)
            break
        camp.elapsed_s += rest
        turn = Turn(proto.name, why)
        camp.turns.append(turn)
        journal.write("trial", n=len(camp.turns), protocol=proto.name, why=why, yaml=text, duration_s=duration)
        req.say(f"trial {len(camp.turns)}: {proto.name} ({duration:.0f} s): {why}")
        result = _one_trial(req, proto, len(camp.turns))
        camp.elapsed_s += result.duration_s
        camp.trial_ended = time.monotonic()
        turn.log, turn.outcome = str(result.log_path), result.outcome
        journal.write("ran", n=len(camp.turns), outcome=result.outcome, log=str(result.log_path),
                      fault=result.fault, samples=result.samples)
        if result.outcome != "completed":
            camp.status = "stopped"
            camp.reason = (f"trial {len(camp.turns)} ended {result.outcome}"
                           + (f": {result.fault}" if result.fault else "") + "; the campaign stops with it")
            break
        logs.append(str(result.log_path))
        last, ex, extra = _fit_all(req, logs, model_name, extra, last, turn, journal)
        camp.final = last
        req.say(f"  {turn.model}: RMSE {turn.rmse_over_noise:.2f}x the noise, "
                f"{'adequate' if turn.adequate else 'NOT adequate'}; largest relative error "
                f"{100 * turn.max_rse:.1f} % ({turn.worst})")
        nxt = _decide(req, last, ex, turn, journal, camp)
        if nxt is None:
            break
        text, why = nxt


def _one_trial(req: Request, proto, n: int):
    config = req.config
    if req.seed_per_trial and config.slider.backend == "sim":
        from dataclasses import replace

        config = replace(config, sim=replace(config.sim, seed=config.sim.seed + n - 1))
    log = req.out_dir / f"{req.specimen}-trial{n}.mcap"
    if req.runner is not None:
        return req.runner(proto, n, log)
    more = req.trial_options(n) if req.trial_options else {}
    return run_trial(proto, config, RunOptions(specimen=req.specimen, speed=req.speed, progress=False,
                                               log_path=log, notes=f"characterize trial {n}", **more),
                     warn=lambda w: _warn_once(req, w))


def _warn_once(req: Request, text: str) -> None:
    """The rig's warnings (the same for every trial of a campaign) said once, on stderr."""
    if text not in req.warned:
        req.warned.add(text)
        print(text, file=sys.stderr)


def _fit_all(req: Request, logs: list[str], model_name: str, extra: list[str], last: FitResult | None,
             turn: Turn, journal: Journal) -> tuple[FitResult, Explanation, list[str]]:
    inp = load_inputs(logs, [], [], ReadOptions(), indenter=req.indenter)
    model = build_model(model_name, extra, inp.registry)
    base = fit(model, inp.trials, initial=last.values if last is not None else None)
    steps = auto(base, inp.registry)
    final = steps[-1]["fit"]
    for s in steps[1:]:
        journal.write("model", added=s["added"], removed=s["removed"], delta_bic=s["delta_bic"], why=s["why"])
    ex = explain(final, inp.registry)
    v = ex.verdict()
    turn.model = final.model.name
    turn.adequate = bool(final.adequate)
    turn.rmse_over_noise = final.overall.rmse_N / max(final.noise_N, 1e-300)
    rse = {k: _rse(final, k) for k in _tissue_params(final)}
    turn.worst = max(rse, key=rse.get) if rse else ""
    turn.max_rse = rse[turn.worst] if rse else 0.0
    turn.lookalikes = [list(x["effects"]) for x in v["lookalikes"]]
    journal.write("fit", trials=len(logs), model=final.model.name, effects=final.model.effect_names,
                  adequate=turn.adequate, rmse_N=final.overall.rmse_N, noise_N=final.noise_N,
                  parameters={k: {"value": final.values[k], "stderr": _finite(final.stderr.get(k)),
                                  "rse": _finite(rse.get(k))} for k in final.values},
                  diagnosis=v["text"], suspected=[s.effect for s in ex.ranked[:5]], lookalikes=turn.lookalikes)
    plain = set(build_model(model_name, [], inp.registry).effect_names)
    return final, ex, [e for e in final.model.effect_names if e not in plain]


def _rest_before_next(req: Request, camp: Campaign) -> tuple[float, float]:
    """The rest before the next trial, and what of it is still to wait, in specimen time. The
    rest begins when the last trial ends: the fits and the choice that follow it run while the
    specimen recovers, so a rest already outlasted by them is not waited again (and a fit that
    outlasts the rest counts as rest: the specimen waited for it)."""
    if not camp.turns:
        return 0.0, 0.0
    gone = (time.monotonic() - camp.trial_ended) * req.speed if camp.trial_ended is not None else 0.0
    rest = max(req.rest_s, gone)
    return rest, rest - gone


def _time_left(req: Request, camp: Campaign) -> float:
    """Specimen time the next trial may take: the budget less what was spent and the rest before
    it, less a margin for what a candidate's motion leaves out (the tare, the drive's settling)."""
    return 60.0 * req.budget_min - camp.elapsed_s - _rest_before_next(req, camp)[0] - TRIAL_MARGIN_S


def _decide(req: Request, f: FitResult, ex: Explanation, turn: Turn, journal: Journal,
            camp: Campaign) -> tuple[str, str] | None:
    if not ex.lookalikes and f.adequate and turn.max_rse <= req.target_rse:
        return _inform_or_stop(req, f, turn, journal, camp)  # done
    if not ex.lookalikes and not f.adequate:
        journal.write("decision", kind="nothing better", why=ex.summary)
        camp.status = "nothing better"
        camp.reason = f"the model is not adequate and nothing in the catalogue explains the rest: {ex.summary}"
        return None
    left = _time_left(req, camp)
    if len(camp.turns) >= req.max_trials or left <= 0:
        why = (f"{req.max_trials} trials run (--max-trials)" if len(camp.turns) >= req.max_trials else
               f"{camp.elapsed_s / 60:.1f} of the {req.budget_min:g} min budget spent, with a "
               f"{req.rest_s:.0f} s rest before any next trial")
        journal.write("decision", kind="budget", why=why)
        camp.status, camp.reason = "budget", why
        return None
    if ex.lookalikes:
        pair = ex.lookalikes[0]["effects"]
        try:
            d = design(ex, req.config, max_duration_s=left)
        except RigError as exc:
            journal.write("decision", kind="nothing better", why=str(exc))
            camp.status = "nothing better"
            camp.reason = f"{pair[0]} and {pair[1]} cannot be told apart within the rig's limits ({exc})"
            return None
        if (d.best.separation_N or 0.0) < SEPARATES * d.noise_N:
            journal.write("decision", kind="cannot separate", effects=pair, protocol=d.best.name,
                          separation_over_noise=(d.best.separation_N or 0.0) / d.noise_N,
                          why=f"the best protocol within the limits separates them by less than {SEPARATES:g}x "
                              "the noise: left as look-alikes")
            return _inform_or_stop(req, f, turn, journal, camp)
        journal.write("decision", kind="separate", effects=pair, protocol=d.best.name,
                      considered=[{"protocol": c.name, "separation_N": c.separation_N} for c in d.ranked[:12]],
                      refused=d.refused, why=d.best.why)
        miss = (d.best.separation_N or 0) / d.noise_N
        return d.yaml, (f"separate {pair[0]} from {pair[1]}: {d.best.name} (the wrong model would still miss "
                        f"it by {miss:.1f}x the noise)")
    return _inform_or_stop(req, f, turn, journal, camp)


def _inform_or_stop(req: Request, f: FitResult, turn: Turn, journal: Journal,
                    camp: Campaign) -> tuple[str, str] | None:
    if turn.max_rse <= req.target_rse:
        journal.write("decision", kind="done", worst=turn.worst, max_rse=turn.max_rse,
                      why=f"adequate; every parameter within {100 * req.target_rse:g} %")
        camp.status = "done"
        camp.reason = (f"the model is adequate and every parameter is determined to {100 * req.target_rse:g} % "
                       f"(largest: {turn.worst}, {100 * turn.max_rse:.2f} %)")
        return None
    left = _time_left(req, camp)
    best = _most_informative(req, f, journal, left, left / max(req.max_trials - len(camp.turns), 1))
    if best is None:
        camp.status = "nothing better"
        camp.reason = (f"no protocol within the limits and the budget left brings {turn.worst} "
                       f"({100 * turn.max_rse:.1f} %) below {100 * INFORMATION_GAIN:g} % of its error")
        return None
    c, after, so_far = best
    also = (f" ({100 * so_far:.1f} % if its samples are worth what the earlier trials' were)"
            if math.isfinite(so_far) else "")
    text = protocol_text(c, f"inform {turn.worst}: {c.name}", req.config.limits.max_force_N,
                         [f"Chosen by rig characterize to narrow {turn.worst}: expected largest relative "
                          f"error {100 * turn.max_rse:.2f} % -> {100 * after:.2f} %{also}."])
    return text, (f"the largest relative error ({turn.worst}, {100 * turn.max_rse:.1f} %) is expected to fall "
                  f"to {100 * after:.1f} % with {c.name}{also}")


def _most_informative(req: Request, f: FitResult, journal: Journal, max_duration_s: float = math.inf,
                      share_s: float = math.inf) -> tuple[Candidate, float, float] | None:
    """The candidate protocol after which the largest relative standard error is smallest, from
    the fit's covariance and the candidate's Fisher information at the fitted values (white noise
    of the fit's level, discounted by the fit's own effective share of independent samples),
    among those that fit in `max_duration_s` of specimen time. Each candidate shorter than
    `share_s` (the time left shared among the trials still allowed) is also considered with its
    ramps slowed to fill it (`design.slowed`): time the budget holds for a trial is information.

    Also, for each, the same forecast with the candidate's information worth what the trials so
    far proved theirs to be (`_as_so_far`): the white-noise forecast counts every sample as new,
    and on a simulated specimen with a frame spring the fit's actual variances of the elastic
    terms were 100-160x their white-noise ones (a wandering zero, the tares), so "expected 13 %"
    became 62 %; the calibrated forecast said 70 %. The choice is the white-noise one: on the two
    seeds where every candidate was run, its best three were the best three run, in order; the
    text gives both.
    Returns (candidate, forecast, calibrated forecast)."""
    if f.covariance is None:
        return None
    names = f.model.param_names
    keep = [names.index(n) for n in _tissue_params(f)]
    values = np.array([f.values[n] for n in names])
    # in units of each parameter's own size: the covariance of parameters ten decades apart in
    # SI would lose its small directions to the pseudo-inverse's cut
    size = np.array([max(abs(v), math.sqrt(abs(c)), 1e-300) for v, c in zip(values, np.diag(f.covariance),
                                                                               strict=True)])
    cov = np.asarray(f.covariance, dtype=float) / np.outer(size, size)
    try:
        info_now = np.linalg.pinv(cov, rcond=1e-12, hermitian=True)
    except np.linalg.LinAlgError:
        return None
    n_all = sum(t.n for t in f.trials)
    share = min(max(f.n_eff / max(n_all, 1), 1e-6), 1.0)
    noise2 = max(f.noise_N, 1e-300) ** 2

    def jacobian(m) -> np.ndarray:
        J = np.empty((len(m.t_s), len(names)))
        for j, v in enumerate(values):
            h = 1e-4 * (abs(v) or 1.0)
            up, dn = values.copy(), values.copy()
            up[j] += h
            dn[j] -= h
            J[:, j] = (f.model.predict(up, m) - f.model.predict(dn, m)) / (2 * h) * size[j]
        return J

    def worst_after(info: np.ndarray) -> float:
        after = np.linalg.pinv(info, rcond=1e-12, hermitian=True)
        se = np.sqrt(np.maximum(np.diag(after), 0.0)) * size
        return max(se[i] / max(abs(values[i]), 1e-300) for i in keep) if keep else 0.0

    calibrate = _as_so_far(cov, share * sum(_gram(jacobian(t.motion)) for t in f.trials) / noise2)
    cands = rig_candidates(shape_of(f.trials), req.config)
    if math.isfinite(share_s):
        fill = min(share_s, max_duration_s)
        # never slower than a quarter of the first trial's speed: each trial could otherwise go a
        # quarter slower than the slowest before it, and on a 30 min budget the ramps fell to
        # 0.12 mm/s, six-minute trials whose fits took four minutes each
        floor = SLOWEST * _first_speed(f.trials)
        cands += [s for s in (slowed(c, fill, req.config, floor) for c in cands) if s is not None]
    scored, refused = [], []
    for c in cands:
        m = c.trial.motion
        pred = f.model.predict(f.values, m)
        duration = float(m.t_s[-1])
        why = (f"{c.name}: {duration:.0f} s, over the {max_duration_s:.0f} s the budget leaves"
               if duration > max_duration_s else inadmissible(c, float(np.max(pred)), req.config))
        if why:
            refused.append(why)
            continue
        new = share * _gram(jacobian(m)) / noise2
        try:
            rse = worst_after(info_now + new)
            so_far = worst_after(info_now + calibrate(new)) if calibrate else math.nan
        except np.linalg.LinAlgError:
            continue
        scored.append((rse, so_far, c))
    now = max(_rse(f, names[i]) for i in keep) if keep else 0.0
    scored.sort(key=lambda x: x[0])
    considered = [{"protocol": c.name, "expected_max_rse": r, "expected_max_rse_noise_as_so_far": _finite(q)}
                  for r, q, c in scored[:12]]
    journal.write("decision", kind="inform", now=now, considered=considered, refused=refused)
    if not scored or scored[0][0] > INFORMATION_GAIN * now:
        return None
    rse, so_far, c = scored[0]
    return c, rse, so_far


def _first_speed(trials) -> float:
    """The ramp speed of the first trial that has a ramp (m/s)."""
    for t in trials:
        try:
            return shape_of([t]).speed_m_s
        except RigError:
            continue
    return 0.0


def _gram(J: np.ndarray) -> np.ndarray:
    return J.T @ J


def _as_so_far(cov: np.ndarray, white_info: np.ndarray) -> Callable[[np.ndarray], np.ndarray] | None:
    """The map that makes white-noise information worth what the trials so far showed theirs to
    be: with C their fit's covariance and W their white-noise information, A = C^1/2 W^1/2 takes
    the white-noise covariance W^-1 to C (A W^-1 A^T = C), and a candidate's information I
    becomes A^-T I A^-1 (W itself becomes C^-1). Any A R with R a rotation does the same to W;
    the symmetric roots are the choice made here, and where C and W do not share their axes
    another choice would move the forecast by some per cent. None when either matrix is
    singular."""
    def root(M: np.ndarray) -> np.ndarray | None:
        w, V = np.linalg.eigh(0.5 * (M + M.T))
        if not np.all(w > 1e-12 * max(float(w.max()), 1e-300)):
            return None
        return (V * np.sqrt(w)) @ V.T

    try:
        a, b = root(cov), root(white_info)
        if a is None or b is None:
            return None
        inv = np.linalg.inv(a @ b)
    except np.linalg.LinAlgError:
        return None
    return lambda info: inv.T @ info @ inv


def format_campaign(camp: Campaign) -> str:
    lines = [f"specimen   {camp.specimen}", f"status     {camp.status}: {camp.reason}",
             f"trials     {len(camp.turns)} in {camp.elapsed_s / 60:.1f} min of specimen time (rests included)"]
    for i, t in enumerate(camp.turns, 1):
        tail = (f"{t.model}: {t.rmse_over_noise:.2f}x noise, {'adequate' if t.adequate else 'not adequate'}, "
                f"largest error {100 * t.max_rse:.1f} % ({t.worst})" if t.model else t.outcome)
        lines.append(f"  {i}. {t.protocol}  [{t.why}]\n     -> {tail}")
    if camp.final is not None:
        f = camp.final
        lines.append(f"model      {f.model.name}  ({', '.join(f.model.effect_names)}); "
                     f"{'adequate' if f.adequate else 'NOT adequate'}")
        for k in _tissue_params(f):
            err = f.stderr.get(k)
            e = f"+/- {err:.4g}" if err is not None and math.isfinite(err) else "(not determined)"
            lines.append(f"  {k:<22} {f.values[k]:.5g} {e}  ({100 * _rse(f, k):.2f} %)")
    lines.append(f"journal    {camp.journal}")
    return "\n".join(lines)


def plot_campaign(camp: Campaign, path: Path) -> Path:
    """The error falling trial by trial: RMSE over the noise and the largest relative error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [t for t in camp.turns if t.model]
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4))
    n = range(1, len(done) + 1)
    a.plot(n, [t.rmse_over_noise for t in done], "o-")
    a.axhline(1.0, color="0.6", lw=0.8)
    a.set(xlabel="trial", ylabel="RMSE / noise", title="model error")
    b.semilogy(n, [100 * t.max_rse for t in done], "o-")
    b.set(xlabel="trial", ylabel="largest relative error (%)", title="parameters")
    for ax in (a, b):
        ax.set_xticks(list(n))
    fig.suptitle(f"{camp.specimen}: {camp.status}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
