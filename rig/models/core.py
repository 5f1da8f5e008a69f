"""Force models built from effects, lmfit style: plain functions, parameters with units and
bounds, composition with `+`.

A model turns a trial's motion into a predicted force through a fixed chain, and every
effect plugs into one stage of it:

    geometry   indentation seen by the tissue      (contact_offset, compliance)
    drive      terms summed into the drive g        (elastic and damping terms)
    rate       a trial's extra lag rate             (speed_relaxation: each of the lag's
                                                     time constants tau becomes 1/(1/tau + rate))
    lag        f + tau df/dt = g                    (relaxation; else f = g)
    branch     parallel branches added after it     (relaxation2, fractional_relaxation)
    clamp      the tissue cannot pull: f >= 0
    sensor     what the load cell adds              (offset, drift, friction)
    delay      the reading arrives late             (delay)

Everything is vectorised: a first-order lag is a linear filter (`scipy.signal.lfilter`),
never a general ODE solver.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.signal import lfilter

STAGES = ("geometry", "drive", "rate", "lag", "branch", "sensor", "delay")


@dataclass(frozen=True)
class Param:
    name: str  # unique across a model; effects that name the same parameter share it
    unit: str
    init: float
    lo: float = -np.inf
    hi: float = np.inf
    scale: float | None = None  # typical magnitude, for the fit's scaling (default: |init| or 1)
    doc: str = ""
    warn_negative: bool = False  # a negative value is physically meaningless
    # init, lo and hi are in the record's own units (force, length and time scales of the data,
    # combined as the unit says) rather than SI: the catalogue's parameters are
    relative: bool = False

    @property
    def typical(self) -> float:
        return self.scale or (abs(self.init) if self.init else 1.0)


@dataclass
class Motion:
    """What the models see of a trial: uniform time, indentation, velocity."""

    t_s: np.ndarray
    x_m: np.ndarray  # indentation from the trial zero (the probe position), m
    v_m_s: np.ndarray  # its time derivative, smoothed
    dt_s: float

    @cached_property
    def speed_m_s(self) -> float:
        """The record's own ramp speed (robust maximum of |v|)."""
        v = np.abs(self.v_m_s)
        return float(np.percentile(v, 99)) if len(v) else 0.0

    @cached_property
    def loading_speed_m_s(self) -> float:
        """The speed of indentation (robust maximum of the velocity into the specimen); the
        return, often faster, does not count."""
        v = self.v_m_s[(self.x_m > 0) & (self.v_m_s > 0)]
        return float(np.percentile(v, 95)) if len(v) else 0.0


@dataclass(frozen=True)
class Effect:
    """One physical effect: where it acts, its parameters, and how it computes."""

    name: str
    stage: str
    params: tuple[Param, ...]
    fn: Callable  # signature depends on the stage; see Model.predict
    equation: str
    signature: str  # where in a trial its absence shows
    source: str = "catalogue"
    needs_force: bool = False  # geometry that depends on the force itself (frame compliance)

    def __post_init__(self) -> None:
        if self.stage not in STAGES:
            raise ValueError(f"effect '{self.name}': stage must be one of {', '.join(STAGES)}")

    def __add__(self, other: Effect | Model) -> Model:
        return Model([self]) + other


@dataclass
class Model:
    effects: list[Effect]
    name: str = ""

    def __post_init__(self) -> None:
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names):
            raise ValueError(f"an effect appears twice in {names}")
        for stage in ("rate", "lag", "delay"):
            if sum(e.stage == stage for e in self.effects) > 1:
                raise ValueError(f"a model holds at most one '{stage}' effect")
        seen: dict[str, Param] = {}
        for e in self.effects:
            for p in e.params:
                if p.name in seen and seen[p.name].unit != p.unit:
                    raise ValueError(f"parameter '{p.name}' has units {seen[p.name].unit} and {p.unit}")
                seen.setdefault(p.name, p)
        self.params: list[Param] = list(seen.values())
        if not self.name:
            self.name = "+".join(e.name for e in self.effects)

    def __add__(self, other: Effect | Model) -> Model:
        extra = other.effects if isinstance(other, Model) else [other]
        return Model(self.effects + [e for e in extra if e.name not in self.effect_names])

    @property
    def effect_names(self) -> list[str]:
        return [e.name for e in self.effects]

    @property
    def param_names(self) -> list[str]:
        return [p.name for p in self.params]

    def has(self, name: str) -> bool:
        return name in self.effect_names

    def predict(self, values: dict[str, float] | np.ndarray, m: Motion) -> np.ndarray:
        """Predicted load-cell force (N) for the motion `m`."""
        if not isinstance(values, dict):
            values = dict(zip(self.param_names, values, strict=True))
        by_stage = {s: [e for e in self.effects if e.stage == s] for s in STAGES}

        def args(e: Effect) -> dict[str, float]:
            return {p.name: values[p.name] for p in e.params}

        compliance = [e for e in by_stage["geometry"] if e.needs_force]
        plain_geometry = [e for e in by_stage["geometry"] if not e.needs_force]
        x, v = m.x_m, m.v_m_s
        for e in plain_geometry:
            x, v = e.fn(x, v, **args(e))
        tissue = self._tissue(x, v, m, by_stage, args)
        for e in compliance:  # the frame spring: indentation = x - f/k; a few fixed-point passes
            for _ in range(3):
                xc, vc = e.fn(x, v, tissue, m.dt_s, **args(e))
                tissue = self._tissue(xc, vc, m, by_stage, args)
        force = tissue
        for e in by_stage["sensor"]:
            force = force + e.fn(m, force, **args(e))
        for e in by_stage["delay"]:
            force = e.fn(m, force, **args(e))
        return force

    def _tissue(self, x, v, m: Motion, by_stage, args) -> np.ndarray:
        contact = x > 0
        xc = np.where(contact, x, 0.0)
        vc = np.where(contact, v, 0.0)
        drive = np.zeros_like(x)
        for e in by_stage["drive"]:
            drive = drive + e.fn(xc, vc, **args(e))
        drive = np.where(contact, drive, 0.0)
        f = drive
        rate = sum(e.fn(m, **args(e)) for e in by_stage["rate"])
        for e in by_stage["lag"]:
            a = args(e)
            if rate:  # a faster lag: every time constant of it shortens alike
                a = {p.name: 1.0 / (1.0 / a[p.name] + rate) if p.unit == "s" else a[p.name] for p in e.params}
            f = e.fn(drive, m.dt_s, **a)
        if by_stage["branch"]:
            # each part of the tissue separates on its own: a lag driven below zero (a fast
            # return) holds no tension to cancel a branch's push
            f = np.maximum(f, 0.0)
        for e in by_stage["branch"]:
            f = f + e.fn(xc, vc, m.dt_s, **args(e))
        return np.maximum(f, 0.0)  # the tissue cannot pull on the probe


def first_order_lag(u: np.ndarray, dt: float, tau: float) -> np.ndarray:
    """y + tau dy/dt = u, exact for u held over each sample (a linear filter)."""
    e = -dt / (tau if abs(tau) > 1e-9 else 1e-9)  # a negative tau grows: meaningless, but defined
    # 1 - a from expm1: for a lag far longer than the record (a creep that never settles) 1 - a
    # is tiny and would otherwise keep only the digits that survive the subtraction
    return lfilter([-float(np.expm1(e))], [1.0, -float(np.exp(e))], u)
