"""Protocol files: load, validate against the rig's limits, and plan.

A protocol is a list of steps run in order, optionally repeated with a rest between
repeats. Positions are in mm from the trial's zero: the start position, or the contact
point found by an `approach` step. Every error names file, line, column and field.
"""

from __future__ import annotations

import math
import typing
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rig.errors import LimitError, SpecError
from rig.specs.config import MAX_PROTOCOL_STEPS_CEILING, LimitsConfig, RigConfig
from rig.specs.motion import LaggedSums, move_time, sample_move
from rig.specs.yamlspec import MapView, Marked, load_marked, read_text


@dataclass(frozen=True)
class Ramp:
    """Move to `to_mm` (the protocol's frame) at `speed_mm_s`."""

    to_mm: float
    speed_mm_s: float
    accel_mm_s2: float | None = None
    line: int = 0
    kind: str = "ramp"


@dataclass(frozen=True)
class Hold:
    """Hold position for `duration_s`, or until |df/dt| < `until_rate_N_s` (capped at `max_s`)."""

    duration_s: float | None = None
    until_rate_N_s: float | None = None
    max_s: float | None = None
    window_s: float = 2.0
    line: int = 0
    kind: str = "hold"

    @property
    def longest_s(self) -> float:
        return self.duration_s if self.duration_s is not None else float(self.max_s or 0.0)


@dataclass(frozen=True)
class Return:
    """Move back; `to_mm` None means the trial's start position."""

    speed_mm_s: float
    to_mm: float | None = None
    line: int = 0
    kind: str = "return"


@dataclass(frozen=True)
class Approach:
    """Move slowly until the force exceeds `contact_N`; that point becomes zero indentation."""

    speed_mm_s: float
    contact_N: float
    max_mm: float
    line: int = 0
    kind: str = "approach"


@dataclass(frozen=True)
class RampForce:
    """Force control: the force's setpoint ramps from the force at the step's start to `to_N`
    (compression, > 0) at `rate_N_s`; the force loop moves the slider, never deeper than `max_mm`
    from the working zero (required, as an approach's: a specimen that slips or tears would
    otherwise be chased to the end of the travel)."""

    to_N: float
    rate_N_s: float
    max_mm: float
    line: int = 0
    kind: str = "ramp_force"


@dataclass(frozen=True)
class HoldForce:
    """Force control: hold the force at `force_N` for `duration_s` (the indentation creeps)."""

    force_N: float
    duration_s: float
    max_mm: float
    line: int = 0
    kind: str = "hold_force"

    @property
    def longest_s(self) -> float:
        return self.duration_s


Step = Ramp | Hold | Return | Approach | RampForce | HoldForce
FORCE_SETPOINT_SHARE = 0.9  # of the force limit, at most, for a force step's setpoint
FORCE_STEPS = (RampForce, HoldForce)
STEP_KINDS = ("ramp", "hold", "return", "approach", "ramp_force", "hold_force")


@dataclass(frozen=True)
class ProtocolLimits:
    """Limits a protocol sets for itself: each tightens the rig's own, never loosens it (None: the rig's)."""

    max_force_N: float | None = None
    max_speed_mm_s: float | None = None
    travel_mm: tuple[float, float] | None = None


@dataclass
class Protocol:
    """A protocol file as run: its ``steps`` in order (ramps, holds, returns, approaches, force
    ramps and holds), repeated ``repeat`` times with ``rest_s`` between, within its own
    ``limits``; ``source_text`` is logged with every trial."""

    name: str
    steps: list[Step]
    description: str = ""
    repeat: int = 1
    rest_s: float = 0.0
    limits: ProtocolLimits = field(default_factory=ProtocolLimits)
    source_path: str = "<memory>"
    source_text: str = ""
    repeat_line: int = field(default=0, repr=False)  # where `repeat` is written, for its errors

    @property
    def executed_steps(self) -> int:
        """How many steps run: every step in every repeat, and a rest between repeats."""
        rests = self.repeat - 1 if self.rest_s > 0 else 0
        return len(self.steps) * self.repeat + rests

    def executed_steps_text(self) -> str:
        rests = f" + {self.repeat - 1} rests" if self.rest_s > 0 and self.repeat > 1 else ""
        return f"{self.executed_steps} steps run ({len(self.steps)} x repeat {self.repeat}{rests})"

    def run_steps(self) -> list[tuple[int, Step]]:
        """The steps as executed: (repeat index, step), with rests between repeats as holds."""
        out: list[tuple[int, Step]] = []
        for r in range(self.repeat):
            if r and self.rest_s > 0:
                out.append((r, Hold(duration_s=self.rest_s, line=0)))
            out.extend((r, s) for s in self.steps)
        return out

    def effective_limits(self, rig: LimitsConfig) -> LimitsConfig:
        """The rig's limits, tightened by the protocol's."""
        lim = self.limits
        travel = rig.travel_mm
        if lim.travel_mm:
            travel = (max(travel[0], lim.travel_mm[0]), min(travel[1], lim.travel_mm[1]))
        return replace(
            rig,
            max_force_N=min(rig.max_force_N, lim.max_force_N or math.inf),
            travel_mm=travel,
            max_speed_mm_s=min(rig.max_speed_mm_s, lim.max_speed_mm_s or math.inf),
        )


# ------------------------------------------------------------------ loading

_STEP_KEYS = {
    "ramp": ("to_mm", "speed_mm_s", "accel_mm_s2"),
    "hold": ("duration_s", "until_rate_N_s", "max_s", "window_s"),
    "return": ("to_mm", "speed_mm_s"),
    "approach": ("speed_mm_s", "contact_N", "max_mm"),
    "ramp_force": ("to_N", "rate_N_s", "max_mm"),
    "hold_force": ("force_N", "duration_s", "max_mm"),
}


def load_protocol(path: str | Path, config: RigConfig | None = None) -> Protocol:
    """Load a protocol file; with `config`, also refuse it if it exceeds the rig's limits."""
    proto = parse_protocol(read_text(path, "protocol file"), str(path))
    if config is not None:
        check_limits(proto, config)
    return proto


def parse_protocol(text: str, path: str = "<protocol>") -> Protocol:
    """The protocol in `text` (YAML), checked step by step: a wrong key, kind or value raises
    `RigError` naming the file, the line and the step."""
    root = MapView(load_marked(path, text), path)
    root.check_keys(("name", "description", "steps", "repeat", "rest_s", "limits"))
    name = root.text("name", required=True)
    steps_node = root.require("steps")
    if not isinstance(steps_node.value, list) or not steps_node.value:
        raise root.error("steps", "expected a non-empty list of steps")
    steps = [_parse_step(node, path, i) for i, node in enumerate(steps_node.value)]
    limits = ProtocolLimits()
    if root.has("limits"):
        lv = MapView(root.get("limits"), path, "limits")
        lv.check_keys(("max_force_N", "max_speed_mm_s", "travel_mm"))
        travel = None
        if lv.has("travel_mm"):
            tn = lv.get("travel_mm")
            vals = tn.plain()
            if (not isinstance(vals, list) or len(vals) != 2
                    or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in vals)
                    or not vals[0] < vals[1]):
                raise lv.error("travel_mm", "expected [min_mm, max_mm] with min < max")
            if not all(math.isfinite(v) for v in vals):
                raise lv.error("travel_mm", f"expected finite numbers [min_mm, max_mm], got {vals}: "
                                            "a travel window without ends limits nothing")
            travel = (float(vals[0]), float(vals[1]))
        limits = ProtocolLimits(lv.number("max_force_N", gt=0), lv.number("max_speed_mm_s", gt=0),
                                travel)
    repeat_node = root.get("repeat")
    proto = Protocol(
        name=name,
        description=root.text("description", "") or "",
        steps=steps,
        repeat=root.integer("repeat", 1, ge=1),
        rest_s=root.number("rest_s", 0.0, ge=0),
        limits=limits,
        source_path=path,
        source_text=text,
        repeat_line=repeat_node.line if repeat_node is not None else 0,
    )
    # Whatever the rig's cap (`limits.max_protocol_steps`, checked with the rig's limits), no
    # rig takes more: refused here, before any code walks the steps (a list of 3e8 steps is
    # gigabytes and minutes).
    if proto.executed_steps > MAX_PROTOCOL_STEPS_CEILING:
        raise root.error("repeat", f"{proto.executed_steps_text()}: more than any rig config allows "
                                   f"({MAX_PROTOCOL_STEPS_CEILING}; limits.max_protocol_steps is "
                                   f"{LimitsConfig().max_protocol_steps} by default)")
    return proto


def _parse_step(node: Marked, path: str, i: int) -> Step:
    where = f"steps[{i}]"
    if not isinstance(node.value, dict) or len(node.value) != 1:
        raise SpecError(f"each step is one of {', '.join(STEP_KINDS)} with its fields, "
                        f"e.g. '- ramp: {{to_mm: 30, speed_mm_s: 1.5}}'",
                        path=path, line=node.line, column=node.column, field=where)
    outer = MapView(node, path, where)
    outer.check_keys(STEP_KINDS)
    (kind, body), = node.value.items()
    where = f"{where}.{kind}"
    if body.value is None:
        raise SpecError(f"'{kind}' needs fields: {', '.join(_STEP_KEYS[kind])}",
                        path=path, line=body.line, column=body.column, field=where)
    v = MapView(body, path, where)
    v.check_keys(_STEP_KEYS[kind])
    line = body.key_line or body.line
    if kind == "ramp":
        return Ramp(to_mm=v.number("to_mm", required=True),
                    speed_mm_s=v.number("speed_mm_s", required=True, gt=0),
                    accel_mm_s2=v.number("accel_mm_s2", gt=0), line=line)
    if kind == "hold":
        duration = v.number("duration_s", gt=0)
        rate = v.number("until_rate_N_s", gt=0)
        max_s = v.number("max_s", gt=0)
        if duration is None and rate is None:
            raise v.error(None, "hold needs 'duration_s', or 'until_rate_N_s' with 'max_s'")
        if duration is not None and rate is not None:
            raise v.error("until_rate_N_s", "give either 'duration_s' or 'until_rate_N_s', not both")
        if rate is not None and max_s is None:
            raise v.error("until_rate_N_s", "'until_rate_N_s' needs 'max_s' (a time cap)")
        return Hold(duration_s=duration, until_rate_N_s=rate, max_s=max_s,
                    window_s=v.number("window_s", 2.0, gt=0), line=line)
    if kind == "return":
        return Return(speed_mm_s=v.number("speed_mm_s", required=True, gt=0),
                      to_mm=v.number("to_mm"), line=line)
    if kind == "ramp_force":
        return RampForce(to_N=v.number("to_N", required=True, gt=0),
                         rate_N_s=v.number("rate_N_s", required=True, gt=0),
                         max_mm=_max_mm(v, kind), line=line)
    if kind == "hold_force":
        return HoldForce(force_N=v.number("force_N", required=True, gt=0),
                         duration_s=v.number("duration_s", required=True, gt=0),
                         max_mm=_max_mm(v, kind), line=line)
    return Approach(speed_mm_s=v.number("speed_mm_s", required=True, gt=0),
                    contact_N=v.number("contact_N", required=True, gt=0),
                    max_mm=_max_mm(v, kind), line=line)


def _max_mm(v: MapView, kind: str) -> float:
    """An approach's or force step's depth budget from the working zero: it pushes in, so the
    budget is a depth (> 0); a negative one would send the step the other way, retracting."""
    max_mm = v.number("max_mm", required=True)
    if not max_mm > 0:
        pushes = "moves in until it finds contact" if kind == "approach" else "pushes in"
        raise v.error("max_mm", f"must be greater than 0, got {max_mm:g}: {kind} {pushes}, and "
                                f"max_mm is how deep it may go from the working zero")
    return max_mm


# ------------------------------------------------------------------ where the slider may go

APPROACH_CONTACT_TICKS = 5  # the sequencer's: this many ticks above contact_N in a row, then STOP


@dataclass(frozen=True)
class Span:
    """Where a position may be: from `lo_mm` to `hi_mm`, measured from the trial's start, or
    from the first contact (`from_contact`) once an approach has found the surface."""

    lo_mm: float
    hi_mm: float
    from_contact: bool = False

    def shifted(self, mm: float) -> Span:
        return Span(self.lo_mm + mm, self.hi_mm + mm, self.from_contact)


class Reach:
    """Where the working zero and the slider may be, step after executed step.

    Before any approach every position is known from the start. The first approach finds the
    surface somewhere between where it starts and its max_mm (a plan, `nominal`, takes
    halfway): that first contact is the frame later positions are measured in. A later approach
    meets the surface again: at once where it starts if the probe is still in contact (at or past
    the first contact), running on by its stopping distance, else back at the first contact.
    So a repeat whose `return: {to_mm: 4}` leaves the probe in contact re-zeroes 4 mm deeper
    each time, and the depths add up; one whose return leaves contact starts where the last did.
    The surface is taken not to sink between repeats; if it did, the approach would go on to its
    max_mm, and that target is checked too.
    """

    def __init__(self, config: RigConfig, *, nominal: bool = False) -> None:
        self.nominal = nominal
        self.rate_Hz = config.loop.rate_Hz
        self.accel_mm_s2 = config.slider.accel_mm_s2
        self.contact: tuple[float, float] | None = None  # the first contact, from the start
        self.zero = Span(0.0, 0.0)
        self.pos = Span(0.0, 0.0)

    def state(self) -> tuple[tuple[float, float] | None, Span, Span]:
        return self.contact, self.zero, self.pos

    def in_frame(self, span: Span) -> tuple[float, float]:
        """`span` in the working frame: from the first contact once one is found."""
        if span.from_contact or self.contact is None:
            return span.lo_mm, span.hi_mm
        return span.lo_mm - self.contact[1], span.hi_mm - self.contact[0]

    def from_start(self, span: Span) -> tuple[float, float]:
        if not span.from_contact or self.contact is None:
            return span.lo_mm, span.hi_mm
        return span.lo_mm + self.contact[0], span.hi_mm + self.contact[1]

    def _span(self, lo: float, hi: float) -> Span:
        return Span(lo, hi, self.contact is not None)

    def step(self, step: Step) -> list[Span]:
        """Carry out `step`: the positions it may send the slider to (its move's target, the
        deepest a force step may push, where an approach stops)."""
        if isinstance(step, Hold):
            return []
        if isinstance(step, Return) and step.to_mm is None:
            self.pos = Span(0.0, 0.0)
            return [self.pos]
        if isinstance(step, Ramp | Return):
            self.pos = self.zero.shifted(step.to_mm)
            return [self.pos]
        deepest = self.zero.shifted(step.max_mm)
        if isinstance(step, FORCE_STEPS):
            if not self.nominal:  # the loop moves the slider anywhere down to its max_mm
                p_lo, p_hi = self.in_frame(self.pos)
                z_lo, _ = self.in_frame(self.zero)
                self.pos = self._span(min(p_lo, z_lo), max(p_hi, self.in_frame(deepest)[1]))
            return [deepest]  # (a plan takes the motion as standing: it follows the specimen)
        return self._approach(step, deepest)

    def _approach(self, step: Approach, target: Span) -> list[Span]:
        p_lo, p_hi = self.in_frame(self.pos)
        t_lo, t_hi = self.in_frame(target)
        if self.contact is None:
            # anywhere between where it starts and its max_mm; a plan: halfway
            self.contact = (((p_lo + t_lo) / 2,) * 2 if self.nominal
                            else (min(p_lo, t_lo), max(p_hi, t_hi)))
            self.zero = self.pos = Span(0.0, 0.0, True)
            return [target, self.pos] if not self.nominal else [self.pos]
        speed = step.speed_mm_s
        run_on = speed * APPROACH_CONTACT_TICKS / self.rate_Hz + speed * speed / (2 * self.accel_mm_s2)
        self.zero = self.pos = Span(_contact_again(p_lo, t_lo, run_on), _contact_again(p_hi, t_hi, run_on),
                                    True)
        return [target, self.pos] if not self.nominal else [self.pos]


def _contact_again(p: float, target: float, run_on: float) -> float:
    """Where an approach from `p` towards `target` stops, both from the first contact (0): in
    contact from the start (at or past 0, less the first approach's own run-on), it stops after
    `run_on` in the direction it moves; out of contact, at the surface (or at its target, short
    of it: no contact, a fault). Never decreasing in p or target, so a span maps end to end."""
    if p >= -run_on:
        return p + min(max(target - p, -run_on), run_on)
    return min(0.0, target)


# ------------------------------------------------------------------ limits

def check_limits(proto: Protocol, config: RigConfig, start_mm: float | None = None) -> None:
    """Refuse, before anything moves, a protocol beyond the rig's travel, speed or force limits,
    or with more steps to run than the rig's `limits.max_protocol_steps`.

    `start_mm` is where the slider is now (the trial's zero); without it, the simulated
    rig's start position or 0 (a check made before the devices are opened). The travel is
    checked on every executed step, repeat after repeat, from where each may start (`Reach`),
    in time proportional to the steps run (at most the cap), less where a repeat starts
    exactly where the one before did (then the rest go where it went).
    """
    rig = config.limits
    where = proto.source_path

    def refuse(line: int, msg: str) -> LimitError:
        return LimitError(f"{where}:{line}: {msg}" if line else f"{where}: {msg}")

    if proto.executed_steps > rig.max_protocol_steps:
        raise refuse(proto.repeat_line or _line_of(proto, "repeat"),
                     f"repeat {proto.repeat}: {proto.executed_steps_text()}, more than the rig's "
                     f"limits.max_protocol_steps {rig.max_protocol_steps} (fewer repeats, or a rig "
                     f"config that raises the cap)")
    lim = proto.limits
    if lim.max_force_N is not None and lim.max_force_N > rig.max_force_N:
        raise refuse(_line_of(proto, "max_force_N"),
                     f"limits.max_force_N {lim.max_force_N:g} N is looser than the rig's "
                     f"{rig.max_force_N:g} N (a protocol may only tighten limits)")
    if lim.max_speed_mm_s is not None and lim.max_speed_mm_s > rig.max_speed_mm_s:
        raise refuse(_line_of(proto, "max_speed_mm_s"),
                     f"limits.max_speed_mm_s {lim.max_speed_mm_s:g} mm/s is looser than the rig's "
                     f"{rig.max_speed_mm_s:g} mm/s")
    eff = proto.effective_limits(rig)
    # The drive moves in whole steps a second (and a second squared): slower is not slower, it
    # is one step a second (and a move planned to take 1e300 s is no plan).
    slowest = 1.0 / config.slider.steps_per_mm
    drive = f"one step a second, {slowest:g} mm/s at slider.steps_per_mm {config.slider.steps_per_mm:g}"
    for step in proto.steps:
        speed = getattr(step, "speed_mm_s", None)
        if speed is not None and speed > eff.max_speed_mm_s:
            raise refuse(step.line, f"{step.kind} speed {speed:g} mm/s exceeds the limit of "
                                    f"{eff.max_speed_mm_s:g} mm/s")
        if speed is not None and speed < slowest:
            raise refuse(step.line, f"{step.kind} speed {speed:g} mm/s is below the drive's slowest "
                                    f"({drive})")
        accel = getattr(step, "accel_mm_s2", None)
        if accel is not None and accel < slowest:
            raise refuse(step.line, f"{step.kind} accel_mm_s2 {accel:g} is below the drive's least, one "
                                    f"step a second squared ({slowest:g} mm/s^2)")
        if isinstance(step, Approach) and step.contact_N >= eff.max_force_N:
            raise refuse(step.line, f"approach contact_N {step.contact_N:g} N is not below the "
                                    f"force limit {eff.max_force_N:g} N")
        if isinstance(step, FORCE_STEPS):
            target_N = step.to_N if isinstance(step, RampForce) else step.force_N
            # the loop overshoots by a few per cent and the limit counts the preload too
            if target_N > FORCE_SETPOINT_SHARE * eff.max_force_N:
                raise refuse(step.line, f"{step.kind} to {target_N:g} N is above {FORCE_SETPOINT_SHARE:g} of "
                                        f"the force limit {eff.max_force_N:g} N (room for its overshoot)")
    _check_travel(proto, config, eff, start_mm, refuse)


def _check_travel(proto: Protocol, config: RigConfig, eff: LimitsConfig, start_mm: float | None,
                  refuse: typing.Callable[[int, str], LimitError]) -> None:
    lo, hi = eff.travel_mm
    if start_mm is None:
        start = config.sim.slider.start_mm if config.slider.backend == "sim" else 0.0
        from_where = ""
    else:
        start = start_mm
        from_where = f" from the slider's position {start_mm:.3f} mm"
    reach = Reach(config)
    last_start = None
    for r in range(proto.repeat):
        if reach.state() == last_start:
            break  # this repeat starts exactly where the last did: it goes where that one went
        last_start = reach.state()
        for step in proto.steps:
            for span in reach.step(step):
                a_lo, a_hi = reach.from_start(span)
                if lo <= start + a_lo and start + a_hi <= hi:
                    continue
                raise refuse(step.line, _outside(proto, reach, r, step, span, start, from_where, lo, hi))


def _outside(proto: Protocol, reach: Reach, r: int, step: Step, span: Span, start: float,
             from_where: str, lo: float, hi: float) -> str:
    """Why `step` (in repeat `r`) is refused: where it may go, from where, and why there."""
    a_lo, a_hi = reach.from_start(span)
    beyond = start + (a_hi if start + a_hi > hi else a_lo)
    if span.from_contact:
        where_to = f"{_span_text(span.lo_mm, span.hi_mm)} mm from the first contact"
    else:
        where_to = f"{_span_text(span.lo_mm, span.hi_mm)} mm{from_where}"
    absolute = f"absolute {_mm(beyond)} mm" if a_lo == a_hi else (
        f"absolute {'up to' if beyond > hi else 'down to'} {_mm(beyond)} mm")
    prefix = f"repeat {r + 1} of {proto.repeat}: " if proto.repeat > 1 else ""
    msg = f"{prefix}{step.kind} to {where_to} ({absolute}) is outside the travel window [{lo:g}, {hi:g}] mm"
    found = ""
    if reach.contact is not None and reach.contact[0] != reach.contact[1]:
        found = (f"the first contact may be found anywhere from {_mm(reach.contact[0])} to "
                 f"{_mm(reach.contact[1])} mm past the start")
    z_hi = reach.in_frame(reach.zero)[1]
    if r > 0 and z_hi > 0 and reach.contact is not None:
        msg += (": each approach re-zeroes where it finds contact, and one that starts in contact (the "
                "step before it left the probe in the tissue) re-zeroes where it starts, so each repeat "
                f"starts deeper (here the zero may be {_mm(z_hi)} mm past the first contact"
                + (f"; {found})" if found else ")"))
    elif found:
        msg += f" ({found})"
    return msg


def _mm(x: float) -> str:
    return f"{round(x, 2):g}"  # to 10 µm: the sums of steps and run-ons carry more digits than they mean


def _span_text(lo: float, hi: float) -> str:
    return _mm(lo) if lo == hi else f"{_mm(lo)} to {_mm(hi)}"


def _line_of(proto: Protocol, key: str) -> int:
    for n, text in enumerate(proto.source_text.splitlines(), 1):
        if key in text:
            return n
    return 0


# ------------------------------------------------------------------ planning

@dataclass
class Plan:
    """The commanded motion, nominally (holds at their longest, a first contact halfway to an
    approach's max_mm), as pieces: none is sampled, so its size is the steps run, not the
    samples (`samples()` samples it, for a short protocol)."""

    duration_s: float
    upper_bound: bool  # a hold-until-relaxed step may end earlier
    depths_mm: list[float]  # every executed ramp's, from the first contact once one is found
    speeds_mm_s: list[float]
    max_position_mm: float  # from the start position
    depths_by_repeat: list[list[float]]
    depths_from_contact: bool  # an approach comes first: depths are from its contact
    rate_Hz: float
    pieces: list[tuple[float, ...]]  # (position_mm, samples) held, or (from, to, speed, accel) moves

    def lagged_sums(self) -> LaggedSums:
        acc = LaggedSums()
        for piece in self.pieces:
            if len(piece) == 2:
                acc.push_poly((piece[0], 0.0, 0.0), int(piece[1]))
            else:
                acc.push_move(*piece, self.rate_Hz)
        return acc

    def excitation_order(self, resolution: float) -> int:
        """`rig.control.estimator.excitation_order` of the sampled plan, from its pieces."""
        return self.lagged_sums().excitation_order(resolution)

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """(t_s, position_mm) at the loop rate: as long as the trial, for a short protocol."""
        parts = [np.full(int(p[1]), p[0]) if len(p) == 2 else sample_move(*p, self.rate_Hz)
                 for p in self.pieces]
        x = np.concatenate(parts)
        return np.arange(len(x)) / self.rate_Hz, x


def plan(proto: Protocol, config: RigConfig) -> Plan:
    """The commanded motion at the loop rate (holds at their longest; contact assumed halfway to
    the first approach's max_mm, and found again at once by an approach that starts in contact).
    Time and memory in proportion to the steps run."""
    rate = config.loop.rate_Hz
    accel = config.slider.accel_mm_s2
    reach = Reach(config, nominal=True)
    pos = 0.0  # from the start
    samples = round(config.loop.tare_s * rate) + 1
    pieces: list[tuple[float, ...]] = [(0.0, samples)]
    depths: list[list[float]] = []
    speeds: list[float] = []
    upper = False
    force = 0.0
    deepest = 0.0
    for r, step in proto.run_steps():
        if r == len(depths):
            depths.append([])
        if isinstance(step, Hold):
            upper |= step.until_rate_N_s is not None
            n = max(round(step.longest_s * rate), 1)
        elif isinstance(step, FORCE_STEPS):
            # the motion follows the specimen: planned as standing, for as long as the step lasts
            # (a ramp from the force the plan last knew)
            to = step.to_N if isinstance(step, RampForce) else step.force_N
            span = abs(to - force) / step.rate_N_s if isinstance(step, RampForce) else step.duration_s
            force = to
            upper = True
            n = max(round(span * rate), 1)
        else:
            n = 0
        if n:
            pieces.append((pos, n))
            samples += n
            reach.step(step)
            continue
        reach.step(step)
        target = reach.from_start(reach.pos)[0]
        speeds.append(step.speed_mm_s)
        if isinstance(step, Ramp):
            depths[-1].append(round(reach.in_frame(reach.pos)[0], 2))
        move_accel = getattr(step, "accel_mm_s2", None) or accel
        pieces.append((pos, target, step.speed_mm_s, move_accel))
        samples += max(math.ceil(move_time(pos, target, step.speed_mm_s, move_accel) * rate), 1)
        pos = target
        deepest = max(deepest, pos)
        upper |= isinstance(step, Approach)
    first_ramp = next((s for s in proto.steps if isinstance(s, Ramp)), None)
    from_contact = first_ramp is not None and any(
        isinstance(s, Approach) for s in proto.steps[:proto.steps.index(first_ramp)])
    return Plan((samples - 1) / rate, upper, [d for rep in depths for d in rep], speeds, deepest,
                depths, from_contact, rate, pieces)
