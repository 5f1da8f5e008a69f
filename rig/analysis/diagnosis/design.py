"""Settle a tie: the protocol that would tell two look-alike effects apart.

When `--explain` finds two effects that explain the trials equally well, each stands for a
fitted model (the base with one effect, or with the other; or the base whose own term takes
the other's shape). The protocol that separates them is one on which those models disagree
by more than the noise. Candidates vary what the trials given did not: the speed, the
depth, the hold, a staircase, load-unload cycles, an oscillation at depth (ramps back and
forth: the rig's protocols have no sine, a triangle wave gives the same excitation order),
a rest out of contact before and after. Each is predicted by both fitted models; the
leaders are then checked the hard way: the wrong model is refitted to the trials given plus
the candidate as the other model predicts it, and what it still misses on the candidate is
the separation that decides (a model that reshapes to absorb the difference does not
separate anything, however far apart the two predictions were).

Every candidate is a protocol in the rig's own format, checked against the rig's limits as
`rig run` checks it, and kept only if both models predict a peak force within the force
limit with a margin. Depths are measured from the zero the analysis took as contact. A
campaign (`rig characterize`) narrows where a candidate may go (`Room`): a margin from the end
of the travel and from the force limit, and an approach that finds the surface first, as its
first trial's did, with the return to the start position after.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rig.analysis.diagnosis.explain import Explanation
from rig.analysis.fitting.fit import FitResult, fit
from rig.analysis.trials.data import PHASES, TrialData, decimate
from rig.errors import LimitError, RigError
from rig.models.core import Model, Motion
from rig.specs.config import RigConfig
from rig.specs.motion import sample_move
from rig.specs.protocol import check_limits, parse_protocol, plan

FORCE_SHARE = 0.8  # a candidate's predicted peak force at most this share of the force limit
TRAVEL_SHARE = 0.95  # `rig analyze --design`: a candidate no deeper than this share of the travel left
MAX_DURATION = 2.0  # a candidate may take at most this many times the longest trial given
CHECKED = 12  # leaders by predicted difference that are refitted the hard way
SCREEN_SAMPLES = 1500  # per trial, for the refits (the effects live on time scales of many samples)
REFIT_NFEV = 40
NOTHING_TO_SETTLE = "nothing to settle: the diagnosis has no look-alikes (no protocol written)"
# A candidate settles the tie when the wrong model, refitted to it, still misses it by the noise or
# more: below that, the two models describe the new trial alike too.
SETTLES = 1.0
# The candidates that carry out what the verdict proposes for a pair (`explain.SEPARATE_BY`), by
# the start of their names: what `--design` says of the verdict's own proposal.
PROPOSED = {
    frozenset({"compliance", "poly_elastic"}): ("ramp to ", "staircase", "slow to ", "oscillation"),
    frozenset({"compliance", "relaxation2"}): ("staircase",),
    frozenset({"delay", "viscous"}): ("ramp at ",),
    frozenset({"delay", "friction"}): ("ramp at ",),
    frozenset({"drift", "relaxation2"}): ("long hold", "rest before and after"),
    frozenset({"offset", "drift"}): ("rest before and after",),
    frozenset({"fractional_relaxation", "relaxation2"}): ("long hold",),
    frozenset({"speed_relaxation", "relaxation2"}): ("ramp at ",),
}


@dataclass(frozen=True)
class Shape:
    """What the trials given did: their deepest point, ramp speed, hold, return speed (SI)."""

    depth_m: float
    speed_m_s: float
    hold_s: float
    return_m_s: float
    duration_s: float


@dataclass
class Candidate:
    """A protocol tried for telling two look-alike effects apart: its steps, the trial simulated from it,
    each fitted model's prediction on it, how far apart they are (RMS and at the peak), and how far the
    wrong one stays after both are refitted with it."""

    name: str
    why: str
    steps: list[tuple[str, dict]]
    trial: TrialData | None = None
    predictions: tuple[np.ndarray, np.ndarray] | None = None
    difference_N: float = 0.0  # RMS difference of the two models' predictions
    peak_N: float = 0.0
    separation_N: float | None = None  # what the wrong model still misses after the joint refit
    wrong: str = ""  # which alternative missed (the one refitted to the other's prediction)


@dataclass
class Design:
    """The protocol chosen to tell two effects apart: the two fitted alternatives, the noise the difference
    is judged against, the best candidate, every candidate that passed the rig's limits (best first) and
    those refused with why, and the protocol as YAML."""

    effects: tuple[str, str]
    alternatives: tuple[FitResult, FitResult]
    noise_N: float
    best: Candidate
    ranked: list[Candidate]  # every candidate that passed the rig's checks, best first
    refused: list[str] = field(default_factory=list)  # candidates beyond the rig's limits, and why
    yaml: str = ""
    duration_s: float = 0.0
    proposed: str = ""  # what the verdict proposed to separate the pair (`explain.SEPARATE_BY`)

    @property
    def settles(self) -> bool:
        """Whether the best candidate tells the two apart: the wrong model, refitted with it,
        still misses it by at least the noise (`SETTLES`)."""
        return (self.best.separation_N or 0.0) >= SETTLES * self.noise_N

    def warning(self) -> str:
        """What the user must know when no candidate settles the tie ("" when one does)."""
        if self.settles:
            return ""
        b = self.best
        x, y = self.effects
        return (f"no candidate settles the tie: on the best, '{b.name}', {b.wrong} refitted still misses by "
                f"only {b.separation_N / self.noise_N:.2g}x the noise (at least {SETTLES:g}x tells them "
                f"apart), so running it will not tell {x} from {y}: the two models predict every candidate "
                f"trial within the rig's limits and {MAX_DURATION:g}x the trials' duration alike")

    def proposal(self) -> str:
        """How the verdict's own proposal fared among the candidates ("" when it is the best or
        has no candidate here)."""
        starts = PROPOSED.get(frozenset(self.effects), ())
        if not self.proposed or not starts:
            return ""
        ran = [c for c in self.ranked if c.name.startswith(starts) and c.separation_N is not None]
        if self.best in ran:
            return ""
        said = f"the verdict's proposal, {self.proposed.split(' (')[0]},"
        if ran:
            c = ran[0]
            return (f"{said} is '{c.name}' here: refitted with it, {c.wrong} misses by "
                    f"{c.separation_N:.3g} N RMS ({c.separation_N / self.noise_N:.2g}x the noise), less "
                    f"than on '{self.best.name}'")
        why = next((r for r in self.refused if r.startswith(starts)), "")
        return f"{said} is not among the candidates run" + (f" ({why})" if why else "")

    def as_dict(self) -> dict:
        b = self.best
        return {"effects": list(self.effects), "protocol": b.name, "why": b.why,
                "settles": self.settles, "warning": self.warning(), "proposal": self.proposal(),
                "difference_N": b.difference_N, "difference_over_noise": b.difference_N / self.noise_N,
                "separation_N": b.separation_N,
                "separation_over_noise": (b.separation_N or 0.0) / self.noise_N, "wrong_model": b.wrong,
                "predicted_peak_N": b.peak_N, "noise_N": self.noise_N, "duration_s": self.duration_s,
                "candidates": [{"protocol": c.name, "difference_N": c.difference_N,
                                "separation_N": c.separation_N} for c in self.ranked],
                "refused": self.refused}


@dataclass(frozen=True)
class ApproachFirst:
    """An `approach` step at the start of a designed trial (SI, force in N)."""

    speed_m_s: float
    contact_N: float
    max_m: float


@dataclass(frozen=True)
class Room:
    """Where a designed trial may go (SI). `depth_m`: the deepest point below the trial's zero;
    `force_share`: the predicted peak force at most this share of the force limit. With
    `approach` every candidate starts by finding the surface as the trials it is designed from
    did, and its depths are from there; the trials were fitted from their start position, and
    found the surface `surface_m` past it, so a candidate's motion is predicted from the start:
    the approach to `surface_m`, the steps from there, and the return to the start position at
    `home_m_s` (a probe left at the surface would start the next trial's approach in contact).
    `pace_m_s` and `return_m_s`, when given, are the ramp and return speeds the candidates are
    built around instead of the trials' own (a force-controlled ramp's pace is the specimen's)."""

    depth_m: float
    force_share: float = FORCE_SHARE
    approach: ApproachFirst | None = None
    surface_m: float = 0.0
    home_m_s: float = 0.0
    pace_m_s: float | None = None
    return_m_s: float | None = None
    max_peak_N: float | None = None  # the predicted peak force also at most this (a campaign's growth)
    # the trial's own travel window, slider mm (a protocol's limits.travel_mm): checked before it
    # runs from wherever the slider is, and on every tick
    travel_mm: tuple[float, float] | None = None


# ------------------------------------------------------------------ the alternatives

def alternatives(ex: Explanation, pair: list[str]) -> tuple[FitResult, FitResult]:
    """The fitted model each effect of a look-alike pair stands for."""
    out = []
    for name in pair:
        if ex.base.model.has(name):
            out.append(ex.base)  # the base's own term takes the other's shape
            continue
        sug = next((s for s in ex.ranked if s.effect == name), None)
        if sug is None:
            raise RigError(f"look-alike {name} has no fit to design from")
        out.append(sug.fit)
    return out[0], out[1]


def _nested(a: Model, b: Model) -> bool:
    return set(b.effect_names) <= set(a.effect_names)


# ------------------------------------------------------------------ what the trials did

def shape_of(trials: list[TrialData]) -> Shape:
    """Depth, loading speeds, hold and return times of the trials given: the designed protocol stays within
    what was already run on this specimen."""
    depth = max(float(np.max(t.motion.x_m)) for t in trials)
    speeds, holds, returns = [], [], []
    for t in trials:
        v = t.motion.v_m_s
        ramp, ret = t.phase == "ramp", t.phase == "return"
        if np.any(ramp):
            speeds.append(float(np.median(np.abs(v[ramp]))))
        if np.any(ret):
            returns.append(float(np.median(np.abs(v[ret]))))
        hold = np.isin(t.phase, ["hold_early", "hold_late"])
        holds.append(float(np.sum(hold)) * t.motion.dt_s)
    if not speeds:
        raise RigError("no ramp in the trials: nothing to design a protocol from")
    speed = max(speeds)
    return Shape(depth, speed, max(holds), max(returns) if returns else 2.0 * speed,
                 max(float(t.motion.t_s[-1] - t.motion.t_s[0]) for t in trials))


def candidate_steps(s: Shape, max_speed_m_s: float, max_depth_m: float) -> list[Candidate]:
    """Protocols that vary what the trials given did not (depths, speeds in m, m/s), none deeper
    than `max_depth_m` (trials given deeper than that are taken as reaching it)."""
    D, V, R = min(s.depth_m, max_depth_m), s.speed_m_s, min(s.return_m_s, max_speed_m_s)
    H = s.hold_s if s.hold_s > 0 else D / V  # without a hold, one as long as the ramp
    deep = min(1.5 * D, max_depth_m)
    out: list[Candidate] = []

    def add(name: str, why: str, *steps: tuple[str, dict], rest: float = 0.0) -> None:
        after = [("hold", {"s": rest})] if rest else []
        out.append(Candidate(name, why, [*steps, ("return", {"to": 0.0, "speed": R}), *after]))

    def ramp(to: float, v: float) -> tuple[str, dict]:
        return ("ramp", {"to": to, "speed": min(v, max_speed_m_s)})

    def hold(t: float) -> tuple[str, dict]:
        return ("hold", {"s": t})

    for f in (0.25, 0.5, 2.0, 4.0):
        if V * f <= max_speed_m_s:
            add(f"ramp at {_mm(V * f)} mm/s", "another speed: damping scales with the speed, elasticity "
                "with the depth", ramp(D, V * f), hold(H))
    for d in (D / 2, 2 * D / 3, deep):
        add(f"ramp to {_mm(d)} mm", "another depth", ramp(d, V), hold(H))
        add(f"ramp to {_mm(d)} mm at {_mm(min(2 * V, max_speed_m_s))} mm/s", "another depth and speed",
            ramp(d, 2 * V), hold(H))
    add("long hold", "a hold three times as long", ramp(D, V), hold(3 * H))
    add("rest before and after", "the force out of contact before the ramp and after the return (a sensor's "
        "drift or offset shows there)", hold(H), ramp(D, V), hold(H), rest=H)
    add("staircase", "a hold at a second depth", ramp(D / 2, V), hold(H / 2), ramp(D, V), hold(H / 2))
    add(f"staircase to {_mm(deep)} mm at two speeds", "holds at two depths, reached at two speeds",
        ramp(D / 2, V / 2), hold(H / 2), ramp(deep, 2 * V), hold(H / 2))
    add("load-unload cycles", "load, unload to a third of the depth and load again, then a hold half as "
        "long at depth", ramp(D, V), ramp(D / 3, V), ramp(D, V), hold(H / 2))
    for amp, f in ((0.1, 2.0), (0.2, 1.0)):
        mid = D * (1 - amp)
        wiggle = [ramp(mid - amp * D if i % 2 == 0 else mid + amp * D, f * V) for i in range(6)]
        add(f"oscillation +/-{_mm(amp * D)} mm at {_mm(min(f * V, max_speed_m_s))} mm/s",
            "a triangle wave at depth (excitation order 2, like a sine)",
            ramp(mid, V), *wiggle, ramp(mid, f * V), hold(H / 2))
    wiggle = [ramp(deep - 0.2 * D if i % 2 == 0 else deep, 2 * V) for i in range(4)]
    add(f"slow to {_mm(D / 2)} mm, fast to {_mm(deep)} mm, oscillation",
        "two speeds, two depths and a triangle wave in one trial",
        ramp(D / 2, V / 2), hold(H / 3), ramp(deep, 2 * V), *wiggle, hold(H / 3))
    return out


def _num(v: float) -> str:
    """Three significant digits, never in exponent form (YAML would read 1e-05 as text)."""
    return np.format_float_positional(float(f"{v:.3g}"), trim="-")


def _mm(x_m: float) -> str:
    return _num(x_m * 1000)


def protocol_text(c: Candidate, name: str, limits_N: float | None, comment: list[str],
                  travel_mm: tuple[float, float] | None = None) -> str:
    """The candidate as a protocol file, with its own force limit and travel window when given."""
    lines = [f"# {line}" for line in comment]
    lines += [f"name: {json.dumps(name)}", f"description: >-\n  {c.why}", "steps:"]
    for kind, p in c.steps:
        if kind == "ramp":
            lines.append(f"  - ramp:   {{to_mm: {_mm(p['to'])}, speed_mm_s: {_mm(p['speed'])}}}")
        elif kind == "hold":
            lines.append(f"  - hold:   {{duration_s: {_num(p['s'])}}}")
        elif kind == "approach":
            lines.append(f"  - approach: {{speed_mm_s: {_mm(p['speed'])}, contact_N: {_num(p['contact_N'])}, "
                         f"max_mm: {_mm(p['max'])}}}")
        elif kind == "home":  # to the start position
            lines.append(f"  - return: {{speed_mm_s: {_mm(p['speed'])}}}")
        else:
            lines.append(f"  - return: {{to_mm: {_mm(p['to'])}, speed_mm_s: {_mm(p['speed'])}}}")
    limits = [f"max_force_N: {_num(limits_N)}"] if limits_N is not None else []
    if travel_mm is not None:
        limits.append(f"travel_mm: [{_num(travel_mm[0])}, {_num(travel_mm[1])}]")
    if limits:
        lines.append(f"limits: {{{', '.join(limits)}}}")
    return "\n".join(lines) + "\n"


def _trial(c: Candidate, config: RigConfig) -> TrialData:
    """The candidate's commanded motion at the loop rate, as the models see a trial: from its
    zero, or, for one that finds the surface first, from the start position, the surface where
    the trials given found it (`Room`)."""
    rate, accel = config.loop.rate_Hz, config.slider.accel_mm_s2
    surface = 1000.0 * c.steps[0][1]["from"] if c.steps and c.steps[0][0] == "approach" else 0.0
    pos, segs, kinds = 0.0, [np.zeros(round(config.loop.tare_s * rate) + 1)], ["rest"]
    for kind, p in c.steps:
        if kind == "hold":
            segs.append(np.full(max(round(p["s"] * rate), 1), pos))
        else:
            target = surface if kind == "approach" else 0.0 if kind == "home" else surface + p["to"] * 1000
            segs.append(sample_move(pos, target, p["speed"] * 1000, accel, rate))
            if kind != "approach":
                kind = "ramp" if target > pos else "return"
            pos = target
        kinds.append(kind)
    x_m = np.concatenate(segs) / 1000.0
    step = np.concatenate([np.full(len(s), k, dtype=object) for s, k in zip(segs, kinds, strict=True)])
    dt = 1.0 / rate
    t = np.arange(len(x_m)) * dt
    phase = np.full(len(t), "", dtype=object)
    phase[step == "ramp"] = "ramp"
    phase[step == "return"] = "return"
    hold = step == "hold"
    if np.any(hold):  # the first sixth of each hold is its early part, as for a recorded trial
        idx = np.flatnonzero(hold)
        for seg in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
            early = t[seg] - t[seg[0]] < (t[seg[-1]] - t[seg[0]]) / 6.0
            phase[seg[early]] = PHASES[1]
            phase[seg[~early]] = PHASES[2]
    m = Motion(t, x_m, np.gradient(x_m, dt), dt)
    return TrialData(f"design: {c.name}", m, np.zeros(len(t)), phase, None, "design")


# ------------------------------------------------------------------ the design

def default_room(config: RigConfig) -> Room:
    """`rig analyze --design`'s: TRAVEL_SHARE of the travel left from the slider's start, no
    approach (depths from the zero the trials given were analysed from)."""
    start = config.sim.slider.start_mm if config.slider.backend == "sim" else 0.0
    return Room(TRAVEL_SHARE * (config.limits.travel_mm[1] - start) / 1000.0)


def rig_candidates(shape: Shape, config: RigConfig, room: Room | None = None) -> list[Candidate]:
    """`candidate_steps` within this rig's speed and travel (from the slider's start) and within
    `room` (default: `default_room`), each with its commanded motion (`Candidate.trial`)."""
    room = room or default_room(config)
    # depths from the surface the approach finds: the trials' own were from their start
    depth_m = max(shape.depth_m - room.surface_m, 0.0) if room.approach is not None else shape.depth_m
    shape = replace(shape, depth_m=depth_m, speed_m_s=room.pace_m_s or shape.speed_m_s,
                    return_m_s=room.return_m_s or shape.return_m_s)
    out = candidate_steps(shape, config.limits.max_speed_mm_s / 1000.0, room.depth_m)
    if room.approach is not None:
        a = room.approach
        first = ("approach", {"speed": a.speed_m_s, "contact_N": a.contact_N, "max": a.max_m,
                              "from": room.surface_m})
        home = ("home", {"speed": room.home_m_s})
        for c in out:
            c.steps = [first, *c.steps, home]
    for c in out:
        c.trial = _trial(c, config)
    return out


SLOWEST = 0.25  # a slowed candidate's ramps at no less than this share of their speed


def slowed(c: Candidate, seconds: float, config: RigConfig, slowest_m_s: float = 0.0) -> Candidate | None:
    """`c` with its ramps slowed by one factor so that the whole takes about `seconds` (its holds
    and return as they were), or None when it already takes that long or cannot be slowed. The
    same path with more samples along it, each nearer the tissue's slow response: on a
    campaign's simulated specimen with a frame spring, the paper's quadratic term came out at
    44 % relative error after a 0.45 mm/s ramp where the same ramp at 0.75 mm/s left 62 % (one
    seed; 67 against 117 % on another). Never slower than SLOWEST of the speeds designed, nor
    than `slowest_m_s`: a longer trial always promises more, and a budget is not there to be
    spent on one ramp."""
    trial = c.trial if c.trial is not None else _trial(c, config)
    took = float(trial.motion.t_s[-1])
    ramping = float(np.sum(trial.phase == "ramp")) * trial.motion.dt_s  # the time going deeper
    speeds = [p["speed"] for k, p in c.steps if k == "ramp"]
    if ramping <= 0.0 or not speeds or not took < 0.97 * seconds:
        return None
    least = max(SLOWEST, slowest_m_s / min(speeds))
    share = max(ramping / (ramping + seconds - took), least)
    # the first share counts only the time going deeper (a cycle's ramps back out are slowed too)
    # and the drive's acceleration as it was: where the trial comes out too long, a little faster
    while share < 1.0:
        steps = [(k, {**p, "speed": p["speed"] * share}) if k == "ramp" else (k, p) for k, p in c.steps]
        shown = ", ".join(dict.fromkeys(_mm(p["speed"]) for k, p in steps if k == "ramp"))
        out = Candidate(f"{c.name}, ramps at {100 * share:.0f} % speed ({shown} mm/s)",
                        f"{c.why}; slowed to use the time left", steps)
        out.trial = _trial(out, config)
        if float(out.trial.motion.t_s[-1]) <= seconds:
            return out
        share *= 1.03
    return None


def inadmissible(c: Candidate, peak_N: float, config: RigConfig, room: Room | None = None) -> str:
    """Why the candidate may not be run on this rig ("" when it may): its protocol beyond a
    limit (as `rig run` checks it), deeper than `room` allows, or its predicted peak force above
    the room's share of the force limit."""
    room = room or default_room(config)
    try:
        check_limits(parse_protocol(protocol_text(c, c.name, None, [], room.travel_mm), c.name), config)
    except LimitError as exc:
        return str(exc)
    deepest_m = max((p["to"] for k, p in c.steps if k == "ramp"), default=0.0)
    if deepest_m > room.depth_m * (1 + 1e-9):
        return f"{c.name}: to {_mm(deepest_m)} mm, past the {_mm(room.depth_m)} mm the travel leaves"
    if peak_N > room.force_share * config.limits.max_force_N:
        return (f"{c.name}: predicted peak {peak_N:.3g} N, above {room.force_share:g} of the force limit "
                f"{config.limits.max_force_N:g} N")
    if room.max_peak_N is not None and peak_N > room.max_peak_N:
        return f"{c.name}: predicted peak {peak_N:.3g} N, above the {room.max_peak_N:.3g} N the room allows"
    return ""


def design(ex: Explanation, config: RigConfig | None = None,
           max_duration_s: float | None = None, room: Room | None = None) -> Design | None:
    """The protocol that best separates the first look-alike pair, or None without one;
    `max_duration_s`: the specimen time left for it, `room`: where it may go (a campaign's budget
    and margins; default `default_room`)."""
    if not ex.lookalikes:
        return None
    config = config or RigConfig()
    pair = ex.lookalikes[0]["effects"]
    a, b = alternatives(ex, pair)
    noise = ex.base.noise_N
    trials = ex.base.trials
    shape = shape_of(trials)
    limits = config.limits
    cands, refused = [], []
    for c in rig_candidates(shape, config, room):
        duration = float(c.trial.motion.t_s[-1])
        if duration > MAX_DURATION * shape.duration_s:
            refused.append(f"{c.name}: {duration:.0f} s, over {MAX_DURATION:g}x the trials given")
            continue
        if max_duration_s is not None and duration > max_duration_s:
            refused.append(f"{c.name}: {duration:.0f} s, over the {max_duration_s:.0f} s the budget leaves")
            continue
        pa, pb = a.model.predict(a.values, c.trial.motion), b.model.predict(b.values, c.trial.motion)
        c.predictions = (pa, pb)
        c.peak_N = float(max(np.max(pa), np.max(pb)))
        why = inadmissible(c, c.peak_N, config, room)
        if why:
            refused.append(why)
            continue
        c.difference_N = float(np.sqrt(np.mean((pa - pb) ** 2)))
        cands.append(c)
    if not cands:
        raise RigError("no candidate protocol fits within the rig's limits: " + "; ".join(refused[:3]))
    cands.sort(key=lambda c: -c.difference_N)
    for c in cands[:CHECKED]:
        _separation(c, a, b, trials)
    cands.sort(key=lambda c: -(c.separation_N if c.separation_N is not None else -1.0))
    d = Design((pair[0], pair[1]), (a, b), noise, cands[0], cands, refused,
               proposed=ex.lookalikes[0].get("separate_with", ""))
    d.yaml = design_yaml(d, limits.max_force_N, room.travel_mm if room is not None else None)
    proto = parse_protocol(d.yaml, "<design>")
    check_limits(proto, config)  # as `rig run` will
    d.duration_s = plan(proto, config).duration_s
    return d


def _separation(c: Candidate, a: FitResult, b: FitResult, trials: list[TrialData]) -> None:
    """Refit the wrong model to the trials given plus the candidate as the other predicts it;
    what it still misses on the candidate. With nested models (one is the other plus an effect)
    only the larger can be the truth the smaller cannot follow; otherwise either may be, and
    the weaker direction counts."""
    pa, pb = c.predictions
    directions = [(a, b, pa)] if _nested(a.model, b.model) else \
        [(b, a, pb)] if _nested(b.model, a.model) else [(a, b, pa), (b, a, pb)]
    worst = None
    for truth, wrong, data in directions:
        stride = max(1, min(t.n for t in trials) // SCREEN_SAMPLES)
        new = c.trial
        made = TrialData(new.name, new.motion, data, new.phase, None, "design")
        k = max(1, new.n // SCREEN_SAMPLES)
        res = fit(wrong.model, [decimate(t, stride) for t in trials] + [decimate(made, k)], starts=1,
                  initial=wrong.values, tol=1e-8, max_nfev=REFIT_NFEV, polish=False)
        miss = float(np.sqrt(np.mean(res.residuals[-1] ** 2)))
        if worst is None or miss < worst[0]:
            worst = (miss, _effect_of(wrong, truth))
    c.separation_N, c.wrong = worst


def _effect_of(wrong: FitResult, truth: FitResult) -> str:
    """Name the wrong alternative by what it lacks or has instead."""
    extra = [e for e in wrong.model.effect_names if e not in truth.model.effect_names]
    lacks = [e for e in truth.model.effect_names if e not in wrong.model.effect_names]
    if extra:
        return f"the model with {extra[0]}"
    return f"the model without {lacks[0]}" if lacks else wrong.model.name


def trial_limit_N(peak_N: float, force_limit_N: float) -> float:
    """A designed trial's own force limit: about twice its predicted peak (a specimen far stiffer
    than its fitted model faults there, not at the rig's limit), never above the rig's."""
    return min(force_limit_N, max(math.ceil(2 * peak_N), 1))


def design_yaml(d: Design, force_limit_N: float, travel_mm: tuple[float, float] | None = None) -> str:
    """The designed protocol as a protocol file, with a comment that says what it tells apart and by how
    much, its force limit set from the predicted peak within the rig's."""
    b = d.best
    x, y = d.effects
    limit = trial_limit_N(b.peak_N, force_limit_N)
    comment = [f"Designed by rig analyze --design to tell {x} from {y} (look-alikes on the trials given).",
               f"Predicted with both fitted models: they differ by {b.difference_N:.3g} N RMS on this trial "
               f"({b.difference_N / d.noise_N:.1f}x the noise, {d.noise_N:.3g} N);",
               f"refitted to the trials given plus this one, {b.wrong} still misses it by "
               f"{b.separation_N:.3g} N RMS ({b.separation_N / d.noise_N:.1f}x the noise).",
               f"Predicted peak force {b.peak_N:.3g} N. Depths are from the zero the analysis took as contact.",
               "Run it on the same specimen, then analyze it together with the trials given."]
    if not d.settles:
        comment = [*_wrapped(f"WARNING: {d.warning()}."), *comment]
    return protocol_text(b, f"separate {x} from {y}: {b.name}", limit, comment, travel_mm)


def _wrapped(text: str, width: int = 100) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width)


def write_design(d: Design, path: str | Path) -> Path:
    """Write the designed protocol to `path`; RigError if it cannot be written."""
    p = Path(path)
    try:
        p.write_text(d.yaml)
    except OSError as exc:
        raise RigError(f"{p}: cannot write the protocol ({exc.strerror})") from None
    return p


def format_design(d: Design, path: str | Path) -> str:
    """The design in words: which protocol to run, how long, how far apart the two models are on it and
    after refitting, and where it was written."""
    b = d.best
    lines = [f"design: to tell {d.effects[0]} from {d.effects[1]}, run '{b.name}' ({path}, about "
             f"{d.duration_s:.0f} s, peak force about {b.peak_N:.3g} N)",
             f"  the two fitted models differ by {b.difference_N:.3g} N RMS on it "
             f"({b.difference_N / d.noise_N:.1f}x the noise); refitted with it, {b.wrong} still misses it "
             f"by {b.separation_N:.3g} N RMS "
             f"({b.separation_N / d.noise_N:.1f}x the noise)"]
    if not d.settles:
        lines.append(f"  warning: {d.warning()}")
    if d.proposal():
        lines.append(f"  {d.proposal()}")
    lines.append(f"  {'candidate':<44}{'differ N':>10}{'refit miss N':>14}")
    for c in d.ranked[:8]:
        sep = f"{c.separation_N:>14.3g}" if c.separation_N is not None else f"{'-':>14}"
        lines.append(f"  {c.name[:43]:<44}{c.difference_N:>10.3g}{sep}")
    return "\n".join(lines)
