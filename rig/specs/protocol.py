"""Protocol files: load, validate against the rig's limits, and plan.

A protocol is a list of steps run in order, optionally repeated with a rest between
repeats. Positions are in mm from the trial's zero: the start position, or the contact
point found by an `approach` step. Every error names file, line, column and field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rig.errors import LimitError, SpecError
from rig.specs.config import LimitsConfig, RigConfig
from rig.specs.motion import sample_move
from rig.specs.yamlspec import MapView, Marked, load_marked, read_text


@dataclass(frozen=True)
class Ramp:
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
    max_force_N: float | None = None
    max_speed_mm_s: float | None = None
    travel_mm: tuple[float, float] | None = None


@dataclass
class Protocol:
    name: str
    steps: list[Step]
    description: str = ""
    repeat: int = 1
    rest_s: float = 0.0
    limits: ProtocolLimits = field(default_factory=ProtocolLimits)
    source_path: str = "<memory>"
    source_text: str = ""

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
            travel = (float(vals[0]), float(vals[1]))
        limits = ProtocolLimits(lv.number("max_force_N", gt=0), lv.number("max_speed_mm_s", gt=0),
                                travel)
    return Protocol(
        name=name,
        description=root.text("description", "") or "",
        steps=steps,
        repeat=root.integer("repeat", 1, ge=1),
        rest_s=root.number("rest_s", 0.0, ge=0),
        limits=limits,
        source_path=path,
        source_text=text,
    )


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
                         max_mm=v.number("max_mm", required=True), line=line)
    if kind == "hold_force":
        return HoldForce(force_N=v.number("force_N", required=True, gt=0),
                         duration_s=v.number("duration_s", required=True, gt=0),
                         max_mm=v.number("max_mm", required=True), line=line)
    return Approach(speed_mm_s=v.number("speed_mm_s", required=True, gt=0),
                    contact_N=v.number("contact_N", required=True, gt=0),
                    max_mm=v.number("max_mm", required=True), line=line)


# ------------------------------------------------------------------ limits

def check_limits(proto: Protocol, config: RigConfig, start_mm: float | None = None) -> None:
    """Refuse, before anything moves, a protocol beyond the rig's travel, speed or force limits.

    `start_mm` is where the slider is now (the trial's zero); without it, the simulated
    rig's start position or 0 (a check made before the devices are opened).
    """
    rig = config.limits
    where = proto.source_path

    def refuse(line: int, msg: str) -> LimitError:
        return LimitError(f"{where}:{line}: {msg}" if line else f"{where}: {msg}")

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
    lo, hi = eff.travel_mm
    if start_mm is None:
        start = config.sim.slider.start_mm if config.slider.backend == "sim" else 0.0
        from_where = ""
    else:
        start = start_mm
        from_where = f" from the slider's position {start_mm:.3f} mm"
    zero_lo = zero_hi = 0.0  # where zero indentation may sit, relative to the start position
    for step in proto.steps:
        speed = getattr(step, "speed_mm_s", None)
        if speed is not None and speed > eff.max_speed_mm_s:
            raise refuse(step.line, f"{step.kind} speed {speed:g} mm/s exceeds the limit of "
                                    f"{eff.max_speed_mm_s:g} mm/s")
        if isinstance(step, Approach):
            if step.contact_N >= eff.max_force_N:
                raise refuse(step.line, f"approach contact_N {step.contact_N:g} N is not below the "
                                        f"force limit {eff.max_force_N:g} N")
            targets = [zero_lo + step.max_mm, zero_hi + step.max_mm]
            zero_lo, zero_hi = min(zero_lo, *targets), max(zero_hi, *targets)
        elif isinstance(step, Ramp | Return) and step.to_mm is not None:
            targets = [zero_lo + step.to_mm, zero_hi + step.to_mm]
        elif isinstance(step, FORCE_STEPS):
            target_N = step.to_N if isinstance(step, RampForce) else step.force_N
            # the loop overshoots by a few per cent and the limit counts the preload too
            if target_N > FORCE_SETPOINT_SHARE * eff.max_force_N:
                raise refuse(step.line, f"{step.kind} to {target_N:g} N is above {FORCE_SETPOINT_SHARE:g} of "
                                        f"the force limit {eff.max_force_N:g} N (room for its overshoot)")
            targets = [zero_lo + step.max_mm, zero_hi + step.max_mm]
        else:
            continue
        for t in targets:
            if not lo <= start + t <= hi:
                raise refuse(step.line, f"{step.kind} to {t:g} mm{from_where} (absolute {start + t:g} mm) "
                                        f"is outside the travel window [{lo:g}, {hi:g}] mm")


def _line_of(proto: Protocol, key: str) -> int:
    for n, text in enumerate(proto.source_text.splitlines(), 1):
        if key in text:
            return n
    return 0


# ------------------------------------------------------------------ planning

@dataclass
class Plan:
    duration_s: float
    upper_bound: bool  # a hold-until-relaxed step may end earlier
    depths_mm: list[float]
    speeds_mm_s: list[float]
    t_s: np.ndarray
    position_mm: np.ndarray


def plan(proto: Protocol, config: RigConfig) -> Plan:
    """The commanded motion at the loop rate (holds at their longest; contact assumed at max_mm/2)."""
    rate = config.loop.rate_Hz
    accel = config.slider.accel_mm_s2
    pos, zero, start = 0.0, 0.0, 0.0
    segments: list[np.ndarray] = [np.zeros(round(config.loop.tare_s * rate) + 1)]
    depths: list[float] = []
    speeds: list[float] = []
    upper = False
    force = 0.0
    for _, step in proto.run_steps():
        if isinstance(step, Hold):
            upper |= step.until_rate_N_s is not None
            segments.append(np.full(max(round(step.longest_s * rate), 1), pos))
            continue
        if isinstance(step, FORCE_STEPS):
            # the motion follows the specimen: planned as standing, for as long as the step lasts
            # (a ramp from the force the plan last knew)
            to = step.to_N if isinstance(step, RampForce) else step.force_N
            span = abs(to - force) / step.rate_N_s if isinstance(step, RampForce) else step.duration_s
            force = to
            upper = True
            segments.append(np.full(max(round(span * rate), 1), pos))
            continue
        if isinstance(step, Approach):
            target = zero + step.max_mm / 2.0
        elif isinstance(step, Return) and step.to_mm is None:
            target = start
        else:
            target = zero + step.to_mm
        speeds.append(step.speed_mm_s)
        if isinstance(step, Ramp):
            depths.append(step.to_mm)
        segments.append(sample_move(pos, target, step.speed_mm_s,
                                    getattr(step, "accel_mm_s2", None) or accel, rate))
        pos = target
        if isinstance(step, Approach):
            zero = pos
            upper = True
    x = np.concatenate(segments)
    t = np.arange(len(x)) / rate
    return Plan(float(t[-1]), upper, depths, speeds, t, x)
