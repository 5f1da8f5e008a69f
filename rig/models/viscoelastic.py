"""Viscoelastic contact: a relaxation modulus E(t) under the indenter's geometric function, so a
relaxing force curve reads as material parameters in Pa and s.

Elastic contact is F = E g(d) (`rig.models.contact`: paraboloid g = 4/3 sqrt(R) d^1.5 / (1 - nu^2),
flat punch 2 R d / (1 - nu^2), cone, pyramid, Sneddon's sphere). With a relaxation modulus E(t) the
force is Lee and Radok's hereditary integral while the contact grows and Ting's construction while
it shrinks (`rig.models.ting`, which holds the equations and the references). Moduli, SI units:

- standard linear solid and Prony series (one to three terms; Pa, s):
      E(t) = E_inf + sum_i E_i exp(-t / tau_i)
  E_inf_Pa the relaxed modulus, E_i_Pa the parts that relax with time constants tau_i_s; the
  instantaneous modulus is E_inf + sum E_i. Each term is convolved exactly (one recursion).
- power law (Pa, dimensionless), the form cell mechanics reports (e.g. Efremov et al. 2017;
  Hecht et al., Soft Matter 11:4584, 2015):
      E(t) = E0 (t / t0)^-beta,   t0 = 1 s (fixed: E0_Pa is the modulus one second after a step)
  beta the fluidity (0 elastic, 1 fluid), bounded to [0, 0.99].

The power law is summed as exponentials from t^-beta = 1/Gamma(beta) int_0^inf r^(beta-1)
exp(-r t) dr with r = e^y: the trapezoidal rule in y, step `POWER_STEP`, converges geometrically
(the integrand is analytic in the strip |Im y| < pi/2: error ~ exp(-pi^2 / step)), so the sum
follows t^-beta to ~1e-7 wherever its nodes cover the rates. Nodes span 1e-3 / duration to
50 / dt; the infinite rule's two tails beyond are summed in closed form (geometric series), each
as one mode: the slow tail keeps its weight and mean rate (what it misses, ~(r t)^2, is below
1e-6 over the record), the fast tail its weight over rate, which is all a mode faster than 50
per sample contributes (its force within the sample it acts in). Measured against the exact
interval integrals of t^-beta: tests/test_viscoelastic.py.
"""

from __future__ import annotations

import math

import numpy as np

from rig.models.contact import Indenter, geometry_factor
from rig.models.core import Effect, Param
from rig.models.ting import hereditary_force

T0_S = 1.0  # reference time of the power law: E0 is E(t0)
POWER_STEP = 0.5  # trapezoidal step in log-rate (error ~ exp(-pi^2 / step) ~ 3e-9)
SLOW_EDGE_PER_DURATION = 1e-3
FAST_EDGE_PER_DT = 50.0
BETA_MAX = 0.99

KINDS = {"sls": 1, "prony2": 2, "prony3": 3}  # terms of the Prony series
MODELS = {"ting_sls": "viscoelastic_sls", "ting_prony2": "viscoelastic_prony2",
          "ting_prony3": "viscoelastic_prony3", "ting_power": "viscoelastic_power"}

Modulus = tuple[float, np.ndarray, np.ndarray]  # constant (Pa), rates (1/s), weights (Pa)


def prony_modulus(E_inf_Pa: float, terms: list[tuple[float, float]]) -> Modulus:
    """E(t) = E_inf + sum E_i exp(-t / tau_i) from (E_i in Pa, tau_i in s) pairs."""
    E = np.array([e for e, _ in terms], dtype=float)
    tau = np.array([t for _, t in terms], dtype=float)
    return float(E_inf_Pa), 1.0 / np.maximum(tau, 1e-300), E


def power_law_modulus(E0_Pa: float, beta: float, duration_s: float, dt_s: float,
                      step: float = POWER_STEP) -> Modulus:
    """E0 (t / t0)^-beta as a constant plus exponentials, accurate over (0, duration] in the
    interval integrals of samples dt apart (see the module's docstring)."""
    if beta <= 1e-9:
        return float(E0_Pa), np.zeros(0), np.zeros(0)
    beta = min(float(beta), BETA_MAX)
    y_lo = math.log(SLOW_EDGE_PER_DURATION / max(duration_s, dt_s))
    y_hi = math.log(FAST_EDGE_PER_DT / dt_s)
    y = y_lo + step * np.arange(math.ceil((y_hi - y_lo) / step) + 1)
    scale = E0_Pa * T0_S ** beta * step / math.gamma(beta)
    weights = scale * np.exp(beta * y)
    # the infinite rule's nodes below y[0] and above y[-1]: geometric series in closed form
    slow_w = scale * math.exp(beta * y[0]) * math.exp(-beta * step) / -math.expm1(-beta * step)
    slow_rate_sum = (scale * math.exp((beta + 1.0) * y[0]) * math.exp(-(beta + 1.0) * step)
                     / -math.expm1(-(beta + 1.0) * step))
    fast_over_rate = (scale * math.exp((beta - 1.0) * y[-1]) * math.exp(-(1.0 - beta) * step)
                      / -math.expm1(-(1.0 - beta) * step))
    fast_rate = math.exp(y[-1] + step)
    rates = np.concatenate([[slow_rate_sum / slow_w], np.exp(y), [fast_rate]])
    return 0.0, rates, np.concatenate([[slow_w], weights, [fast_over_rate * fast_rate]])


def modulus_at(modulus: Modulus, t_s: np.ndarray) -> np.ndarray:
    """E(t) of a modulus given as constant plus exponentials (Pa)."""
    c, r, w = modulus
    return c + np.exp(-np.outer(np.asarray(t_s, dtype=float), r)) @ w


def _param(name: str, unit: str, init: float, lo: float, hi: float, doc: str) -> Param:
    # in the record's own units (force F, travel L, loading time T), as the catalogue's are
    return Param(name, unit, init, lo, hi, relative=True, doc=doc, warn_negative=unit == "Pa")


def _prony_params(terms: int) -> tuple[Param, ...]:
    # starting time constants spread over the decades a ramp-hold shows
    taus = {1: (0.5,), 2: (0.2, 5.0), 3: (0.1, 1.0, 10.0)}[terms]
    out = [_param("E_inf_Pa", "Pa", 0.5, 0.0, np.inf, "relaxed (long-time) Young's modulus")]
    for i, tau in enumerate(taus, start=1):
        out.append(_param(f"E{i}_Pa", "Pa", 0.5 / terms, 0.0, np.inf, f"modulus relaxing with tau{i}"))
        out.append(_param(f"tau{i}_s", "s", tau, 1e-4, 1e5, f"relaxation time {i}"))
    return tuple(out)


def viscoelastic_effect(name: str, indenter: Indenter, poisson: float = 0.5) -> Effect:
    """The branch force of `indenter` pressed into a half-space of the relaxation modulus `name`
    names (viscoelastic_sls, viscoelastic_prony2, viscoelastic_prony3, viscoelastic_power)."""
    kind = name.removeprefix("viscoelastic_")
    where = f"{indenter.describe()}, Poisson {poisson:g}"
    source = f"indenter {indenter.spec()}"
    signature = "hold residual decaying, or approach and retract split apart: the contact relaxes"

    def g_of(d: np.ndarray) -> np.ndarray:
        return geometry_factor(indenter, d, poisson)

    if kind == "power":
        def _power(x, v, dt, E0_Pa, beta):
            mod = power_law_modulus(E0_Pa, beta, len(x) * dt, dt)
            return hereditary_force(x, g_of(x), dt, *mod, exponent=indenter.exponent)

        params = (_param("E0_Pa", "Pa", 1.0, 0.0, np.inf, "modulus at t0 = 1 s after a step"),
                  _param("beta", "1", 0.2, 0.0, BETA_MAX, "power-law exponent (fluidity)"))
        return Effect(name=name, stage="branch", params=params, fn=_power,
                      equation=f"Lee-Radok/Ting contact, E(t) = E0 (t / 1 s)^-beta: {where}",
                      signature=signature, source=source)
    terms = KINDS[kind]

    def _prony(x, v, dt, E_inf_Pa, **kw):
        mod = prony_modulus(E_inf_Pa, [(kw[f"E{i}_Pa"], kw[f"tau{i}_s"]) for i in range(1, terms + 1)])
        return hereditary_force(x, g_of(x), dt, *mod, exponent=indenter.exponent)

    series = " + ".join(f"E{i} exp(-t/tau{i})" for i in range(1, terms + 1))
    return Effect(name=name, stage="branch", params=_prony_params(terms), fn=_prony,
                  equation=f"Lee-Radok/Ting contact, E(t) = E_inf + {series}: {where}", signature=signature,
                  source=source)


def viscoelastic_effects(indenter: Indenter, poisson: float = 0.5) -> dict[str, Effect]:
    """Every viscoelastic contact effect for the indenter, by name."""
    return {n: viscoelastic_effect(n, indenter, poisson) for n in MODELS.values()}
