"""Force models built from effects, lmfit style: plain functions, parameters with units and
bounds, composition with `+`.

A model turns a trial's motion into a predicted force through a fixed chain, and every
effect plugs into one stage of it:

    geometry   indentation seen by the tissue      (contact_offset, compliance)
    drive      terms summed into the drive g        (elastic and damping terms)
    lag        f + tau df/dt = g                    (relaxation; else f = g)
    branch     parallel branches added after it     (relaxation2)
    clamp      the tissue cannot pull: f >= 0
    sensor     what the load cell adds              (offset, drift, friction)
    delay      the reading arrives late             (delay)

Everything is vectorised: a first-order lag is a linear filter (`scipy.signal.lfilter`),
never a general ODE solver.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.linalg import solve_banded
from scipy.signal import lfilter

FRAME_RTOL = 1e-10  # of the force's own peak: far below any sensor's resolution
FRAME_MAX_ITER = 60


class NotConverged(RuntimeWarning):
    pass


STAGES = ("geometry", "drive", "lag", "branch", "sensor", "delay")


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
        for stage in ("lag", "delay"):
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
        for e in compliance:  # the frame spring: indentation = x - f/k, solved for f
            tissue = self._through_frame(e, x, v, m, by_stage, args, tissue)
        force = tissue
        for e in by_stage["sensor"]:
            force = force + e.fn(m, force, **args(e))
        for e in by_stage["delay"]:
            force = e.fn(m, force, **args(e))
        return force

    def _through_frame(self, e: Effect, x, v, m: Motion, by_stage, args, f: np.ndarray) -> np.ndarray:
        """The tissue force f with f = tissue(indentation given f), by Newton's method on the
        whole trajectory.

        Substituting the last force (a fixed point) diverges once the frame is softer than the
        tissue: each pass over-corrects the last. Newton's step needs the chain's Jacobian,
        which is cheap here: the drive acts sample by sample (its slopes in x and v, by
        differences), velocity is a three-point difference, and a first-order lag has a
        two-term inverse, so the lag's inverse times the Jacobian is tridiagonal
        (`scipy.linalg.solve_banded`). What the step leaves out (a parallel branch, the
        no-pull clamp) only slows it down: convergence is checked on the equation itself."""
        dt = m.dt_s
        n = len(x)
        drives = by_stage["drive"]
        lags = by_stage["lag"]
        a = 0.0
        if lags:  # the lag's pole, from its response to an impulse
            y = lags[0].fn(np.array([1.0, 0.0]), dt, **args(lags[0]))
            a = float(y[1] / y[0]) if y[0] else 0.0

        def drive(xc, vc):
            out = np.zeros_like(xc)
            for d in drives:
                out = out + d.fn(xc, vc, **args(d))
            return out

        def residual(f):
            xc, vc = e.fn(x, v, f, dt, **args(e))
            return f - self._tissue(xc, vc, m, by_stage, args), xc, vc

        r, xc, vc = residual(f)
        x_scale = max(float(np.max(np.abs(x))), 1e-300)
        v_scale = max(float(np.max(np.abs(v))), x_scale / max(m.t_s[-1] - m.t_s[0], dt))
        norm = float(np.max(np.abs(r)))
        for _ in range(FRAME_MAX_ITER):
            scale = max(float(np.max(np.abs(f))), 1e-300)
            if norm <= FRAME_RTOL * scale:
                return f - r
            # slopes of the drive (zero out of contact) and of the frame's give (1/k)
            hx, hv = 1e-6 * x_scale, 1e-6 * v_scale
            d0 = drive(np.maximum(xc, 0.0), vc)
            contact = xc > 0
            alpha = np.where(contact, (drive(np.maximum(xc, 0.0) + hx, vc) - d0) / hx, 0.0)
            beta = np.where(contact, (drive(np.maximum(xc, 0.0), vc + hv) - d0) / hv, 0.0)
            hf = 1e-6 * scale
            give = -(e.fn(x, v, f + hf, dt, **args(e))[0] - xc) / hf
            # (L^-1 + (diag(alpha) + diag(beta) G) diag(give)) step = -L^-1 r, L the lag
            g = 1.0 / (1.0 - a)
            diag = g + alpha * give
            lower = np.full(n, -a * g)  # lower[i] multiplies step[i-1] in row i
            upper = np.zeros(n)  # upper[i] multiplies step[i+1] in row i
            c = 0.5 / dt
            # three-point velocity inside, one-sided at the ends (as np.gradient)
            upper[1:-1] += beta[1:-1] * c * give[2:]
            lower[1:-1] += -beta[1:-1] * c * give[:-2]
            diag[0] += -beta[0] / dt * give[0]
            upper[0] += beta[0] / dt * give[1]
            diag[-1] += beta[-1] / dt * give[-1]
            lower[-1] += -beta[-1] / dt * give[-2]
            ab = np.zeros((3, n))
            ab[0, 1:] = upper[:-1]
            ab[1] = diag
            ab[2, :-1] = lower[1:]
            rhs = -(g * r - a * g * np.concatenate(([0.0], r[:-1])))
            try:
                step = solve_banded((1, 1), ab, rhs)
            except (np.linalg.LinAlgError, ValueError):
                step = -r
            if not np.all(np.isfinite(step)):
                step = -r
            for _ in range(30):  # backtrack until the equation's error falls
                r_new, xc_new, vc_new = residual(f + step)
                norm_new = float(np.max(np.abs(r_new)))
                if np.isfinite(norm_new) and norm_new < norm:
                    break
                step = 0.5 * step
            else:
                break
            f, r, xc, vc, norm = f + step, r_new, xc_new, vc_new, norm_new
        warnings.warn(f"frame compliance: the force did not converge (residual {norm:.3g} N)",
                      NotConverged, stacklevel=3)
        return f - r

    def _tissue(self, x, v, m: Motion, by_stage, args) -> np.ndarray:
        contact = x > 0
        xc = np.where(contact, x, 0.0)
        vc = np.where(contact, v, 0.0)
        drive = np.zeros_like(x)
        for e in by_stage["drive"]:
            drive = drive + e.fn(xc, vc, **args(e))
        drive = np.where(contact, drive, 0.0)
        f = drive
        for e in by_stage["lag"]:
            f = e.fn(drive, m.dt_s, **args(e))
        for e in by_stage["branch"]:
            f = f + e.fn(xc, vc, m.dt_s, **args(e))
        return np.maximum(f, 0.0)  # the tissue cannot pull on the probe


def first_order_lag(u: np.ndarray, dt: float, tau: float) -> np.ndarray:
    """y + tau dy/dt = u, exact for u held over each sample (a linear filter)."""
    e = -dt / (tau if abs(tau) > 1e-9 else 1e-9)  # a negative tau grows: meaningless, but defined
    # 1 - a from expm1: for a lag far longer than the record (a creep that never settles) 1 - a
    # is tiny and would otherwise keep only the digits that survive the subtraction
    return lfilter([-float(np.expm1(e))], [1.0, -float(np.exp(e))], u)
