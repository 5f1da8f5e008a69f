"""The AFM instrument's own effects: what the cantilever and the sample's support add to a force
curve that the contact law does not describe. They are offered to `--explain` only for a model
with an indenter's elastic contact (rig.models.catalogue.instrument_effects), not put in the
catalogue the tissue rig's records are screened with.

    effect        stage     equation              what

    tilt          sensor    F += tilt x           virtual deflection: the optical lever reads a
                                                  deflection linear in the piezo's travel x, in
                                                  and out of contact (optical interference, a
                                                  laser spot sliding on the lever)
    drag          sensor    F += b dx/dt          hydrodynamic drag on the cantilever in liquid,
                                                  in and out of contact: approach and retract
                                                  baselines split apart by 2 b v
    bottom_effect drive     F = F_contact(d) B(chi)   a sample of finite thickness h on a hard
    (_free)                 chi = sqrt(R d) / h       substrate reads stiffer as d grows
    adhesion      sensor    F += F_off d / L          the tip stuck to the sample on the way out:
                            (retract, -L < d < 0)     past the contact point a neck pulls on it,
                                                      linearly to the pull-off force F_off at the
                                                      pull-off distance L, where it lets go

Adhesion acts past the contact point, so it shares the record's contact point x_c_m with the
contact (d = x - x_c: the indentation before the geometry clamps it at nought). Its neck is
linear in the tip's travel, as a stretched tether or a meniscus pulls; the pull-off force is the
figure DMT and JKR theory relate to the work of adhesion w (F_off = 2 pi R w for DMT, 3/2 pi R w
for JKR), so the report gives F_off and leaves the choice of theory to the reader. It acts on
the retract only (moving out: the smoothed velocity below nought): an approach's snap-in is a
few samples where the tip jumps, not a law. The let-go is spread over the travel to a neighbouring
sample (linearly), so the force is continuous in L and a fit can move it between samples.

The bottom effect, Dimitriadis et al. 2002 (Biophys. J. 82:2798: their general series), for a paraboloid
(or a sphere in Hertz's approximation) of radius R on a layer of Poisson's ratio nu:

    B(chi) = 1 - 2 a0/pi chi + 4 a0^2/pi^2 chi^2 - 8/pi^3 (a0^3 + 4 pi^2 b0/15) chi^3
               + 16 a0/pi^4 (a0^3 + 3 pi^2 b0/5) chi^4
    bonded to the substrate:  a0 = -(1.2876 - 1.4678 nu + 1.3442 nu^2)/(1 - nu)
                              b0 =  (0.6387 - 1.0277 nu + 1.5164 nu^2)/(1 - nu)
    lying on it (slipping):   a0 = -0.347 (3 - 2 nu)/(1 - nu)
                              b0 =  0.056 (5 - 2 nu)/(1 - nu)

At nu = 0.5 these give the paper's printed brackets 1 + 1.133 chi + 1.283 chi^2 + 0.769 chi^3
+ c4 chi^4 (bonded) and 1 + 0.884 chi + 0.781 chi^2 + 0.386 chi^3 + 0.0048 chi^4 (not bonded).
The general form gives c4 = -0.0975 for the bonded layer where the paper's printed bracket (and
sim_device/afm_map.py, which copies it) has +0.0975. The general form is used: it holds for every
nu, and it reproduces the seven other printed coefficients, the not-bonded c4 among them (0.0048,
a small difference of two large terms, the kind a sign slip would not survive); the printed
bonded c4 was not checked against the paper's own pages here. The two differ by 0.195 chi^4,
under 1 % of the bracket for chi < 0.5 and 4 % at chi = 1 (tests/test_instrument_effects.py).

The correction multiplies the contact force. It is a drive term, E g(d) (B - 1) beside the
contact's E g(d) (sharing E_Pa), not a geometry one that stretches the depth: the drive sees
the indentation after the record's contact point, where a geometry effect would run before it
(the record's contact point is appended last when the fit sets a record's own parameters,
rig.analysis.fitting.fit.with_record_params) and so measure chi from the wrong zero. The term is exact
for Hertz's paraboloid and for Sneddon's sphere alike (the series is the paraboloid's: for the
sphere it holds while d << R, as Dimitriadis's derivation does). A cone or pyramid needs
Gavara and Chadwick's (2012) correction (a different series, in d tan(alpha) / h) and a flat
punch its own: those are refused rather than given the paraboloid's series.
"""

from __future__ import annotations

import math

import numpy as np

from rig.models.contact import Indenter, geometry_factor
from rig.models.core import Effect, Motion, Param

TILT = "tilt"
DRAG = "drag"
ADHESION = "adhesion"
BOTTOM = "bottom_effect"  # the layer bonded to its substrate (cells, gels cast on glass)
BOTTOM_FREE = "bottom_effect_free"  # the layer lying on it, free to slip
BOTTOM_EFFECTS = {BOTTOM: True, BOTTOM_FREE: False}
BOTTOM_SHAPES = ("paraboloid", "sphere")
REFERENCE = "Dimitriadis et al. 2002, Biophys. J. 82:2798"


def dimitriadis_coefficients(nu: float, bonded: bool) -> tuple[float, float, float, float]:
    """(c1, c2, c3, c4) of B(chi) = 1 + c1 chi + c2 chi^2 + c3 chi^3 + c4 chi^4 (module docstring)."""
    if bonded:
        a0 = -(1.2876 - 1.4678 * nu + 1.3442 * nu * nu) / (1.0 - nu)
        b0 = (0.6387 - 1.0277 * nu + 1.5164 * nu * nu) / (1.0 - nu)
    else:
        a0 = -0.347 * (3.0 - 2.0 * nu) / (1.0 - nu)
        b0 = 0.056 * (5.0 - 2.0 * nu) / (1.0 - nu)
    pi = math.pi
    return (-2.0 * a0 / pi, 4.0 * a0 * a0 / pi ** 2, -8.0 / pi ** 3 * (a0 ** 3 + 4.0 * pi * pi * b0 / 15.0),
            16.0 * a0 / pi ** 4 * (a0 ** 3 + 3.0 * pi * pi * b0 / 5.0))


def bottom_factor(chi: np.ndarray, coeffs: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """B(chi) and dB/dchi."""
    c1, c2, c3, c4 = coeffs
    b = 1.0 + chi * (c1 + chi * (c2 + chi * (c3 + chi * c4)))
    db = c1 + chi * (2.0 * c2 + chi * (3.0 * c3 + chi * 4.0 * c4))
    return b, db


def bottom_effect(indenter: Indenter, poisson: float = 0.5, bonded: bool = True,
                  thickness_m: float | None = None) -> Effect:
    """The bottom effect for `indenter`'s elastic contact, thickness h_m fitted, or the
    specimen's known `thickness_m` (the log's header: `rig run --thickness-mm`): the drive term
    E g(d) (B(chi) - 1) beside the contact's E g(d), sharing its E_Pa. Raises ValueError for a
    shape the series is not for."""
    if indenter.kind not in BOTTOM_SHAPES:
        raise ValueError(
            f"the bottom effect is implemented for a paraboloid or sphere only ({REFERENCE}); a "
            f"{indenter.kind} needs its own correction (Gavara and Chadwick 2012 for a cone), not this series")
    R = float(indenter.R_m)
    coeffs = dimitriadis_coefficients(poisson, bonded)

    def _bottom(x, v, E_Pa, h_m):
        d = np.maximum(x, 0.0)
        h = max(abs(h_m), 1e-300)  # a negative thickness is the positive one: the bracket needs h > 0
        b, _ = bottom_factor(np.sqrt(R * d) / h, coeffs)
        return E_Pa * geometry_factor(indenter, d, poisson) * (b - 1.0)

    how = "bonded to" if bonded else "lying on"
    c = ", ".join(f"{x:.4g}" for x in coeffs)
    law = "F = F_contact(d) (1 + c1 chi + c2 chi^2 + c3 chi^3 + c4 chi^4), chi = sqrt(R d)/h"
    signature = ("ramp residual growing faster than the contact law with depth: the sample reads stiffer "
                 "the deeper the tip goes (a thin sample on a hard support); E fitted without it is too high")
    if thickness_m is not None:
        h_known = float(thickness_m)

        def _bottom_known(x, v, E_Pa):
            return _bottom(x, v, E_Pa, h_known)

        return Effect(
            name=BOTTOM if bonded else BOTTOM_FREE, stage="drive", fn=_bottom_known,
            params=(Param("E_Pa", "Pa", 1.0, 0.0, relative=True, warn_negative=True),),
            equation=(f"{law}: a layer of thickness h = {h_known * 1e3:g} mm (the specimen's, from the "
                      f"log) {how} a hard substrate ({REFERENCE}; nu {poisson:g}: c = {c})"),
            signature=signature, source=f"indenter {indenter.spec()}, thickness {h_known * 1e3:g} mm")
    return Effect(
        name=BOTTOM if bonded else BOTTOM_FREE, stage="drive", fn=_bottom,
        params=(Param("E_Pa", "Pa", 1.0, 0.0, relative=True, warn_negative=True),
                Param("h_m", "m", 3.0, 0.02, 1e4, relative=True, warn_negative=True,
                      doc="the sample's thickness over the hard substrate")),
        equation=f"{law}: a layer of thickness h {how} a hard substrate ({REFERENCE}; nu {poisson:g}: c = {c})",
        signature=signature, source=f"indenter {indenter.spec()}")


def _tilt(m: Motion, force, tilt_N_per_m):
    return tilt_N_per_m * m.x_m


def _drag(m: Motion, force, drag_N_s_per_m):
    return drag_N_s_per_m * m.v_m_s


TILT_EFFECT = Effect(
    name=TILT, stage="sensor", fn=_tilt, params=(Param("tilt_N_per_m", "N/m", 0.0, relative=True),),
    equation="F += tilt x: virtual deflection, a force linear in the piezo's travel, in and out of contact",
    signature="baseline sloped with the travel before contact, the same slope under the contact force; on a "
    "curve at one constant speed it is drift (time and travel are proportional): only where the speed "
    "changes (the retract, a hold) are the two told apart", linear=True)

DRAG_EFFECT = Effect(
    name=DRAG, stage="sensor", fn=_drag, params=(Param("drag_N_s_per_m", "N s/m", 0.0, relative=True),),
    equation="F += b dx/dt: hydrodynamic drag on the cantilever, proportional to the piezo's speed, in "
    "and out of contact",
    signature="a step in the force where the motion turns: approach and retract read 2 b v apart, also out of "
    "contact; on an approach alone at one speed it is a constant, an offset", linear=True)

def _adhesion(m: Motion, force, pull_off_N, pull_off_m, x_c_m):
    d = m.x_m - x_c_m
    L = max(abs(pull_off_m), 1e-300)
    # the travel to the farther neighbour: the let-go windows of successive samples overlap, so
    # wherever L falls some sample's force moves with it (the tip jumps where it lets go: the
    # velocity's own step would leave gaps)
    gap = np.abs(np.diff(m.x_m))
    step = np.maximum(np.maximum(np.r_[gap, 0.0], np.r_[0.0, gap]), 1e-300)
    held = np.clip((d + L) / step + 0.5, 0.0, 1.0)
    return np.where((m.v_m_s < 0) & (d < 0), pull_off_N * (d / L) * held, 0.0)


def _adhesion_guess(m: Motion, misfit_N: np.ndarray, values: dict, model_N: np.ndarray) -> dict[str, float]:
    """The neck that best fits the misfit on the way out past the contact point: for every sample
    it might let go after, the slope by least squares over the samples before it (the force
    through nought at the contact point) and nought after; the let-go that leaves the least."""
    d = m.x_m - values["x_c_m"]
    out = np.flatnonzero((m.v_m_s < 0) & (d < 0))
    if len(out) < 3:
        return {}
    r, dd = misfit_N[out], d[out]
    rd, d2 = np.cumsum(r * dd), np.cumsum(dd * dd)
    gain = np.where(rd > 0, rd * rd / np.maximum(d2, 1e-300), 0.0)  # what a neck pulling (s > 0) removes
    j = int(np.argmax(gain[:-1]))
    if gain[j] <= 0:
        return {}
    L = -0.5 * (dd[j] + dd[j + 1])
    return {"pull_off_N": float(rd[j] / d2[j] * L), "pull_off_m": float(L)}


ADHESION_EFFECT = Effect(
    name=ADHESION, stage="sensor", fn=_adhesion,
    params=(Param("pull_off_N", "N", 0.0, 0.0, relative=True, warn_negative=True,
                  doc="the pull-off force: the most the neck pulls before the tip lets go"),
            Param("pull_off_m", "m", 0.3, 1e-3, 10.0, relative=True, warn_negative=True,
                  doc="the tip's travel past the contact point when it lets go"),
            # the contact point's own parameter (rig.models.catalogue.CONTACT_POINT), shared by name:
            # the neck starts there; a model holding both takes its bounds from the geometry stage
            Param("x_c_m", "m", 0.0, -1.0, 0.99, relative=True, per_record=True)),
    equation="F += F_off d / L on the retract for -L < d < 0 (d = x - x_c): the tip stuck to the sample, "
    "pulled linearly to the pull-off force F_off at the pull-off distance L, then let go (DMT: F_off = "
    "2 pi R w, JKR: 3/2 pi R w)",
    signature="retract dipping below the baseline past the contact point, then a jump back to it: the tip "
    "sticks on the way out; a model without it pulls the contact point and the baseline towards the dip",
    guess=_adhesion_guess)

SENSOR_EFFECTS = {TILT: TILT_EFFECT, DRAG: DRAG_EFFECT, ADHESION: ADHESION_EFFECT}
