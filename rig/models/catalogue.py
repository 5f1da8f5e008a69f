"""The effects catalogue and the named models (names are part of the CLI contract)."""

from __future__ import annotations

import numpy as np

from rig.models.core import Effect, Model, Motion, Param, first_order_lag
from rig.models.fractional import fractional_maxwell
from rig.models.instrument import BOTTOM_EFFECTS, BOTTOM_SHAPES, SENSOR_EFFECTS, bottom_effect
from rig.models.viscoelastic import MODELS as VISCOELASTIC_EFFECTS
from rig.models.viscoelastic import viscoelastic_effect

INF = np.inf
FRICTION_ROUNDING = 0.02


def _linear_elastic(x, v, k_N_per_m):
    return k_N_per_m * x


def _poly_elastic(x, v, k1_N_per_m3, k2_N_per_m2, k3_N_per_m):
    return ((k1_N_per_m3 * x + k2_N_per_m2) * x + k3_N_per_m) * x


def _power_elastic(x, v, k_N_per_m_n, n):
    return k_N_per_m_n * np.power(x, n)


def _viscous(x, v, eta_N_s_per_m):
    return eta_N_s_per_m * v


def _hc_damping(x, v, b_N_s_per_m_n1, n):
    return b_N_s_per_m_n1 * np.power(x, n) * v


def _nonlinear_damping(x, v, tau2_N_s_per_m2):
    return tau2_N_s_per_m2 * x * v


def _relaxation(drive, dt, tau1_s):
    # floored: driven to pull (a fast unloading's damping), the tissue separates and stores no
    # tension for the next loading to climb out of
    return first_order_lag(drive, dt, tau1_s, floor=True)


def _relaxation2(x, v, dt, k_m_N_per_m, tau_m_s):
    # Maxwell element: f2 + tau df2/dt = k tau dx/dt, i.e. a lag of k tau v; floored as the
    # main lag: the branch separates rather than pull
    return first_order_lag(k_m_N_per_m * tau_m_s * v, dt, tau_m_s, floor=True)


def _speed_relaxation(m: Motion, relax_rate_per_speed_1_per_mm):
    # the lag's extra rate (1/s) grows with the trial's own loading speed (mm/s)
    return relax_rate_per_speed_1_per_mm * 1000.0 * m.loading_speed_m_s


def _fractional_relaxation(x, v, dt, k_f_N_per_m, tau_f_s, alpha_f):
    return fractional_maxwell(v, dt, k_f_N_per_m, tau_f_s, alpha_f)


def _contact_offset(x, v, x0_mm):
    x0 = x0_mm / 1000.0
    return np.maximum(x - x0, 0.0), np.where(x > x0, v, 0.0)


def _contact_point(x, v, x_c_m):
    return np.maximum(x - x_c_m, 0.0), v * _in_contact(x, x_c_m)


def _in_contact(x, x_c):
    """How far each sample's step has gone past the contact point, from 0 before it to 1 after:
    a rate term switched on at contact then moves with the contact point continuously, where a
    switch at whole samples would make the fit's cost a staircase in it that no solver can climb."""
    step = np.abs(np.diff(x, prepend=x[:1]))
    with np.errstate(divide="ignore", invalid="ignore"):
        part = np.where(step > 0, (x - x_c) / step, (x > x_c).astype(float))
    return np.clip(part, 0.0, 1.0)


def _compliance(x, v, force, dt, k_frame_N_per_m):
    # the slider's rate as the record gives it (smoothed) less the frame's give: as the frame
    # stiffens this is exactly the model without it
    return x - force / k_frame_N_per_m, v - np.gradient(force, dt) / k_frame_N_per_m


def _offset(m: Motion, force, offset_N):
    return np.full_like(force, offset_N)


def _drift(m: Motion, force, drift_N_per_s):
    return drift_N_per_s * (m.t_s - m.t_s[0])


def _friction(m: Motion, force, friction_N):
    # Coulomb friction with the sign rounded over 2 % of the record's own speed (the guide
    # does not chatter at rest)
    return friction_N * np.tanh(m.v_m_s / max(FRICTION_ROUNDING * m.speed_m_s, 1e-300))


def _delay(m: Motion, force, delay_s):
    return np.interp(m.t_s - delay_s, m.t_s, force, left=force[0])


DELAY_GRID = 40  # delays tried for a start, log-spaced from a sample to the loading time


def _delay_guess(m: Motion, misfit_N: np.ndarray, values: dict, model_N: np.ndarray) -> dict[str, float]:
    """The delay, from a sample to the loading time, that best explains the misfit as the model's
    force read late. A delay's cost has a minimum at every ramp corner's echo: from a default start
    a solver settles in the nearest (half the hidden 50 ms on an oocyte's relaxation, where a
    damping then mimicked the rest); the grid finds the deepest."""
    dt = float(np.median(np.diff(m.t_s)))
    span = float(m.t_s[-1] - m.t_s[0])
    loading = float(np.max(m.x_m)) / m.loading_speed_m_s if m.loading_speed_m_s > 0 else span
    top = max(min(loading, span), 2.0 * dt)
    best, cost0 = None, float(np.sum(misfit_N ** 2))
    for d in np.geomspace(dt, top, DELAY_GRID):
        cost = float(np.sum((misfit_N - (_delay(m, model_N, d) - model_N)) ** 2))
        if cost < cost0:
            best, cost0 = float(d), cost
    return {"delay_s": best} if best is not None else {}



def P(name: str, unit: str, init: float, lo: float = -INF, hi: float = INF, **kw) -> Param:
    """A catalogue parameter: init and bounds in the record's own units (see rig.analysis.fitting.scaling)."""
    return Param(name, unit, init, lo, hi, relative=True, **kw)


# Starting values and bounds are in units of the record's force F, travel L and loading time T
# (the first ramp's duration): k = 1 means F at depth L; tau1 = 0.5 means half the loading time.
CATALOGUE: dict[str, Effect] = {e.name: e for e in [
    Effect(name="linear_elastic", stage="drive", fn=_linear_elastic,
           params=(P("k_N_per_m", "N/m", 1.0, warn_negative=True),),
           equation="k x",
           signature="residual curved in the ramp (stiffening) and a step at the ramp-hold corner"),
    Effect(name="poly_elastic", stage="drive", fn=_poly_elastic,
           params=(P("k1_N_per_m3", "N/m^3", 0.5),
                   P("k2_N_per_m2", "N/m^2", 0.2),
                   P("k3_N_per_m", "N/m", 0.2)),
           equation="k1 x^3 + k2 x^2 + k3 x",
           signature="ramp residual growing with depth: the force stiffens faster than the model"),
    Effect(name="power_elastic", stage="drive", fn=_power_elastic,
           params=(P("k_N_per_m_n", "N/m^n", 1.0, 0.0),
                   P("n", "1", 1.5, 0.2, 6.0)),
           equation="k x^n (Hertz when n = 1.5)",
           signature="ramp residual shaped like a power of depth"),
    Effect(name="viscous", stage="drive", fn=_viscous,
           params=(P("eta_N_s_per_m", "N s/m", 0.1, warn_negative=True),),
           equation="eta dx/dt",
           signature="residual steps at ramp start and end proportional to speed"),
    Effect(name="hc_damping", stage="drive", fn=_hc_damping,
           params=(P("b_N_s_per_m_n1", "N s/m^(n+1)", 0.1, warn_negative=True),
                   P("n", "1", 1.5, 0.2, 6.0)),
           equation="b x^n dx/dt (Hunt-Crossley)",
           signature="ramp residual growing with depth and speed; drops at the ramp end"),
    Effect(name="nonlinear_damping", stage="drive", fn=_nonlinear_damping,
           params=(P("tau2_N_s_per_m2", "N s/m^2", 0.1, warn_negative=True),),
           equation="tau2 x dx/dt (paper)",
           signature="ramp residual proportional to depth x speed; a drop at the ramp end"),
    # fitted as its rate 1/tau1 (rig.analysis.fitting.scaling) down to 1e-8 (a lag 1e8 loading times
    # long, an integrator over any record): a creep that never settles is followed that way
    Effect(name="relaxation", stage="lag", fn=_relaxation,
           params=(P("tau1_s", "s", 0.5, 1e-4, 1e8),),
           equation="f + tau1 df/dt = drive (paper)",
           signature="hold residual decaying: the force relaxes but the model holds"),
    Effect(name="relaxation2", stage="branch", fn=_relaxation2,
           params=(P("k_m_N_per_m", "N/m", 0.5, 0.0),
                   P("tau_m_s", "s", 3.0, 1e-3, 1e5)),
           equation="Maxwell branch: f2 + tau_m df2/dt = k_m tau_m dx/dt, in parallel",
           signature="hold residual still decaying with a second, slower time constant"),
    # relaxation faster after faster loading (the paper's observation); seen only in a joint fit
    # over trials at several speeds, where one tau1 cannot serve them all
    Effect(name="speed_relaxation", stage="rate", fn=_speed_relaxation,
           params=(P("relax_rate_per_speed_1_per_mm", "1/mm", 0.5, 0.0, 1e4),),
           equation="the lag's rate 1/tau1 + c v, v the trial's loading speed",
           signature="hold residual decaying with opposite signs at different speeds: one tau1 cannot serve "
                     "every speed"),
    Effect(name="fractional_relaxation", stage="branch", fn=_fractional_relaxation,
           params=(P("k_f_N_per_m", "N/m", 0.5, 0.0),
                   P("tau_f_s", "s", 0.05, 1e-4, 1e4),
                   P("alpha_f", "1", 0.4, 0.05, 0.95)),
           equation="fractional Maxwell branch: modulus k_f E_a(-(t/tau_f)^a), a power "
                    "law t^-a after tau_f, in parallel",
           signature="hold residual decaying over many time scales at once: fast at first, then a long "
                     "power-law tail"),
    Effect(name="offset", stage="sensor", fn=_offset,
           params=(P("offset_N", "N", 0.0),),
           equation="constant force offset (tare error)",
           signature="residual constant, also before contact and after retraction",
           linear=True),
    Effect(name="drift", stage="sensor", fn=_drift,
           params=(P("drift_N_per_s", "N/s", 0.0),),
           equation="force drift linear in time",
           signature="residual growing linearly with time, also before contact",
           linear=True),
    Effect(name="contact_offset", stage="geometry", fn=_contact_offset,
           params=(P("x0_mm", "mm", 0.02, -0.3, 0.9),),
           equation="indentation = max(x - x0, 0)",
           signature="model force too early (or too late) at the start of the ramp: contact elsewhere "
                     "than assumed"),
    Effect(name="delay", stage="delay", fn=_delay,
           params=(P("delay_s", "s", 0.01, 0.0, 1.0),),
           equation="force measured late by a fixed delay",
           signature="residual proportional to the force's rate of change: peaks at ramp corners",
           guess=_delay_guess),
    Effect(name="compliance", stage="geometry", fn=_compliance,
           params=(P("k_frame_N_per_m", "N/m", 10.0, 1e-2, 1e6),),
           equation="indentation = x - f / k_frame",
           signature="ramp residual growing with force: the tissue sees less than the slider moved",
           needs_force=True),
    Effect(name="friction", stage="sensor", fn=_friction,
           params=(P("friction_N", "N", 0.0),),
           equation="Coulomb friction in the probe guide, sign of velocity",
           signature="residual steps at ramp start and end with the sign of velocity"),
]}

NAMED_MODELS: dict[str, list[str]] = {
    # elastic contact for the record's indenter, from a fitted contact point over a fitted baseline
    "hertz": ["elastic_contact", "contact_point", "offset"],
    "hooke": ["linear_elastic"],
    "maxwell": ["viscous", "relaxation"],
    "voigt": ["linear_elastic", "viscous"],
    "kelvin": ["linear_elastic", "viscous", "relaxation"],
    "hunt_crossley": ["power_elastic", "hc_damping"],
    "proposed": ["poly_elastic", "nonlinear_damping", "relaxation"],
}

# Viscoelastic contact for the record's indenter (rig.models.viscoelastic: Lee-Radok and Ting under
# a relaxation modulus), the contact point fitted as hertz's. Built when a model names it, from the
# indenter the elastic contact holds; not among the models --compare ranks.
VISCOELASTIC_MODELS: dict[str, list[str]] = {
    model: [effect, "contact_point", "offset"] for model, effect in VISCOELASTIC_EFFECTS.items()}


CONTACT = "elastic_contact"  # the effect an indenter brings (rig.models.contact)
NEEDS_INDENTER = ("needs the indenter's geometry, which the record does not name: give --indenter (e.g. "
                  "paraboloid:R=10um, sphere:R=2.5um, cone:half_angle=35deg, pyramid:half_angle=35deg,sides=4, "
                  "cylinder:R=1mm), or probe: in the rig config for the rig's own logs")


def contact_effect(indenter, poisson: float = 0.5) -> Effect:
    """Elastic contact of `indenter` (rig.models.contact.Indenter) with E in Pa: the force is
    E times the law's geometric factor at the indentation, with Poisson's ratio `poisson`."""
    from rig.models.contact import geometry_factor

    def _elastic_contact(x, v, E_Pa):
        return E_Pa * geometry_factor(indenter, x, poisson)

    # what a viscoelastic contact on the same record is built from (build_model)
    _elastic_contact.indenter, _elastic_contact.poisson = indenter, poisson

    law = {"paraboloid": "Hertz", "sphere": "Sneddon's exact sphere", "cone": "Sneddon's cone",
           "pyramid": "Bilodeau's pyramid", "cylinder": "Boussinesq's flat punch"}[indenter.kind]
    return Effect(name=CONTACT, stage="drive", fn=_elastic_contact,
                  params=(P("E_Pa", "Pa", 1.0, 0.0, warn_negative=True),),
                  equation=f"F = E g(d): {law}, {indenter.describe()}, Poisson {poisson:g}",
                  signature="ramp residual shaped like a power of depth other than the indenter's",
                  source=f"indenter {indenter.spec()}", linear=True)


# The contact point as a parameter of the record (AFM practice): anywhere from a travel before the
# first estimate to just short of the deepest point, which a threshold can miss by far. An indenter
# brings it; so does every record whose contact was only estimated from its force (an approach),
# one value per record (rig.analysis.fitting.fit.with_record_params). Not among the candidates `--explain`
# tries: for a record whose surface is known, contact_offset is that.
CONTACT_POINT = Effect(name="contact_point", stage="geometry", fn=_contact_point,
                       params=(P("x_c_m", "m", 0.0, -1.0, 0.99, per_record=True),),
                       equation="indentation = max(x - x_c, 0), x_c fitted from the first estimate",
                       signature="model force rises too early or too late: the contact point is elsewhere",
                       source="the record (its contact point)")


# The offset as the zero of a record that does not know it (its contact only estimated from the
# force): one value per record (rig.analysis.fitting.fit.with_record_params).
RECORD_ZERO = Effect(name="offset", stage="sensor", fn=_offset,
                     params=(P("offset_N", "N", 0.0, per_record=True),),
                     equation="constant force offset: the record's zero, one per record",
                     signature="residual constant, also before contact and after retraction",
                     linear=True, source="the record (its force at rest)")


def instrument_effects(model: Model, registry: dict[str, Effect]) -> dict[str, Effect]:
    """`registry` with the AFM's own effects (rig.models.instrument) when `model` holds an
    indenter's elastic contact: virtual deflection (tilt), the cantilever's drag and the bottom
    effect (bonded and not; for the shapes its series is for, built for the indenter's radius,
    which only the contact effect in the registry knows). Kept out of CATALOGUE: a cantilever's
    artefacts have no place among the tissue rig's candidates, and the catalogue's names are a
    contract."""
    law = registry[CONTACT].fn if CONTACT in registry else None
    if not (model.has(CONTACT) and hasattr(law, "indenter")):
        return registry
    extra = {n: e for n, e in SENSOR_EFFECTS.items() if n not in registry}
    if law.indenter.kind in BOTTOM_SHAPES:
        extra.update({n: bottom_effect(law.indenter, law.poisson, bonded)
                      for n, bonded in BOTTOM_EFFECTS.items() if n not in registry})
    return {**registry, **extra}


def named_models(registry: dict[str, Effect]) -> list[str]:
    """The named models every part of which `registry` holds (hertz only with an indenter)."""
    return [n for n, parts in NAMED_MODELS.items() if all(p in registry for p in parts)]


def build_model(name: str, extra: list[str] | None = None,
                registry: dict[str, Effect] | None = None) -> Model:
    """The model called `name` (a named model such as "hertz" or "proposed", one effect of the
    catalogue, or a model as the tool prints it, "hertz+drift"), with the effects in `extra`
    added in order. `registry` is the catalogue to draw from (default: `CATALOGUE`; a record's
    indenter adds its contact law and the viscoelastic and bottom effects that need it).

    Raises `RigError` for an unknown name (with the nearest one) or an effect that needs an
    indenter the record does not give.
    """
    from rig.errors import RigError, did_you_mean

    reg = registry or CATALOGUE
    models = {**NAMED_MODELS, **VISCOELASTIC_MODELS}
    # a model as the tool prints it (`--auto`'s final model, a fit's name): its first part, the
    # rest added, the record's own contact point among them
    head, *rest = [n.strip() for n in name.split("+")]
    if rest:
        name, extra = head, [*rest, *(extra or [])]
    if CONTACT_POINT.name not in reg:
        reg = {**reg, CONTACT_POINT.name: CONTACT_POINT}
    indenter_effects = (CONTACT, *VISCOELASTIC_EFFECTS.values())
    reg = {**{n: e for n, e in SENSOR_EFFECTS.items() if n not in reg}, **reg}  # --add tilt, drag anywhere
    if name not in models and name not in reg:
        if name in indenter_effects:
            raise RigError(f"'{name}' {NEEDS_INDENTER}")
        raise RigError(f"unknown model '{name}'{did_you_mean(name, [*models, *reg])}; "
                       "`rig models` lists them")
    names = models.get(name, [name])
    wanted = [n for n in [*names, *(extra or [])] if n in VISCOELASTIC_EFFECTS.values() and n not in reg]
    law = reg[CONTACT].fn if CONTACT in reg else None
    if wanted and hasattr(law, "indenter"):
        reg = {**reg, **{n: viscoelastic_effect(n, law.indenter, law.poisson) for n in wanted}}
    bottom = [n for n in [*names, *(extra or [])] if n in BOTTOM_EFFECTS and n not in reg]
    if bottom:
        if not hasattr(law, "indenter"):
            raise RigError(f"'{bottom[0]}' {NEEDS_INDENTER}")
        try:
            reg = {**reg, **{n: bottom_effect(law.indenter, law.poisson, BOTTOM_EFFECTS[n]) for n in bottom}}
        except ValueError as exc:
            raise RigError(f"'{bottom[0]}': {exc}") from None
    if any(n in indenter_effects and n not in reg for n in names):
        raise RigError(f"the {name} model {NEEDS_INDENTER}")
    for n in extra or []:
        if n in indenter_effects and n not in reg:
            raise RigError(f"'{n}' {NEEDS_INDENTER}")
        if n not in reg:
            raise RigError(f"unknown effect '{n}'{did_you_mean(n, reg)}; `rig models` lists the catalogue")
    model = Model([reg[n] for n in names], name=name)
    extra = [n for i, n in enumerate(extra or []) if n not in names and n not in (extra or [])[:i]]
    for n in extra:
        model = model + reg[n]
    if extra:
        model.name = name + "".join(f"+{n}" for n in extra)
    return model


def catalogue_json(effects: dict[str, Effect]) -> dict:
    """The effects (with their parameters) and the named models, as `rig models --json` gives them."""
    return {"effects": {n: {"stage": e.stage, "equation": e.equation, "signature": e.signature,
                            "source": e.source,
                            "params": [{"name": p.name, "unit": p.unit, "init": p.init, "lo": p.lo, "hi": p.hi,
                                        "in_record_units": p.relative} for p in e.params]}
                        for n, e in effects.items()},
            "models": NAMED_MODELS}


def format_catalogue(effects: dict[str, Effect]) -> str:
    lines = ["effects (stage: equation; parameters; where its absence shows)"]
    for n, e in effects.items():
        params = ", ".join(f"{p.name} [{p.unit}]" for p in e.params)
        src = "" if e.source == "catalogue" else f"  ({e.source})"
        lines.append(f"  {n:<18} {e.stage:<8} {e.equation}{src}\n  {'':<18} {'':<8} {params}\n"
                     f"  {'':<18} {'':<8} missing: {e.signature}")
    lines.append("\n(catalogue starting values and bounds are in each record's own units: its peak force, "
                 "its travel and its loading time, combined as the parameter's unit says)")
    lines.append("\nnamed models")
    lines += [f"  {n:<14} {' + '.join(parts)}" for n, parts in NAMED_MODELS.items()]
    if CONTACT not in effects:
        lines.append(f"  (hertz: E in Pa for the indenter; it {NEEDS_INDENTER})")
    lines.append("\nthe AFM's own (rig.models.instrument; candidates of --explain with an indenter's contact)")
    for e in SENSOR_EFFECTS.values():
        lines.append(f"  {e.name:<18} {e.stage:<8} {e.equation}")
    lines.append(f"  {'bottom_effect':<18} {'drive':<8} the contact force x Dimitriadis et al. 2002's series "
                 "in sqrt(R d)/h (paraboloid, sphere; bottom_effect_free: not bonded)")
    lines.append("\nviscoelastic contact for the indenter (Lee-Radok and Ting; rig.models.viscoelastic)")
    lines += [f"  {n:<14} {' + '.join(parts)}" for n, parts in VISCOELASTIC_MODELS.items()]
    return "\n".join(lines)
