"""A specimen characterised by the rig itself: run a trial, fit every trial so far jointly,
diagnose, choose the next trial, until the model is right and its parameters are determined.

    start     the protocol given, or a first look that respects a specimen of unknown stiffness:
              the surface found by force at an approach's pace, then a force-controlled ramp to
              a budget (a share of the force limit) no deeper than half the travel left, a hold,
              and back to the start position
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
wave at depth), each checked against the rig's limits before it is considered and kept a
margin from the end of the travel and from the force limit (its predicted peak at most a share
of it); after a first trial that found the surface, each starts by finding it the same way (its
depths are from there) and ends back at the start position. The journal says, trial by trial,
why its size is what it is.
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rig.analysis.diagnosis.design import (
    FORCE_SHARE,
    SLOWEST,
    ApproachFirst,
    Candidate,
    Room,
    design,
    inadmissible,
    protocol_text,
    rig_candidates,
    shape_of,
    slowed,
    trial_limit_N,
)
from rig.analysis.diagnosis.explain import Explanation, auto, explain
from rig.analysis.fitting.fit import FitResult, fit
from rig.analysis.workflow.inputs import load_inputs
from rig.control.trial import TrialResult
from rig.errors import RigError
from rig.models.catalogue import build_model
from rig.records import ReadOptions, read_record
from rig.records.record import Record
from rig.service.run import RunOptions, run_trial
from rig.specs.config import RigConfig
from rig.specs.frames import Frame
from rig.specs.protocol import (
    FORCE_SETPOINT_SHARE,
    FORCE_STEPS,
    Approach,
    Protocol,
    check_limits,
    parse_protocol,
    plan,
)

TARGET_RSE = 0.05
MAX_TRIALS = 6
BUDGET_MIN = 30.0
REST_S = 60.0  # between trials: the specimen recovers (counted in the budget; waited at speed 1)
SEPARATES = 2.0  # a designed trial must leave the wrong model this many noise levels off
TRIAL_MARGIN_S = 5.0  # a trial's tare and settling beyond its candidate's motion
INFORMATION_GAIN = 0.9  # a candidate must bring the largest relative error below this share of today's

# The first trial knows nothing of the specimen: a position ramp to a fixed depth that is gentle on
# the default tissue drives one ten times stiffer to the force limit (20.1 N, a fault, on trial 1).
# So it finds the surface by force and loads by force, to a budget.
FIRST_FORCE_SHARE = 0.25  # the first trial's force budget, a share of the force limit
FORCE_MARGIN_SHARE = FORCE_SHARE  # a designed trial's predicted peak force, at most this share of the limit
TRAVEL_MARGIN_MM = 5.0  # no trial planned closer than this to the far end of the travel
# each trial carries the margin as its own travel window, this much beyond its deepest planned
# point (a drive's overshoot at the end of a move must not fault a trial that keeps to its plan):
# checked from wherever the slider is before the trial runs, and on every tick
TRAVEL_GUARD_MM = 0.5
APPROACH_SPEED_SHARE = 0.05  # of the speed limit: the approach's pace (the force loop's own seek speed)
CONTACT_SIGMAS = 3.0  # the approach's contact threshold, in the load cell's expected noise
# of the speed limit: the first trial's own speed limit (the force loop's too; 3 mm/s, the paper's
# fastest ramp, on the simulated rig): at 1.5 mm/s the loop could not keep a soft tissue's force up
# with its setpoint (see FIRST_RAMP_S)
FIRST_SPEED_SHARE = 0.3
PACE_SHARE = 0.15  # of the speed limit: what designed trials' speeds are built around after a first look
# the first trial's force ramp, from contact to its setpoint. On a tissue ten times softer than
# the default the loop, at the trial's speed limit, falls behind a setpoint rising faster than the
# tissue's force can, and its check that the force answers the motion (5 mm with the force within
# 4 sigma: a frozen cell) stopped the first look: under a 1.5 mm/s limit in 4 of 5 seeds over 20 s,
# 1 of 12 over 45 s and none of 50 over 90 s (0.1x-0.5x), which made the first look 150 s long and
# cost the campaigns' science (relaxation2 missed in 2 of 5 bench seeds); under 3 mm/s, over 30 s,
# in none of 52 (0.1x-0.3x)
FIRST_RAMP_S = 30.0
OVERSHOOT_SHARE = 0.05  # the force loop's overshoot at most (its own target)
PEAK_SIGMAS = 5.0  # a reading this many times the cell's noise above the force is not a fault
FIRST_HOLD_S = 30.0
# a later trial's approach searches this much past the deepest surface found so far (on the
# simulated rig the contact moved by up to 1.3 mm from seed to seed, 17-19 mm deep on a tissue ten
# times softer than the default, 0.4-0.5 mm on one a hundred times stiffer)
SURFACE_SLACK_MM = 2.0
SURFACE_SLACK_SHARE = 0.25
MIN_DEPTH_MM = 1.0  # a designed trial needs at least this much travel past the surface
# a designed trial's predicted peak at most this times the largest force measured so far: the model
# is trusted near what it was fitted to (one fitted to a first look's 4.6 N on a specimen ten times
# stiffer than the default chose a trial predicted at 14.3 N next)
GROWTH = 2.0


@dataclass
class Turn:
    """One trial of the campaign and what followed from it."""

    protocol: str
    why: str
    size: str = ""  # why the trial is as deep and as forceful as it is
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
    """A characterisation campaign as it went: the specimen, its status and why, each trial's turn, the
    final fit, and the specimen time it took."""

    specimen: str
    status: str = "running"  # done, nothing better, budget, stopped
    reason: str = ""
    turns: list[Turn] = field(default_factory=list)
    final: FitResult | None = None
    journal: Path | None = None
    elapsed_s: float = 0.0  # specimen time: the trials and the rests between them
    trial_ended: float | None = None  # time.monotonic() when the last trial ended
    # the first trial's approach, which every designed trial repeats (None: the first had none, and
    # its depths, like theirs, are from the start position); the surfaces found, mm below the start
    approach: Approach | None = None
    surfaces_mm: list[float] = field(default_factory=list)
    by_force: bool = False  # the first trial loaded under force control: its pace was the specimen's
    # where the first trial started, slider coordinates: the fits' zero for every trial
    start_mm: float | None = None
    records: list[Record] = field(default_factory=list)  # the trials as fitted, positions from start_mm

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
    """What a campaign is asked to do: the specimen, the rig and where its logs go, the model and
    indenter, the first trial, its budget (trials, minutes, the error to reach), the rest between
    trials and the margins every planned trial keeps; and the hooks of whoever runs it (the
    daemon's runner, a stop event, a live view)."""

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
    first_force_share: float = FIRST_FORCE_SHARE  # the first trial's force budget, of the force limit
    force_margin_share: float = FORCE_MARGIN_SHARE  # a designed trial's predicted peak, of the force limit
    travel_margin_mm: float = TRAVEL_MARGIN_MM  # kept from the far end of the travel by every trial planned
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


@dataclass
class Sized:
    """A trial's protocol text, why it was chosen, and why it is the size it is (in words and in
    figures, for the journal)."""

    text: str
    why: str
    size: str
    figures: dict = field(default_factory=dict)


def _start_mm(config: RigConfig) -> float:
    return config.sim.slider.start_mm if config.slider.backend == "sim" else 0.0


def _far_mm(req: Request) -> float:
    """The deepest a trial may be planned to go, in slider coordinates."""
    return req.config.limits.travel_mm[1] - req.travel_margin_mm


def check_request(req: Request) -> None:
    """Refuse margins and budgets that cannot be met, before anything moves."""
    if not 0.0 < req.first_force_share <= 1.0:
        raise RigError(f"first_force_share {req.first_force_share:g}: expected a share of the force limit "
                       "in (0, 1]")
    if not 0.0 < req.force_margin_share <= 1.0:
        raise RigError(f"force_margin_share {req.force_margin_share:g}: expected a share of the force limit in "
                       "(0, 1]")
    if not (math.isfinite(req.travel_margin_mm) and req.travel_margin_mm >= 0.0):
        raise RigError(f"travel_margin_mm {req.travel_margin_mm:g}: expected a finite distance >= 0 mm")
    room = _far_mm(req) - _start_mm(req.config)
    if room <= 0.0:
        raise RigError(f"travel_margin_mm {req.travel_margin_mm:g} leaves no travel: the slider starts at "
                       f"{_start_mm(req.config):g} mm and the travel ends at "
                       f"{req.config.limits.travel_mm[1]:g} mm")


def _down(x: float) -> float:
    """`x` rounded down to three significant digits (a setpoint written never above its share)."""
    if x <= 0.0:
        return x
    step = 10.0 ** (math.floor(math.log10(x)) - 2)
    return math.floor(x / step * (1 + 1e-12)) * step


def _g(x: float) -> str:
    """A number for a protocol file: at most four significant digits, never in exponent form (YAML
    would read 1e-05 as text)."""
    return np.format_float_positional(float(f"{x:.4g}"), trim="-")


def first_look(req: Request) -> Sized:
    """The first trial when none is given, safe on a specimen of any stiffness: the surface found
    by force at an approach's pace (the contact threshold CONTACT_SIGMAS times the cell's noise),
    then a force-controlled ramp to a budget (`first_force_share` of the force limit, and the
    trial's own force limit; the setpoint below it by the loop's overshoot and the cell's noise),
    never deeper than what the approach left of the travel, under a speed limit of its own; a hold
    at that depth (the relaxation) and back to the start position.

    Half the travel left (the far end less `travel_margin_mm`) to each of the approach and the
    ramp: a soft specimen's surface is found deep (at 3x the noise, 17-19 mm below where a tissue
    ten times softer than the default begins), and the check before the trial must find the
    deepest point inside the travel wherever the surface turns out to be."""
    cfg = req.config
    lim = cfg.limits
    start = _start_mm(cfg)
    room = _far_mm(req) - start
    half = math.floor(10.0 * room / 2.0) / 10.0
    budget = req.first_force_share * lim.max_force_N
    noise = cfg.estimator.noise_N
    # the budget is the trial's own force limit, checked on every reading: the setpoint leaves room
    # for the loop's overshoot (OVERSHOOT_SHARE) and a reading PEAK_SIGMAS of the noise high on top
    setpoint = _down(min(FORCE_SETPOINT_SHARE * budget, (budget - PEAK_SIGMAS * noise) / (1 + OVERSHOOT_SHARE)))
    contact = CONTACT_SIGMAS * noise
    if contact >= setpoint:
        raise RigError(f"first_force_share {req.first_force_share:g}: the first trial's budget, "
                       f"{budget:.3g} N, is too small: its force ramp must end above the approach's contact "
                       f"threshold ({contact:.3g} N, {CONTACT_SIGMAS:g}x the load cell's noise) and below the "
                       f"budget by the loop's overshoot and {PEAK_SIGMAS:g}x the noise")
    cap = FIRST_SPEED_SHARE * lim.max_speed_mm_s
    approach = min(APPROACH_SPEED_SHARE * lim.max_speed_mm_s, cap)
    rate = setpoint / FIRST_RAMP_S
    text = ("name: first look\ndescription: >-\n  the campaign's first look at the specimen: the surface found "
            "by force, a force-controlled ramp to a budget, a hold, back to the start\nsteps:\n"
            f"  - approach:   {{speed_mm_s: {_g(approach)}, contact_N: {_g(contact)}, max_mm: {_g(half)}}}\n"
            f"  - ramp_force: {{to_N: {_g(setpoint)}, rate_N_s: {_g(rate)}, max_mm: {_g(half)}}}\n"
            f"  - hold:       {{duration_s: {_g(FIRST_HOLD_S)}}}\n"
            f"  - return:     {{speed_mm_s: {_g(cap)}}}\n"
            f"limits: {{max_force_N: {_g(budget)}, max_speed_mm_s: {_g(cap)}, "
            f"travel_mm: [{_g(lim.travel_mm[0])}, {_g(_far_mm(req) + TRAVEL_GUARD_MM)}]}}\n")
    size = (f"force budget {budget:.3g} N ({req.first_force_share:g} of the {lim.max_force_N:g} N limit, the "
            f"trial's own limit): the surface found at {contact:.3g} N ({CONTACT_SIGMAS:g}x the noise) within "
            f"{half:g} mm, a force ramp to {setpoint:.3g} N at most {half:g} mm past it and {cap:g} mm/s: "
            f"at most {start + 2 * half:g} mm, {lim.travel_mm[1] - start - 2 * half:g} mm short of the end of "
            f"travel (its own travel to {_far_mm(req) + TRAVEL_GUARD_MM:g} mm)")
    figures = {"force_budget_N": budget, "first_force_share": req.first_force_share, "setpoint_N": setpoint,
               "contact_N": contact, "approach_max_mm": half, "force_max_mm": half, "speed_limit_mm_s": cap,
               "deepest_mm": start + 2 * half, "travel_end_mm": lim.travel_mm[1],
               "travel_margin_mm": req.travel_margin_mm, "travel_window_mm": [lim.travel_mm[0],
                                                                              _far_mm(req) + TRAVEL_GUARD_MM]}
    return Sized(text, "exploratory: the first look, by force within a budget", size, figures)


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
    """Run a campaign: a first trial, then fit, diagnose and design the next trial until the model holds,
    nothing better can be learnt, the budget is spent or it is stopped."""
    check_request(req)
    if req.first or req.first_text:
        text = req.first_text or Path(req.first).read_text()
        first = Sized(text, f"given ({req.first or 'with the request'})", "as given")
    else:
        first = first_look(req)  # refused here, before the journal
    camp = Campaign(req.specimen)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    camp.journal = req.out_dir / f"characterize-{req.specimen}-{stamp}.jsonl"
    journal = Journal(camp.journal, req.on_event)
    journal.write("start", journal=str(camp.journal), specimen=req.specimen, model=req.model,
                  indenter=req.indenter, target_rse=req.target_rse, max_trials=req.max_trials,
                  budget_min=req.budget_min, first_force_share=req.first_force_share,
                  force_margin_share=req.force_margin_share, travel_margin_mm=req.travel_margin_mm,
                  limits=vars(req.config.limits))
    try:
        _run(req, camp, journal, first)
    finally:
        journal.write("end", status=camp.status, reason=camp.reason, summary=camp.summary())
        journal.close()
    return camp


def _run(req: Request, camp: Campaign, journal: Journal, nxt: Sized) -> None:
    logs: list[str] = []
    model_name, extra = req.model, []
    last: FitResult | None = None
    budget_s = 60.0 * req.budget_min
    while True:
        text, why = nxt.text, nxt.why
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
        turn = Turn(proto.name, why, nxt.size)
        camp.turns.append(turn)
        journal.write("trial", n=len(camp.turns), protocol=proto.name, why=why, size=nxt.size,
                      sizing=nxt.figures, yaml=text, duration_s=duration)
        req.say(f"trial {len(camp.turns)}: {proto.name} ({duration:.0f} s): {why}")
        req.say(f"  size: {nxt.size}")
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
        if len(camp.turns) == 1:
            camp.approach = next((st for st in proto.steps if isinstance(st, Approach)), None)
            camp.by_force = any(isinstance(st, FORCE_STEPS) for st in proto.steps)
        record, start_mm, surface_mm = _read_from_start(result.log_path, camp.start_mm)
        camp.start_mm = start_mm if camp.start_mm is None else camp.start_mm
        camp.records.append(record)
        if camp.approach is not None:
            camp.surfaces_mm.append(surface_mm)
        last, ex, extra = _fit_all(req, logs, camp.records, model_name, extra, last, turn, journal)
        camp.final = last
        req.say(f"  {turn.model}: RMSE {turn.rmse_over_noise:.2f}x the noise, "
                f"{'adequate' if turn.adequate else 'NOT adequate'}; largest relative error "
                f"{100 * turn.max_rse:.1f} % ({turn.worst})")
        nxt = _decide(req, last, ex, turn, journal, camp)
        if nxt is None:
            break


def _read_from_start(log_path: Path, start_mm: float | None) -> tuple[Record, float, float]:
    """The trial's log as the analysis reads it, its positions measured from `start_mm` (slider
    coordinates; None: from where this trial started), and where the trial started and where its
    approach found the surface, mm from `start_mm` (the start, without an approach).

    Every trial of a campaign is fitted from one zero, the first trial's start, not from the
    surface its own approach found: the threshold fires where the tissue's toe first carries a
    few times the noise (4.1-4.8 mm into the default tissue, 17-19 mm into one ten times softer),
    a little further or nearer each time, and one contact offset cannot follow a zero that moves
    from trial to trial (read from the surface, a first look on the softer tissue left the fit at
    1.09x the noise, its contact offset at the bound of its range). Read from the start, a fit
    places the tissue's start itself (`contact_offset`) when it is not where the slider started."""
    from rig.recording.logs import read_log

    log = read_log(log_path)
    rec = read_record(log_path)
    frames = log.frames.frames
    start = frames.start_mm if start_mm is None else start_mm
    kinds = np.asarray(log.step_kind)
    keep = ~np.isin(kinds, ["tare", "fault", "done"])  # the samples rig.records keeps of a log
    slider_mm = log.position_mm(Frame.SLIDER)[keep]
    if len(slider_mm) != rec.n:
        raise RigError(f"{log_path}: {rec.n} samples read for the analysis, {len(slider_mm)} positions")
    from_start = replace(rec, position_m=(slider_mm - start) / 1000.0,
                         notes=[*rec.notes, f"positions from the campaign's start, slider {start:g} mm"])
    return from_start, frames.start_mm, frames.zero_mm(Frame.SURFACE) - start


def _one_trial(req: Request, proto, n: int):
    config = req.config
    if req.seed_per_trial and config.slider.backend == "sim":
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


def _fit_all(req: Request, logs: list[str], records: list[Record], model_name: str, extra: list[str],
             last: FitResult | None, turn: Turn, journal: Journal) -> tuple[FitResult, Explanation, list[str]]:
    # every sample in force form (the force predicted from the measured motion), as for a trial in
    # position control: the first trial's force-controlled ramp is a ramp whose pace the specimen
    # set. In creep form (the indentation predicted from the force) its fit on a specimen ten
    # times softer than the default, whose ramp reached its max_mm, missed by 5.2x the noise.
    inp = load_inputs(logs, [], [], ReadOptions(), indenter=req.indenter, form="force", records=records)
    model = build_model(model_name, extra, inp.registry)
    base = fit(model, inp.trials, initial=last.values if last is not None else None)
    steps = auto(base, inp.registry)
    final = steps[-1]["fit"]
    for s in steps[1:]:
        journal.write("model", added=s["added"], removed=s["removed"], delta_bic=s["delta_bic"], why=s["why"])
    ex = steps[-1].get("explanation") or explain(final, inp.registry)  # the search's last, when it ended there
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


def _room(req: Request, camp: Campaign, f: FitResult) -> tuple[Room, dict]:
    """Where the next designed trial may go, and the figures that say why. After a first trial that
    found the surface by force, a designed trial finds it the same way (its depths are from
    there; the fit's from the first trial's start, where the surfaces found are measured from),
    searching SURFACE_SLACK_MM or SURFACE_SLACK_SHARE past the deepest surface
    found so far; the check before it runs counts its depths from the far end of that search,
    so the deepest it may be planned to go from the surface is what is left of the travel (its end
    less `travel_margin_mm`) past that. Its predicted peak force is at most `force_margin_share`
    of the force limit and GROWTH times the largest force measured so far. It goes back to the
    start position."""
    cfg = req.config
    start = camp.start_mm if camp.start_mm is not None else _start_mm(cfg)
    far = _far_mm(req)
    fastest = cfg.limits.max_speed_mm_s / 1000.0
    pace = back = None
    if camp.by_force:
        # the first trial's pace was what its force loop needed on this specimen (stopping and
        # starting, slower on stiffer ones): the designs are built around 15 % of the speed limit
        # and return at half of it, as after the position ramp that was the first trial before,
        # and the predicted force keeps the stiff specimens' trials slow
        pace, back = PACE_SHARE * fastest, 0.5 * fastest
    try:
        home_m_s = min(back or shape_of(f.trials).return_m_s, fastest)
    except RigError:
        home_m_s = 0.5 * fastest
    measured = max(float(np.max(t.force_N)) for t in f.trials)
    grow = GROWTH * measured
    window = (cfg.limits.travel_mm[0], far + TRAVEL_GUARD_MM)
    figures = {"start_mm": start, "travel_end_mm": cfg.limits.travel_mm[1],
               "travel_margin_mm": req.travel_margin_mm, "force_margin_share": req.force_margin_share,
               "force_limit_N": cfg.limits.max_force_N, "largest_force_measured_N": measured,
               "growth": GROWTH}
    if pace is not None:
        figures["pace_mm_s"] = 1000.0 * pace
    a = camp.approach
    if a is None or not camp.surfaces_mm:
        depth = far - start
        figures.update(zero="the start position", depth_room_mm=depth)
        return Room(depth / 1000.0, req.force_margin_share, pace_m_s=pace, return_m_s=back,
                    max_peak_N=grow, travel_mm=window), figures
    deepest = max(camp.surfaces_mm)
    search = round(deepest + max(SURFACE_SLACK_MM, SURFACE_SLACK_SHARE * deepest), 1)
    depth = far - start - search
    figures.update(zero="the surface the approach finds", surfaces_found_mm=list(camp.surfaces_mm),
                   approach_max_mm=search, depth_room_mm=depth)
    approach = ApproachFirst(a.speed_mm_s / 1000.0, a.contact_N, search / 1000.0)
    surface = float(np.mean(camp.surfaces_mm))
    return Room(max(depth, 0.0) / 1000.0, req.force_margin_share, approach, surface / 1000.0, home_m_s,
                pace, back, grow, window), figures


def _sized(req: Request, c: Candidate, peak_N: float, room: Room, figures: dict) -> tuple[float, str, dict]:
    """A designed trial's own force limit, and why its size is what it is (words, figures)."""
    cfg = req.config
    limit = trial_limit_N(peak_N, cfg.limits.max_force_N)
    deepest = 1000.0 * max((p["to"] for k, p in c.steps if k == "ramp"), default=0.0)
    search = 1000.0 * room.approach.max_m if room.approach is not None else 0.0
    # the deepest the check before the trial allows for: the surface at the far end of its search
    lowest = figures.get("start_mm", _start_mm(cfg)) + search + deepest
    found = figures.get("surfaces_found_mm") or [0.0]
    seen = f"{found[0]:.1f}" if len(found) == 1 else f"{min(found):.1f}-{max(found):.1f}"
    where = (f"{deepest:.1f} mm past the surface, which its approach seeks within {search:g} mm of the start "
             f"(found at {seen} mm so far)" if room.approach is not None
             else f"to {deepest:.1f} mm from the start position")
    measured = figures.get("largest_force_measured_N")
    grown = f" and {GROWTH:g}x the {measured:.3g} N measured so far" if measured is not None else ""
    size = (f"{where}: at most {lowest:.1f} mm, {cfg.limits.travel_mm[1] - lowest:.1f} mm short of the end of "
            f"travel ({req.travel_margin_mm:g} mm kept); predicted peak {peak_N:.3g} N (at most "
            f"{req.force_margin_share:g} of the {cfg.limits.max_force_N:g} N limit{grown}); its own force "
            f"limit {limit:g} N" + (f", its travel to {room.travel_mm[1]:g} mm" if room.travel_mm else ""))
    return limit, size, {**figures, "deepest_from_zero_mm": deepest, "deepest_mm": lowest,
                         "predicted_peak_N": peak_N, "trial_force_limit_N": limit,
                         "travel_window_mm": list(room.travel_mm) if room.travel_mm else None}


def _decide(req: Request, f: FitResult, ex: Explanation, turn: Turn, journal: Journal,
            camp: Campaign) -> Sized | None:
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
    room, figures = _room(req, camp, f)
    if room.depth_m < MIN_DEPTH_MM / 1000.0:
        why = (f"{figures['depth_room_mm']:.1f} mm of travel left past the surface (the approach searching "
               f"{figures.get('approach_max_mm', 0.0):g} mm from the start at {figures['start_mm']:g} mm, the "
               f"travel ending at {figures['travel_end_mm']:g} mm less the {req.travel_margin_mm:g} mm "
               "margin): no room for a designed trial")
        journal.write("decision", kind="nothing better", why=why, sizing=figures)
        camp.status, camp.reason = "nothing better", why
        return None
    if ex.lookalikes:
        pair = ex.lookalikes[0]["effects"]
        try:
            d = design(ex, req.config, max_duration_s=left, room=room)
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
            return _inform_or_stop(req, f, turn, journal, camp, room, figures)
        journal.write("decision", kind="separate", effects=pair, protocol=d.best.name,
                      considered=[{"protocol": c.name, "separation_N": c.separation_N} for c in d.ranked[:12]],
                      refused=d.refused, why=d.best.why)
        miss = (d.best.separation_N or 0) / d.noise_N
        _, size, sizing = _sized(req, d.best, d.best.peak_N, room, figures)  # design_yaml sets the same limit
        return Sized(d.yaml, f"separate {pair[0]} from {pair[1]}: {d.best.name} (the wrong model would still "
                             f"miss it by {miss:.1f}x the noise)", size, sizing)
    return _inform_or_stop(req, f, turn, journal, camp, room, figures)


def _inform_or_stop(req: Request, f: FitResult, turn: Turn, journal: Journal,
                    camp: Campaign, room: Room | None = None, figures: dict | None = None) -> Sized | None:
    if turn.max_rse <= req.target_rse:
        journal.write("decision", kind="done", worst=turn.worst, max_rse=turn.max_rse,
                      why=f"adequate; every parameter within {100 * req.target_rse:g} %")
        camp.status = "done"
        camp.reason = (f"the model is adequate and every parameter is determined to {100 * req.target_rse:g} % "
                       f"(largest: {turn.worst}, {100 * turn.max_rse:.2f} %)")
        return None
    left = _time_left(req, camp)
    if room is None:
        room, figures = _room(req, camp, f)
    share_s = left / max(req.max_trials - len(camp.turns), 1)
    best, over_budget = _most_informative(req, f, journal, left, share_s, room)
    if best is None and over_budget:
        camp.status = "budget"
        camp.reason = (f"no candidate protocol fits in the {max(left, 0.0):.0f} s of specimen time the "
                       f"{req.budget_min:g} min budget leaves")
        return None
    if best is None:
        camp.status = "nothing better"
        camp.reason = (f"no protocol within the limits and the budget left brings {turn.worst} "
                       f"({100 * turn.max_rse:.1f} %) below {100 * INFORMATION_GAIN:g} % of its error")
        return None
    c, after, so_far = best
    also = (f" ({100 * so_far:.1f} % if its samples are worth what the earlier trials' were)"
            if math.isfinite(so_far) else "")
    limit, size, sizing = _sized(req, c, c.peak_N, room, figures or {})
    text = protocol_text(c, f"inform {turn.worst}: {c.name}", limit,
                         [f"Chosen by rig characterize to narrow {turn.worst}: expected largest relative "
                          f"error {100 * turn.max_rse:.2f} % -> {100 * after:.2f} %{also}.",
                          f"Size: {size}."], room.travel_mm)
    return Sized(text, f"the largest relative error ({turn.worst}, {100 * turn.max_rse:.1f} %) is expected to "
                       f"fall to {100 * after:.1f} % with {c.name}{also}", size, sizing)


def _most_informative(req: Request, f: FitResult, journal: Journal, max_duration_s: float = math.inf,
                      share_s: float = math.inf, room: Room | None = None
                      ) -> tuple[tuple[Candidate, float, float] | None, bool]:
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
    Candidates go only where `room` lets them (default: `rig analyze --design`'s); the one chosen
    carries its predicted peak force (`Candidate.peak_N`).
    Returns (candidate, forecast, calibrated forecast) or None, and whether every candidate was
    refused for taking longer than `max_duration_s`."""
    if f.covariance is None:
        return None, False
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
        return None, False
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
    cands = rig_candidates(shape_of(f.trials), req.config, room)
    if math.isfinite(share_s):
        fill = min(share_s, max_duration_s)
        # never slower than a quarter of the first trial's speed: each trial could otherwise go a
        # quarter slower than the slowest before it, and on a 30 min budget the ramps fell to
        # 0.12 mm/s, six-minute trials whose fits took four minutes each
        floor = SLOWEST * (room.pace_m_s if room is not None and room.pace_m_s else _first_speed(f.trials))
        cands += [s for s in (slowed(c, fill, req.config, floor) for c in cands) if s is not None]
    scored, refused = [], []
    over_time = 0
    for c in cands:
        m = c.trial.motion
        pred = f.model.predict(f.values, m)
        c.peak_N = float(np.max(pred))
        duration = float(m.t_s[-1])
        over_time += duration > max_duration_s
        why = (f"{c.name}: {duration:.0f} s, over the {max_duration_s:.0f} s the budget leaves"
               if duration > max_duration_s else inadmissible(c, c.peak_N, req.config, room))
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
        return None, bool(cands) and over_time == len(cands)
    rse, so_far, c = scored[0]
    return (c, rse, so_far), False


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
    """The campaign in words: its status, each trial with its model's verdict, and the final model."""
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


def campaign_figure(camp: Campaign):
    """The error falling trial by trial: RMSE over the noise and the largest relative error (a
    matplotlib Figure). The error's axis starts at 0 with no offset, so 1.0004 -> 0.9999 reads as
    the flat line it is."""
    from rig.views.plots import figure

    done = [t for t in camp.turns if t.model]
    fig = figure(figsize=(9, 3.4))
    a, b = fig.subplots(1, 2)
    n = range(1, len(done) + 1)
    ratio = [t.rmse_over_noise for t in done]
    a.plot(n, ratio, "o-")
    a.axhline(1.0, color="0.6", lw=0.8)
    a.set(xlabel="trial", ylabel="RMSE / noise", title="model error")
    a.ticklabel_format(axis="y", style="plain", useOffset=False)
    a.set_ylim(0.0, max([1.5, *(1.15 * r for r in ratio if math.isfinite(r))]))
    b.semilogy(n, [100 * t.max_rse for t in done], "o-")
    b.set(xlabel="trial", ylabel="largest relative error (%)", title="parameters")
    for ax in (a, b):
        ax.set_xticks(list(n))
    fig.suptitle(f"{camp.specimen}: {camp.status}")
    return fig


def plot_campaign(camp: Campaign, path: Path) -> Path:
    """campaign_figure, written to `path`."""
    campaign_figure(camp).savefig(path, dpi=110)
    return path
