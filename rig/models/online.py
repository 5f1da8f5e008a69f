"""A fitted model advanced one tick at a time from the measured position: the paper's force
from motion alone, in the loop.

Constant work per tick: a one-pole filter for the velocity, one per lag, a state per
branch; the drive terms are plain arithmetic. The chain is `Model.predict`'s, so the
same model evaluated offline (vectorised, `offline_force`) on the logged positions gives
the same numbers: that is how `rig replay` checks the online evaluation.

Velocity: the backward difference of the position, smoothed by a causal one-pole filter
(`velocity_tau_s`); the loop cannot look ahead as the offline smoother does.
"""

from __future__ import annotations

import math

import numpy as np

from rig.errors import RigError
from rig.models.core import Model, Motion, lag_coefficients, linear_recursion

# Effects with a causal one-step form. Compliance is implicit in the force, friction's
# rounding scales with the whole record's speed and the delay looks back by a fraction
# of a sample: they stay offline.
ONLINE_EFFECTS = ("linear_elastic", "poly_elastic", "power_elastic", "viscous", "hc_damping",
                  "nonlinear_damping", "relaxation", "relaxation2", "contact_offset", "offset", "drift")
VELOCITY_TAU_S = 0.05


def check_online(model: Model) -> None:
    """RigError unless every effect of `model` has a one-step form the loop can run."""
    bad = [e.name for e in model.effects if e.name not in ONLINE_EFFECTS]
    if bad:
        raise RigError(f"model '{model.name}': {', '.join(bad)} cannot run in the loop (no one-step form); "
                       f"online effects: {', '.join(ONLINE_EFFECTS)}")


class OnlineModel:
    """A saved model run in the loop: one step per tick from the position, with a causal velocity, giving
    the force the model expects now (the loop's model force; the force itself where there is no load
    cell)."""

    def __init__(self, model: Model, values: dict[str, float], dt_s: float,
                 velocity_tau_s: float = VELOCITY_TAU_S) -> None:
        check_online(model)
        self.model = model
        self.dt = dt_s
        v = dict(values)
        names = set(model.effect_names)
        self._av = math.exp(-dt_s / velocity_tau_s)
        self._k = v.get("k_N_per_m", 0.0) if "linear_elastic" in names else 0.0
        self._poly = ((v["k1_N_per_m3"], v["k2_N_per_m2"], v["k3_N_per_m"]) if "poly_elastic" in names
                      else None)
        self._power = (v["k_N_per_m_n"], v["n"]) if "power_elastic" in names else None
        self._eta = v["eta_N_s_per_m"] if "viscous" in names else 0.0
        self._hc = (v["b_N_s_per_m_n1"], v["n"]) if "hc_damping" in names else None
        self._tau2 = v["tau2_N_s_per_m2"] if "nonlinear_damping" in names else 0.0
        # each lag as Model.predict steps it (exact for its input linear between ticks)
        self._lag1 = lag_coefficients(dt_s, v["tau1_s"]) if "relaxation" in names else None
        if "relaxation2" in names:
            self._km_tau = v["k_m_N_per_m"] * v["tau_m_s"]
            self._lag2 = lag_coefficients(dt_s, v["tau_m_s"])
        else:
            self._lag2 = None
        self._x0 = v["x0_mm"] / 1000.0 if "contact_offset" in names else None
        self._offset = v.get("offset_N", 0.0) if "offset" in names else 0.0
        self._drift = v.get("drift_N_per_s", 0.0) if "drift" in names else 0.0
        self.reset()

    def reset(self) -> None:
        self._x_prev: float | None = None
        self._v = 0.0
        self._f1 = 0.0
        self._f2 = 0.0
        self._g_prev = 0.0  # the lags' inputs at the last tick
        self._u_prev = 0.0
        self._t0: float | None = None

    def step(self, t_s: float, x_m: float) -> float:
        """The model's force (N) at this tick, from the indentation `x_m` measured now."""
        if self._x_prev is None:
            self._x_prev, self._t0 = x_m, t_s
        raw = (x_m - self._x_prev) / self.dt
        self._x_prev = x_m
        a = self._av
        self._v = a * self._v + (1.0 - a) * raw
        x, v = x_m, self._v
        if self._x0 is not None:
            x, v = (x - self._x0, v) if x > self._x0 else (0.0, 0.0)
        if x > 0.0:
            g = self._k * x + self._eta * v + self._tau2 * x * v
            if self._poly is not None:
                k1, k2, k3 = self._poly
                g += ((k1 * x + k2) * x + k3) * x
            if self._power is not None:
                g += self._power[0] * x ** self._power[1]
            if self._hc is not None:
                g += self._hc[0] * x ** self._hc[1] * v
        else:
            v = 0.0
            g = 0.0
        if self._lag1 is not None:
            b0, b1, a = self._lag1
            self._f1 = max(a * self._f1 + b0 * g + b1 * self._g_prev, 0.0)  # floored as Model.predict
            self._g_prev = g
            f = self._f1
        else:
            f = g
        if self._lag2 is not None:
            # as Model.predict: a lag driven below zero holds no tension against the branch
            f = f if f > 0.0 else 0.0
            b0, b1, a = self._lag2
            u = self._km_tau * v
            self._f2 = max(a * self._f2 + b0 * u + b1 * self._u_prev, 0.0)
            self._u_prev = u
            f += self._f2
        f = f if f > 0.0 else 0.0
        return f + self._offset + self._drift * (t_s - self._t0)


def causal_velocity(x_m: np.ndarray, dt_s: float, velocity_tau_s: float = VELOCITY_TAU_S) -> np.ndarray:
    """The loop's velocity, vectorised: backward difference, then the same one-pole filter."""
    raw = np.diff(x_m, prepend=x_m[:1]) / dt_s
    a = math.exp(-dt_s / velocity_tau_s)
    return linear_recursion(raw, 1.0 - a, 0.0, a)


def offline_force(model: Model, values: dict[str, float], t_s: np.ndarray, x_m: np.ndarray,
                  dt_s: float, velocity_tau_s: float = VELOCITY_TAU_S) -> np.ndarray:
    """The same model on logged positions, by `Model.predict` (vectorised, independent code)."""
    check_online(model)
    v = causal_velocity(x_m, dt_s, velocity_tau_s)
    return model.predict(values, Motion(np.asarray(t_s, float), np.asarray(x_m, float), v, dt_s))
