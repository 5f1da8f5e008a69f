"""The log's message types, each defined once.

The JSON schema stored in every log (and sent to the live view), the reader's columns and
the record the loop writes all come from these definitions: a field added here is logged,
described and read back, or the loop's `record` call fails at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any


@dataclass(frozen=True)
class Field:
    """One field of a log message: its name, JSON-schema type, description, whether it is required, and its
    bounds."""

    name: str
    type: str  # a JSON schema type: number, integer, boolean, string, object
    description: str = ""
    required: bool = True
    minimum: float | None = None
    sparse: bool = False  # carried by some messages of a log only (a force step's ticks)

    @property
    def numeric(self) -> bool:
        return self.type in ("number", "integer")

    def schema(self) -> dict[str, Any]:
        out: dict[str, Any] = {"type": self.type}
        if self.minimum is not None:
            out["minimum"] = self.minimum
        if self.description:
            out["description"] = self.description
        return out


@dataclass(frozen=True)
class MessageType:
    """One kind of log message: its topic, title, description and fields; its JSON schema is written into
    every log."""

    topic: str
    title: str
    description: str
    fields: tuple[Field, ...]

    @cached_property
    def schema(self) -> dict[str, Any]:
        """The JSON schema (draft 2020-12 compatible) the log stores for this topic."""
        out: dict[str, Any] = {"title": self.title}
        if self.description:
            out["description"] = self.description
        out |= {"type": "object", "properties": {f.name: f.schema() for f in self.fields},
                "required": [f.name for f in self.fields if f.required]}
        return out

    @cached_property
    def numeric(self) -> tuple[str, ...]:
        """Numeric fields every message carries: the reader's columns."""
        return tuple(f.name for f in self.fields if f.numeric and f.required)

    @cached_property
    def optional_numeric(self) -> tuple[str, ...]:
        """Numeric fields only some logs carry, in every message of those (read when the first
        message has them)."""
        return tuple(f.name for f in self.fields if f.numeric and not f.required and not f.sparse)

    @cached_property
    def sparse_numeric(self) -> tuple[str, ...]:
        """Numeric fields only some messages of a log carry (read when any message has them, NaN
        in the others)."""
        return tuple(f.name for f in self.fields if f.numeric and f.sparse)

    @cached_property
    def _names(self) -> frozenset[str]:
        return frozenset(f.name for f in self.fields)

    @cached_property
    def _required(self) -> frozenset[str]:
        return frozenset(f.name for f in self.fields if f.required)

    def record(self, **values: Any) -> dict[str, Any]:
        """One message as written: the given fields, checked against the definition (a missing
        required field or an unknown one is a programming error, raised at once)."""
        keys = values.keys()
        if not (self._required <= keys <= self._names):
            missing, unknown = sorted(self._required - keys), sorted(keys - self._names)
            raise TypeError(f"{self.title}: missing {missing}, unknown {unknown}")
        return values


def _num(name: str, description: str, required: bool = True, sparse: bool = False) -> Field:
    return Field(name, "number", description, required, sparse=sparse)


def _int(name: str, description: str = "", required: bool = True) -> Field:
    return Field(name, "integer", description, required)


SAMPLE = MessageType("/rig/sample", "rig.Sample", "One loop tick.", (
    Field("seq", "integer", "tick number", minimum=0),
    _num("t_s", "time since trial start, s"),
    _num("position_mm", "feedback position from the working zero (the trial's start; the surface once "
         "an approach found it) as it stood at the start of the tick, mm"),
    _num("position_cmd_mm", "commanded (ideal profile) position from the working zero after the tick, mm"),
    _num("slider_mm", "feedback position in the slider's own coordinates, mm (logs before it derive it "
         "from the step_start events' zero_mm)", required=False),
    _num("force_N", "load cell force after tare, N"),
    _num("stiffness_N_per_m", "online RLS estimate k in f(t) = k x(t-1)"),
    _num("force_pred_N", "a-priori prediction k(t-1) x(t-1), N"),
    _num("error_N", "a-priori error f(t) - k(t-1) x(t-1), N"),
    _num("forgetting", "forgetting factor used this tick (1 = no update)"),
    Field("contact", "boolean", "estimator updated (probe in contact)", required=False),
    _int("step", "step index (-1 tare)"),
    Field("step_kind", "string", "tare, ramp, hold, return, approach, ramp_force, hold_force, fault, done",
          required=False),
    _num("late_ms", "tick start after its scheduled time, ms"),
    _num("force_model_N", "the loaded model's force from the measured position (if a model runs), N",
         required=False),
    _num("model_error_N", "force_N - force_model_N, N", required=False),
    _num("force_cmd_N", "a force-controlled step's setpoint this tick, N", required=False, sparse=True),
    _num("force_error_N", "force_cmd_N - force_N, N", required=False, sparse=True),
))

EVENT = MessageType("/rig/event", "rig.Event", "", (
    _num("t_s", "time since trial start, s"),
    Field("kind", "string", "trial_start, step_start, tare, stop_requested, fault, abort, trial_end"),
    Field("message", "string"),
    Field("data", "object", required=False),
))

HEALTH = MessageType("/rig/health", "rig.Health", "", (
    _num("t_s", "time since trial start, s"),
    _int("ticks"),
    _int("late_ticks", "ticks late so far"),
    _int("missed_ticks", "scheduled ticks skipped so far", required=False),
    _num("period_err_p50_ms", "median |period - nominal| over the last interval, ms", required=False),
    _num("period_err_p99_ms", "99th percentile |period - nominal|, ms"),
    _num("period_err_max_ms", "largest |period - nominal|, ms", required=False),
    _int("bus_transactions", required=False),
    _int("bus_errors", required=False),
    _int("loadcell_lines_ok", required=False),
    _int("loadcell_lines_bad", required=False),
    _num("loadcell_age_ms", "age of the newest load-cell reading, ms", required=False),
    _int("queue_depth", "messages waiting for the writer", required=False),
    _int("live_dropped", "messages the live view dropped (slow viewer)", required=False),
))

MESSAGES = (SAMPLE, EVENT, HEALTH)
SCHEMAS = {m.topic: m.schema for m in MESSAGES}
SAMPLE_TOPIC, EVENT_TOPIC, HEALTH_TOPIC = SAMPLE.topic, EVENT.topic, HEALTH.topic
