"""Force models built from effects, lmfit style: plain functions, parameters with units and
bounds, composition with `+`.

A model turns a trial's motion into a predicted force through a fixed chain, and every
effect plugs into one stage of it:

    geometry   indentation seen by the tissue      (contact_offset, compliance)
    drive      terms summed into the drive g        (elastic and damping terms)
    rate       a trial's extra lag rate             (speed_relaxation: each of the lag's
                                                     time constants tau becomes 1/(1/tau + rate))
    lag        f + tau df/dt = g, f >= 0            (relaxation; else f = g)
    branch     parallel branches added after it     (relaxation2, fractional_relaxation)
    clamp      the tissue cannot pull: f >= 0
    sensor     what the load cell adds              (offset, drift, friction)
    delay      the reading arrives late             (delay)

Everything is vectorised: a first-order lag is a linear recursion solved as a prefix scan
(`linear_recursion`), never a general ODE solver.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from rig.models import frame

STAGES = ("geometry", "drive", "rate", "lag", "branch", "sensor", "delay")
# What each stage passes an effect's function before its parameters (by keyword, named as its
# `Param`s): `Effect` checks a function against these when it is declared.
STAGE_INPUTS = {"geometry": ("x", "v"), "drive": ("x", "v"), "rate": ("m",), "lag": ("drive", "dt"),
                "branch": ("x", "v", "dt"), "sensor": ("m", "force"), "delay": ("m", "force")}
FORCE_GEOMETRY_INPUTS = ("x", "v", "force", "dt")  # a geometry that needs the force (a frame spring)


@dataclass(frozen=True)
class Param:
    """One fitted parameter of an effect: its name, unit, starting value and bounds together.

    ``name`` is unique across a model, and effects that name the same parameter share it (the
    earliest stage's bounds and start define it). ``init``, ``lo`` and ``hi`` are in SI unless
    ``relative`` says they are in the record's own scales (a catalogue parameter starts at a
    fraction of the record's force, length and time, so one catalogue fits a tissue and a cell).
    ``scale`` is the typical magnitude the fit divides by (default: ``|init|``, or 1).
    ``warn_negative``: a negative value is physically meaningless (the fit says so, and
    ``--explain`` rejects a candidate that needs one significantly). ``per_record``: one value per
    record fitted together (``name@0``, ``name@1``, ...), as where each record's surface lies.
    """

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
    # one value per record when several are fitted together: where each record's surface lies
    # differs from record to record (the records' own parameters, named name@0, name@1, ...)
    per_record: bool = False

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
    record: int = 0  # the position of this record among those fitted together

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

    def forget_solutions(self) -> None:
        """Drop the frame solutions kept from earlier predictions on this motion: they are only
        starting points, but a fit must not depend on what was computed before it."""
        self.__dict__.pop("_frame_force", None)
        self.__dict__.pop("_held_x", None)


@dataclass(frozen=True, kw_only=True)
class Effect:
    """One physical effect: where it acts, its parameters, and how it computes; declared by
    keyword, and its function checked against its stage and parameters when it is."""

    name: str
    stage: str
    params: tuple[Param, ...]
    fn: Callable  # (the stage's inputs, STAGE_INPUTS; then the parameters by name)
    equation: str
    signature: str  # where in a trial its absence shows (the residual's shape without it)
    source: str = "catalogue"
    needs_force: bool = False  # geometry that depends on the force itself (frame compliance)
    # a drive or sensor term that is its one parameter times a term free of it: the fit then
    # solves for that parameter directly (rig.analysis.fitting.separable)
    linear: bool = False
    # where a fit should start its parameters, from the data: (motion, measured minus predicted
    # force without the effect, the other parameters' values in SI, the predicted force without
    # the effect) -> {name: SI value}. For an effect whose cost moves in steps with a parameter
    # (a let-go between samples), or has many minima (a delay), which no solver finds from a
    # default start
    guess: Callable | None = None

    @property
    def of_record(self) -> bool:
        """A parameter of the record (where its surface lies, what it reads at rest), not of the
        tissue: fitted with it, never saved, and near nought not "undetermined"."""
        return self.source.startswith("the record")

    def __post_init__(self) -> None:
        if self.stage not in STAGES:
            raise ValueError(f"effect '{self.name}': stage must be one of {', '.join(STAGES)}")
        self._check_fn()

    def _check_fn(self) -> None:
        """`fn` takes the stage's inputs, then exactly the declared parameters by name (as lmfit
        reads a model's names from its function): a misspelt or missing one fails here, at the
        declaration, not at the first fit."""
        import inspect

        try:
            sig = inspect.signature(self.fn)
        except (TypeError, ValueError):  # a builtin or C callable: nothing to read
            return
        kinds = inspect.Parameter
        if any(q.kind is kinds.VAR_KEYWORD for q in sig.parameters.values()):
            return  # takes any names
        inputs = FORCE_GEOMETRY_INPUTS if self.needs_force else STAGE_INPUTS[self.stage]
        named = [q for q in sig.parameters.values() if q.kind is not kinds.VAR_POSITIONAL]
        leading, rest = named[:len(inputs)], named[len(inputs):]
        where = f"effect '{self.name}' ({self.stage} stage)"
        if len(leading) < len(inputs) or any(q.kind is kinds.KEYWORD_ONLY for q in leading):
            raise ValueError(f"{where}: its function must take the stage's inputs "
                             f"({', '.join(inputs)}) first, then its parameters")
        declared = [p.name for p in self.params]
        taken = [q.name for q in rest]
        missing = [n for n in declared if n not in taken]
        extra = [q.name for q in rest if q.name not in declared and q.default is kinds.empty]
        if missing or extra:
            raise ValueError(f"{where}: its parameters are {', '.join(declared) or 'none'}, but its "
                             f"function takes {', '.join(taken) or 'none'} after the inputs "
                             f"({', '.join(inputs)})")

    def __add__(self, other: Effect | Model) -> Model:
        return Model([self]) + other


@dataclass
class Model:
    """A force model: a list of effects, each acting at its stage of the chain from geometry to
    the sensor (``STAGES``), with the parameters they declare.

    Built by adding effects (``build_model("hertz") + CATALOGUE["drift"]``); ``params`` lists
    every fitted parameter in order (a per-record one expanded once per record when ``records``
    > 1), and ``name`` is the effects joined with ``+`` unless given. A model refuses two effects
    of one name, more than one rate, lag or delay stage, more than one force-dependent geometry,
    and one parameter name with two units. ``predict`` gives the force for a trial's motion.
    """

    effects: list[Effect]
    name: str = ""
    records: int = 1  # fitted together: a per-record parameter has this many values

    def __post_init__(self) -> None:
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names):
            raise ValueError(f"an effect appears twice in {names}")
        for stage in ("rate", "lag", "delay"):
            if sum(e.stage == stage for e in self.effects) > 1:
                raise ValueError(f"a model holds at most one '{stage}' effect")
        if sum(e.needs_force for e in self.effects) > 1:
            raise ValueError("a model holds at most one effect whose geometry depends on the force")
        seen: dict[str, Param] = {}
        owner: dict[str, int] = {}
        for e in self.effects:
            for p in e.params:
                if p.name in seen and seen[p.name].unit != p.unit:
                    raise ValueError(f"parameter '{p.name}' has units {seen[p.name].unit} and {p.unit}")
                # a parameter shared by several stages is defined (bounds, init) by the earliest:
                # a sensor term that reads the contact point takes the contact point's bounds
                if p.name not in seen or STAGES.index(e.stage) < owner[p.name]:
                    seen[p.name], owner[p.name] = p, STAGES.index(e.stage)
        self.params: list[Param] = [q for p in seen.values() for q in self._expanded(p)]
        if not self.name:
            self.name = "+".join(e.name for e in self.effects)

    def _expanded(self, p: Param) -> list[Param]:
        if not (p.per_record and self.records > 1):
            return [p]
        return [replace(p, name=f"{p.name}@{i}") for i in range(self.records)]

    def key(self, p: Param, record: int) -> str:
        """The name of `p`'s value for the record at position `record`."""
        return f"{p.name}@{record}" if p.per_record and self.records > 1 else p.name

    def for_records(self, n: int) -> Model:
        """This model fitted to `n` records together (a per-record parameter takes n values)."""
        return Model(list(self.effects), self.name, max(int(n), 1))

    @property
    def has_record_params(self) -> bool:
        """Whether some parameter takes one value per record."""
        return any(p.per_record for p in self.params)

    def __add__(self, other: Effect | Model) -> Model:
        extra = other.effects if isinstance(other, Model) else [other]
        return Model(self.effects + [e for e in extra if e.name not in self.effect_names], records=self.records)

    @property
    def effect_names(self) -> list[str]:
        return [e.name for e in self.effects]

    @property
    def param_names(self) -> list[str]:
        return [p.name for p in self.params]

    def has(self, name: str) -> bool:
        return name in self.effect_names

    def _chain(self, values: dict[str, float] | np.ndarray, m: Motion):
        """The effects by stage, and a function giving an effect its parameters' values for the
        record `m` belongs to (by name, as its function takes them)."""
        if not isinstance(values, dict):
            values = dict(zip(self.param_names, values, strict=True))
        by_stage = {s: [e for e in self.effects if e.stage == s] for s in STAGES}

        def args(e: Effect) -> dict[str, float]:
            return {p.name: values[self.key(p, m.record)] for p in e.params}

        return by_stage, args

    def predict(self, values: dict[str, float] | np.ndarray, m: Motion) -> np.ndarray:
        """Predicted load-cell force (N) for the motion `m`."""
        by_stage, args = self._chain(values, m)
        compliance = [e for e in by_stage["geometry"] if e.needs_force]
        plain_geometry = [e for e in by_stage["geometry"] if not e.needs_force]
        x, v = m.x_m, m.v_m_s
        for e in plain_geometry:
            x, v = e.fn(x, v, **args(e))
        if compliance:  # the frame spring: indentation = x - f/k, solved for f
            force = self._through_frame(compliance[0], x, v, m, by_stage, args)
        else:
            force = self._tissue(x, v, m, by_stage, args)
        for e in by_stage["sensor"]:
            force = force + e.fn(m, force, **args(e))
        for e in by_stage["delay"]:
            force = e.fn(m, force, **args(e))
        return force

    def _filters(self, m: Motion, by_stage, args):
        """(b0, b1, a) of the lag (identity without one), and of a parallel branch that filters
        the rate alone (None when there is none, or it is of another form): read off their
        responses to an impulse."""
        dt = m.dt_s
        lags = by_stage["lag"]
        lag = (1.0, 0.0, 0.0)
        if lags:  # y[i] = a y[i-1] + b0 u[i] + b1 u[i-1], read off its response to an impulse
            y = lags[0].fn(np.array([1.0, 0.0, 0.0]), dt, **self._lag_args(lags[0], m, by_stage, args))
            a = float(y[2] / y[1]) if y[1] else 0.0
            lag = (float(y[0]), float(y[1]) - a * float(y[0]), a)
        branch = None
        if len(by_stage["branch"]) == 1:  # a branch that filters the rate alone enters the step
            b = by_stage["branch"][0]
            zero, pulse = np.zeros(4), np.array([1.0, 0.0, 0.0, 0.0])
            y = b.fn(zero, pulse, dt, **args(b))
            first_order = y[1] != 0 and np.isclose(y[3] * y[1], y[2] ** 2, rtol=1e-9, atol=0.0)
            if (first_order and np.allclose(b.fn(zero, 2 * pulse, dt, **args(b)), 2 * y, rtol=1e-12, atol=0.0)
                    and not np.any(b.fn(pulse, zero, dt, **args(b)))):
                a2 = float(y[2] / y[1])
                branch = (float(y[0]), float(y[1]) - a2 * float(y[0]), a2)
        return lag, branch

    def predict_held(self, values: dict[str, float] | np.ndarray, m: Motion, held: np.ndarray,
                     force_N: np.ndarray, solve: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Creep form (`rig.models.creep`): where `held`, the position x (m) that makes the tissue
        carry the measured force `force_N` (its sensor terms and delay taken off); elsewhere
        the position as measured and the predicted load-cell force. Returns (force, position)
        over the record; the force on held samples is the model's at the predicted position.
        `solve` False: the measured position is kept on held samples too (the forward model in
        creep form's discretisation)."""
        from rig.models import creep

        if not isinstance(values, dict):
            values = dict(zip(self.param_names, values, strict=True))
        by_stage, args = self._chain(values, m)

        # the force the tissue carried: the reading moved back by the delay (the delay run on the
        # record reversed in time moves it forward), less what the sensor adds
        target = np.asarray(force_N, dtype=float)
        for e in by_stage["delay"]:
            back = Motion(-m.t_s[::-1], m.x_m[::-1], -m.v_m_s[::-1], m.dt_s, m.record)
            target = e.fn(back, target[::-1], **args(e))[::-1]
        for e in by_stage["sensor"]:
            target = target - e.fn(m, force_N, **args(e))
        compliance = [e for e in by_stage["geometry"] if e.needs_force]
        plain_geometry = [e for e in by_stage["geometry"] if not e.needs_force]
        dt = m.dt_s
        cache = m.__dict__

        def motion_of(xf: np.ndarray) -> Motion:
            v = m.v_m_s.copy()
            v[held] = creep.backward_velocity(xf, dt)[held]
            out = Motion(m.t_s, xf, v, dt, m.record)
            out.__dict__["_frame_force"] = cache.setdefault("_frame_force", {})
            return out

        def geometry(xf: np.ndarray, vf: np.ndarray):
            for e in plain_geometry:
                xf, vf = e.fn(xf, vf, **args(e))
            return xf, vf

        lag, exact, branch = self._held_filters(m, by_stage, args)
        held_lag = (*exact, held) if by_stage["lag"] else None

        def tissue(xf: np.ndarray) -> np.ndarray:
            mm = motion_of(xf)
            xg, vg = geometry(mm.x_m, mm.v_m_s)
            if compliance:
                return self._through_frame(compliance[0], xg, vg, mm, by_stage, args, (held, target), held_lag)
            return self._tissue(xg, vg, mm, by_stage, args, held_lag)

        def drive_at(xg, vg):
            out = np.zeros_like(xg)
            for d in by_stage["drive"]:
                out = out + d.fn(xg, vg, **args(d))
            return out

        def held_geometry(xh, vh, known):
            xg, vg = geometry(xh, vh)
            for e in compliance:
                xg, vg = xg - known / values[self.key(e.params[0], m.record)], vg
            return xg, vg

        grad_target = np.gradient(target, dt) if len(target) > 1 else np.zeros_like(target)
        x_scale = max(float(np.max(np.abs(m.x_m))), 1e-300)
        v_scale = max(float(np.max(np.abs(m.v_m_s))), x_scale / max(len(m.x_m) * dt, dt))

        def slopes(xf: np.ndarray):
            v = creep.backward_velocity(xf, dt)[held]
            xh = xf[held]
            known = target[held]
            xg, vg = held_geometry(xh, v, known)
            if compliance:
                vg = vg - grad_target[held] / values[self.key(compliance[0].params[0], m.record)]
            contact = xg > 0
            hx, hv = 1e-6 * x_scale, 1e-6 * v_scale
            xg1, vg1 = held_geometry(xh + hx, v, known)
            xg2, vg2 = held_geometry(xh, v + hv, known)
            if compliance:
                k = values[self.key(compliance[0].params[0], m.record)]
                vg1, vg2 = vg1 - grad_target[held] / k, vg2 - grad_target[held] / k
            pos = lambda q: np.maximum(q, 0.0)  # noqa: E731
            d0 = drive_at(pos(xg), vg)
            alpha = np.where(contact, (drive_at(pos(xg1), vg1) - d0) / hx, 0.0)
            beta = np.where(contact, (drive_at(pos(xg2), vg2) - d0) / hv, 0.0)
            return alpha, beta, contact

        key = tuple(self.effect_names)
        last = cache.setdefault("_held_x", {})
        x_full = m.x_m.copy()
        if solve and np.any(held):
            # the lag with its drive held over each step answers half a step early (`_held_filters`):
            # its y[i] is the force of t_i + dt/2, so that is what it is matched to, the held force
            # half a step on (a position otherwise half a step late: 0.075 mm on a 15 mm/s force
            # ramp, about the length noise, and the time constants 2 % long on a quiet record)
            ahead = target.copy()
            ahead[:-1] = 0.5 * (target[:-1] + target[1:])
            if len(target) > 1:
                ahead[-1] = 1.5 * target[-1] - 0.5 * target[-2]
            sol = creep.solve_held(tissue, slopes, m.x_m, held, ahead, dt, lag, branch, last.get(key))
            if np.all(np.isfinite(sol.x_m)):
                last[key] = sol.x_m
            else:
                last.pop(key, None)
            x_full[held] = sol.x_m
        mm = motion_of(x_full)
        force = tissue(x_full)
        for e in by_stage["sensor"]:
            force = force + e.fn(mm, force, **args(e))
        for e in by_stage["delay"]:
            force = e.fn(mm, force, **args(e))
        return force, x_full

    def _held_filters(self, m: Motion, by_stage, args):
        """`_filters` for creep form: on held samples the lag's drive is held over each step,
        y[i] = a y[i-1] + (1 - a) u[i]. The drive taken linear between samples (the force form's)
        gives a lag no gain at all at the sampling's Nyquist frequency, so the position solved
        from a force would be free to ring there without bound; held, the gain there is the lag's
        own (about dt / 2 tau), and the price is half a step's delay, (dt / 2) df/dt of force,
        small where the force is held. Elsewhere the force form's exact step is kept: on a fast
        return (5 N/s) the half step was 0.6 of the noise, and --explain read it as friction.
        Returns the held step (b0, b1, a) for the solve, the lag as (b0, b1, a, held samples) for
        `_tissue`, and the branch."""
        (b0, b1, a), branch = self._filters(m, by_stage, args)
        return (b0 + b1, 0.0, a), (b0, b1, a), branch

    def _through_frame(self, e: Effect, x, v, m: Motion, by_stage, args, held_force=None,
                       held_lag: tuple | None = None) -> np.ndarray:
        """The tissue force f with f = tissue(indentation given f) (`rig.models.frame`), started
        from the last solution of this model on this motion. `held_force`: (mask, force) where
        the force is known (held samples in creep form): the frame's give there is explicit."""
        dt = m.dt_s
        drives = by_stage["drive"]
        lag, branch = self._filters(m, by_stage, args)

        def drive(xc, vc):
            out = np.zeros_like(xc)
            for d in drives:
                out = out + d.fn(xc, vc, **args(d))
            return out

        last = m.__dict__.setdefault("_frame_force", {})
        key = tuple(self.effect_names)
        if held_force is not None:
            mask, known = held_force

            def give(q):
                return e.fn(x, v, np.where(mask, known, q), dt, **args(e))
        else:
            def give(q):
                return e.fn(x, v, q, dt, **args(e))
        solution = frame.solve(give,
                               lambda xc, vc: self._tissue(xc, vc, m, by_stage, args, held_lag),
                               drive, lag, x, v, dt, last.get(key), branch)
        last[key] = solution
        return solution.force_N

    @staticmethod
    def _lag_args(e: Effect, m: Motion, by_stage, args) -> dict[str, float]:
        a = args(e)
        rate = sum(r.fn(m, **args(r)) for r in by_stage["rate"])
        if rate:  # a faster lag: every time constant of it shortens alike
            a = {p.name: 1.0 / (1.0 / a[p.name] + rate) if p.unit == "s" else a[p.name] for p in e.params}
        return a

    def _tissue(self, x, v, m: Motion, by_stage, args, held_lag: tuple | None = None) -> np.ndarray:
        contact = x > 0
        xc = np.where(contact, x, 0.0)
        vc = np.where(contact, v, 0.0)
        drive = np.zeros_like(x)
        for e in by_stage["drive"]:
            drive = drive + e.fn(xc, vc, **args(e))
        drive = np.where(contact, drive, 0.0)
        f = drive
        for e in by_stage["lag"]:
            if held_lag is not None:
                # creep form: the drive held over each step where the force was held, linear
                # between samples elsewhere (`Model._held_filters`)
                b0, b1, a, held = held_lag
                w = b0 * drive
                w[1:] += b1 * drive[:-1]
                w[held] = (b0 + b1) * drive[held]
                f = floored_recursion(w, a)
            else:
                f = e.fn(drive, m.dt_s, **self._lag_args(e, m, by_stage, args))
        if by_stage["branch"]:
            # each part of the tissue separates on its own: a lag driven below zero (a fast
            # return) holds no tension to cancel a branch's push
            f = np.maximum(f, 0.0)
        for e in by_stage["branch"]:
            f = f + e.fn(xc, vc, m.dt_s, **args(e))
        return np.maximum(f, 0.0)  # the tissue cannot pull on the probe


def lag_coefficients(dt: float, tau: float) -> tuple[float, float, float]:
    """(b0, b1, a) of y[i] = a y[i-1] + b0 u[i] + b1 u[i-1]: y + tau dy/dt = u solved exactly
    for u linear between samples. Holding u[i] over the step before it instead would put the
    response half a sample early, an error in the force of (dt / 2) df/dt."""
    e = -dt / (tau if abs(tau) > 1e-9 else 1e-9)  # a negative tau grows: meaningless, but defined
    # from expm1 and, for a lag far longer than the step, a series: a creep that never settles
    # has 1 - a tiny, and the differences below would keep only the digits that survive
    one_minus_a = -float(np.expm1(e))
    if abs(e) < 1e-3:
        b0 = -e * (0.5 + e * (1.0 / 6.0 + e * (1.0 / 24.0 + e / 120.0)))
    else:
        b0 = 1.0 - one_minus_a / -e
    return b0, one_minus_a - b0, 1.0 - one_minus_a


def first_order_lag(u: np.ndarray, dt: float, tau: float, floor: bool = False) -> np.ndarray:
    """y + tau dy/dt = u from rest, exact for u linear between samples (a linear filter).

    `floor`: y never goes below zero. Where it would, it stays at zero until the input alone
    lifts it: a part of the tissue driven to pull (the damping of a fast unloading) separates
    from the probe instead of storing tension, so a reloading starts from zero, not from a debt
    it must first climb out of."""
    b0, b1, a = lag_coefficients(dt, tau)
    if not floor:
        return linear_recursion(u, b0, b1, a)
    u = np.asarray(u, dtype=float)
    w = b0 * u
    if len(u) > 1 and b1:
        w[1:] += b1 * u[:-1]
    return floored_recursion(w, a)


def floored_recursion(w: np.ndarray, a: float) -> np.ndarray:
    """y[i] = max(a y[i-1] + w[i], 0) from rest. Between two stays at zero this is the linear
    recursion, so it is solved as one: the scan, then from the first sample it would go below
    zero, zero until the first positive input, and the scan again from there (a few restarts
    per trial, one per separation)."""
    w = np.asarray(w, dtype=float)
    y = linear_recursion(w, 1.0, 0.0, a)
    start = 0
    while True:
        below = np.flatnonzero(y[start:] < 0.0)
        if not len(below):
            return y
        j = start + int(below[0])
        lift = np.flatnonzero(w[j + 1:] > 0.0)
        if not len(lift):
            y[j:] = 0.0
            return y
        k = j + 1 + int(lift[0])
        y[j:k] = 0.0
        y[k:] = linear_recursion(w[k:], 1.0, 0.0, a)
        start = k


def linear_recursion(u: np.ndarray, b0: float, b1: float, a: float) -> np.ndarray:
    """y[i] = a y[i-1] + b0 u[i] + b1 u[i-1] from rest (u[-1] = 0), as `scipy.signal.lfilter`
    computes it, by a doubling scan: after the pass with stride k every y holds the inputs of
    the last 2k samples, so log2(n) vector passes replace the loop. Importing scipy.signal
    (which imports scipy.stats) would cost `rig analyze` 0.7 s before any work; this agrees
    with lfilter to ~1e-14 of the largest output."""
    u = np.asarray(u, dtype=float)
    y = b0 * u
    if len(u) > 1 and b1:
        y[1:] += b1 * u[:-1]
    k, ak = 1, float(a)
    # once a^k is below 1e-18 the older inputs no longer reach the digits of a float
    while k < len(y) and abs(ak) > 1e-18:
        y[k:] = y[k:] + ak * y[:-k]
        k, ak = 2 * k, ak * ak
    return y
