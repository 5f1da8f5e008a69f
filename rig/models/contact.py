"""Elastic contact laws: the force a rigid indenter of known shape needs to push a depth d into an
elastic half-space of Young's modulus E (Pa) and Poisson's ratio nu.

AFM and tissue-indentation users quote E from the indenter's geometry, so a geometry is a value
(`Indenter`, written as a spec string such as `sphere:R=10um`) and each law is one small function
holding its equation and its source. Every law is linear in the reduced modulus E/(1-nu^2), so a
law returns F per unit reduced modulus (m^2) and `geometry_factor` = F/E is what a fit needs:
F = E * geometry_factor(ind, d, nu). SI units throughout.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from decimal import Decimal

import numpy as np

from rig.errors import SpecError, did_you_mean

KINDS = ("paraboloid", "sphere", "cone", "pyramid", "cylinder")

# Bilodeau (1992) coefficients c in F = c E/(1-nu^2) tan(alpha) d^2, alpha the face half-angle.
PYRAMID_COEFFICIENTS = {3: 0.8887, 4: 0.7453}

# Below this s (a/R ~ s) the closed-form sphere force cancels to ~eps/s^2: use its Taylor series.
_SPHERE_SERIES_BELOW = 0.02
_SPHERE_SERIES = (4 / 3, -4 / 5, 136 / 315, -124 / 567)  # s^3, s^5, s^7, s^9 of (1+tanh^2 s) s - tanh s


# ----------------------------------------------------------------------------------------- indenter

@dataclass(frozen=True)
class Indenter:
    """A rigid indenter: `kind` one of KINDS; `R_m` the radius (paraboloid's tip radius, sphere's
    radius, flat punch's radius); `half_angle_rad` the cone's half-opening angle or the pyramid's
    face half-angle (axis to face); `sides` 3 or 4 for a pyramid (default 4)."""

    kind: str
    R_m: float | None = None
    half_angle_rad: float | None = None
    sides: int | None = None

    def __post_init__(self) -> None:
        if self.kind == "pyramid" and self.sides is None:
            object.__setattr__(self, "sides", 4)  # frozen: the default is set once, here
        problem = _problem(self)
        if problem:
            raise SpecError(f"indenter {self.kind!r}: {problem}")

    @property
    def exponent(self) -> float:
        """n in F ~ d^n (for the sphere, its small-depth exponent)."""
        return {"paraboloid": 1.5, "sphere": 1.5, "cone": 2.0, "pyramid": 2.0, "cylinder": 1.0}[self.kind]

    def describe(self) -> str:
        """One line for reports, e.g. 'paraboloid, R = 10 µm' or 'cone, half-angle 35°'."""
        if self.kind in ("cone", "pyramid"):
            angle = f"half-angle {math.degrees(self.half_angle_rad):.4g}°"
            if self.kind == "cone":
                return f"cone, {angle}"
            return f"{'three' if self.sides == 3 else 'four'}-sided pyramid, {angle}"
        value, unit = _length_in_unit(self.R_m)
        radius = f"R = {value:.4g} {'µm' if unit == 'um' else unit}"
        return f"flat cylindrical punch, {radius}" if self.kind == "cylinder" else f"{self.kind}, {radius}"

    def spec(self) -> str:
        """The canonical spec string; `parse_indenter(ind.spec()) == ind`."""
        if self.kind == "cone":
            return f"cone:half_angle={_angle_text(self.half_angle_rad)}"
        if self.kind == "pyramid":
            return f"pyramid:half_angle={_angle_text(self.half_angle_rad)},sides={self.sides}"
        return f"{self.kind}:R={_length_text(self.R_m)}"


def _problem(ind: Indenter) -> str:
    """What is wrong with an indenter's fields, or ''."""
    if ind.kind not in KINDS:
        return f"unknown shape (shapes: {', '.join(KINDS)})"
    needs_radius = ind.kind in ("paraboloid", "sphere", "cylinder")
    if needs_radius:
        if ind.half_angle_rad is not None or ind.sides is not None:
            return "takes only R_m"
        if ind.R_m is None or not math.isfinite(ind.R_m) or not ind.R_m > 0:
            return f"R_m must be a finite positive length in m, got {ind.R_m!r}"
        return ""
    if ind.R_m is not None:
        return "takes half_angle_rad (and sides for a pyramid), not R_m"
    a = ind.half_angle_rad
    if a is None or not 0 < a < math.pi / 2:
        return f"half_angle_rad must lie strictly between 0 and pi/2, got {a!r}"
    if ind.kind == "cone" and ind.sides is not None:
        return "a cone has no sides"
    if ind.kind == "pyramid" and ind.sides not in PYRAMID_COEFFICIENTS:
        return f"sides must be 3 or 4, got {ind.sides!r}"
    return ""


# ------------------------------------------------------------------------------------- spec strings

_LENGTH_UNITS = {"nm": -9, "um": -6, "µm": -6, "μm": -6, "mm": -3, "m": 0}  # power of ten of a metre
_ANGLE_UNITS = ("deg", "°", "rad")
_NUMBER = re.compile(r"\s*([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(.*?)\s*$")
_KIND_HINTS = {"flat": "cylinder", "punch": "cylinder", "flat_punch": "cylinder", "flat-punch": "cylinder",
               "ball": "sphere", "bead": "sphere"}
_EXAMPLES = "e.g. sphere:R=10um, cone:half_angle=35deg, pyramid:half_angle=35deg,sides=4, cylinder:R=1mm"


def _metres(number: str, unit: str) -> float:
    """The length in m, rounded once from the decimal text: '10um', '0.01mm' and '1e-5m' are one float."""
    try:
        return float(Decimal(number).scaleb(_LENGTH_UNITS[unit]))
    except ArithmeticError:  # an exponent beyond the decimal context: no finite length anyway
        return math.inf


def _length_in_unit(x_m: float) -> tuple[float, str]:
    """x in the unit that keeps its number between 1 and 1000 where it can (nm to m)."""
    unit = "nm" if x_m < 1e-6 else "um" if x_m < 1e-3 else "mm" if x_m < 1.0 else "m"
    return x_m * 10.0 ** -_LENGTH_UNITS[unit], unit


def _shortest(x: float, back: Callable[[str], bool]) -> str | None:
    """Fewest significant digits of x (no exponent) whose text `back` maps to the target exactly."""
    if not 1e-6 <= abs(x) < 1e16:
        return None  # positional text would run to hundreds of digits: the caller writes repr
    for digits in range(1, 18):
        text = np.format_float_positional(x, precision=digits, unique=False, fractional=False, trim="-")
        if back(text):
            return text
    return None


def _length_text(x_m: float) -> str:
    """Shortest text that parses back to exactly x_m (e.g. '10um'), else metres in full."""
    value, unit = _length_in_unit(x_m)
    text = _shortest(value, lambda t: _metres(t, unit) == x_m)
    return text + unit if text else f"{x_m!r}m"


def _angle_text(a_rad: float) -> str:
    """Shortest exact text: degrees (e.g. '35deg') unless radians are shorter (e.g. '0.3rad')."""
    deg = _shortest(math.degrees(a_rad), lambda t: math.radians(float(t)) == a_rad)
    rad = _shortest(a_rad, lambda t: float(t) == a_rad) or repr(a_rad)
    return f"{deg}deg" if deg and len(deg) <= len(rad) else f"{rad}rad"


def _number_and_unit(key: str, raw: str, what: str) -> tuple[str, str]:
    m = _NUMBER.fullmatch(raw)
    if not m:
        raise SpecError(f"{key}={raw!r} is not a number with a unit ({what})")
    return m.group(1), m.group(2)


def _parse_length(key: str, raw: str) -> float:
    what = "expected a length such as 10um; units nm, um, µm, mm, m"
    number, unit = _number_and_unit(key, raw, what)
    if unit == "":
        # a bare 10 is 10 m to a parser and 10 µm to an AFM user: the unit is never guessed
        raise SpecError(f"{key}={raw}: the length has no unit (expected nm, um, µm, mm or m, e.g. 10um)")
    if unit not in _LENGTH_UNITS:
        raise SpecError(f"{key}={raw}: unknown length unit {unit!r}{did_you_mean(unit, _LENGTH_UNITS)}"
                        f" (length units: nm, um, µm, mm, m)")
    x_m = _metres(number, unit)
    if not math.isfinite(x_m) or not x_m > 0:
        raise SpecError(f"{key}={raw}: the radius must be a finite positive length")
    return x_m


def _parse_angle(key: str, raw: str) -> float:
    number, unit = _number_and_unit(key, raw, "expected an angle such as 35deg; units deg, ° or rad")
    if unit == "":
        raise SpecError(f"{key}={raw}: the angle has no unit (expected deg, ° or rad, e.g. 35deg)")
    if unit not in _ANGLE_UNITS:
        raise SpecError(f"{key}={raw}: unknown angle unit {unit!r}{did_you_mean(unit, _ANGLE_UNITS)}"
                        f" (angle units: deg, °, rad)")
    a_rad = float(number) if unit == "rad" else math.radians(float(number))
    if not 0 < a_rad < math.pi / 2:
        raise SpecError(f"{key}={raw}: the half-angle must lie strictly between 0 and 90 degrees"
                        f" (got {math.degrees(a_rad):.6g}°)")
    return a_rad


def _parse_sides(key: str, raw: str) -> int:
    if raw.strip() not in ("3", "4"):
        raise SpecError(f"{key}={raw}: a pyramid has 3 or 4 sides (expected sides=3 or sides=4)")
    return int(raw)


def _canonical_key(kind: str, key: str) -> str:
    """The parameter a user's key stands for: R, half_angle or sides (aliases: radius, a for R)."""
    low = key.lower()
    if low in ("r", "radius") and kind in ("paraboloid", "sphere", "cylinder"):
        return "R"
    if low == "a" and kind == "cylinder":
        return "R"
    if low == "a" and kind in ("paraboloid", "sphere"):
        raise SpecError(f"parameter 'a' (a contact radius) does not describe a {kind}: give its radius R")
    if low in ("half_angle", "half-angle") and kind in ("cone", "pyramid"):
        return "half_angle"
    if low == "sides" and kind == "pyramid":
        return "sides"
    expected = {"cone": ["half_angle"], "pyramid": ["half_angle", "sides"]}.get(kind, ["R"])
    if low in ("r", "radius", "a", "half_angle", "half-angle", "sides"):
        raise SpecError(f"parameter {key!r} does not apply to a {kind} (expected: {', '.join(expected)})")
    raise SpecError(f"unknown parameter {key!r}{did_you_mean(key, expected)}"
                    f" (a {kind} takes: {', '.join(expected)})")


def _parse(spec: str) -> Indenter:
    text = spec.strip()
    if not text:
        raise SpecError(f"empty (expected a shape and its parameters, {_EXAMPLES})")
    kind, _, rest = text.partition(":")
    kind = kind.strip().lower()
    if kind not in KINDS:
        hint = did_you_mean(kind, KINDS).strip()[1:-1]  # "did you mean 'x'?" without its brackets
        if not hint and kind in _KIND_HINTS:
            hint = f"did you mean '{_KIND_HINTS[kind]}'?"
        raise SpecError(f"unknown shape {kind!r} ({hint + ' ' if hint else ''}shapes: {', '.join(KINDS)})")
    params: dict[str, tuple[str, str]] = {}
    for item in rest.split(","):
        if not item.strip():
            continue  # tolerate 'sphere:R=10um,' and 'sphere:'
        key, eq, raw = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise SpecError(f"parameter {item.strip()!r} is not key=value (e.g. R=10um)")
        name = _canonical_key(kind, key)
        if name in params:
            raise SpecError(f"{name} given twice ({params[name][0]}= and {key}=)")
        params[name] = (key, raw.strip())

    def need(name: str, example: str) -> tuple[str, str]:
        if name not in params:
            raise SpecError(f"missing parameter {name} (e.g. {kind}:{example})")
        return params[name]

    if kind in ("paraboloid", "sphere", "cylinder"):
        return Indenter(kind, R_m=_parse_length(*need("R", "R=10um" if kind != "cylinder" else "R=1mm")))
    a_rad = _parse_angle(*need("half_angle", "half_angle=35deg"))
    if kind == "cone":
        return Indenter("cone", half_angle_rad=a_rad)
    sides = _parse_sides(*params["sides"]) if "sides" in params else 4
    return Indenter("pyramid", half_angle_rad=a_rad, sides=sides)


def parse_indenter(spec: str) -> Indenter:
    """An `Indenter` from a spec string: 'sphere:R=10um', 'paraboloid:R=2.5um', 'cone:half_angle=35deg',
    'pyramid:half_angle=35deg,sides=4' (sides 3 or 4, default 4), 'cylinder:R=1mm' (alias a= or
    radius=). Lengths in nm, um, µm, mm or m, the unit always written (1e-5m works); angles in deg,
    ° or rad. Anything wrong raises SpecError saying what and what was expected."""
    if not isinstance(spec, str):
        raise SpecError(f"indenter {spec!r}: expected a spec string ({_EXAMPLES})")
    try:
        return _parse(spec)
    except SpecError as e:
        raise SpecError(f"indenter {spec!r}: {e.message}") from None


# ------------------------------------------------------------------------------------------- laws
# Each law: F / E* in m^2 (E* = E/(1-nu^2) the reduced modulus) for depths d_m > 0 (the caller masks).

def hertz_paraboloid(ind: Indenter, d_m: np.ndarray) -> np.ndarray:
    """Paraboloid of tip radius R (Hertz 1882; Sneddon 1965 for the rigid punch):

        F = 4/3 E/(1-nu^2) sqrt(R) d^(3/2)

    Also the small-depth limit of the sphere."""
    # d sqrt(d), not d ** 1.5: the same to rounding, at a fifth of the cost (a map's fits
    # evaluate it some fifty thousand times a curve)
    return 4.0 / 3.0 * np.sqrt(ind.R_m) * (d_m * np.sqrt(d_m))


def sphere_contact_radius(R_m: float, d_m: np.ndarray) -> np.ndarray:
    """Contact radius a (m) of a rigid sphere of radius R at depth d (0 where d <= 0; Sneddon 1965):
    d = (a/2) ln((R+a)/(R-a)). a < R, tending to R as d grows (in floating point a = R past d ~ 19 R)."""
    d = np.asarray(d_m, dtype=float)
    t = _sphere_s(np.maximum(d / R_m, 1e-300))[1]  # the floor keeps 0/0 out of the solver
    return np.where(d > 0, R_m * t, 0.0)


def _sphere_s(delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """s = artanh(a/R) and tanh(s) solving s tanh(s) = d/R (the depth law with a/R = tanh s).

    Solving in s, not a, keeps full precision where a -> R (deep: s ~ d/R). The start is one
    fixed-point step s = delta/tanh(s) from the small-depth series s^2 = delta (1 + delta/3 +
    4 delta^2/45), within 0.5 % everywhere; two Newton steps on all samples at once then leave
    < 1e-12 relative error for d/R from 1e-300 to 1e6 (beyond, tanh(s) = 1 and s = d/R exactly).
    tanh is the costly part, so the last one is carried to the new s to first order."""
    capped = np.minimum(delta, 1e6)  # the series only steers tanh, which is 1 long before this
    s = delta / np.tanh(np.sqrt(capped * (1.0 + capped / 3.0 * (1.0 + capped * 4.0 / 15.0))))
    for _ in range(2):
        t = np.tanh(s)
        u = 1.0 - t * t
        step = (s * t - delta) / (t + s * u)  # the slope tanh(s) + s (1 - tanh^2 s) is > 0
        s = s - step
    return s, t - u * step


def sneddon_sphere(ind: Indenter, d_m: np.ndarray) -> np.ndarray:
    """Sphere of radius R, exact (Sneddon 1965, Int. J. Eng. Sci. 3:47), contact radius a:

        d = (a/2) ln((R+a)/(R-a))
        F = E/(2(1-nu^2)) [(a^2+R^2) ln((R+a)/(R-a)) - 2 a R]

    Softer than Hertz by ~d/(10R) when shallow; deep (a -> R) it tends to a flat punch of radius R,
    F -> 2 E/(1-nu^2) R (d - R/2). With a = R tanh(s): d = R s tanh(s), F = E* R^2 [(1+tanh^2 s) s - tanh s]."""
    R = ind.R_m
    s, t = _sphere_s(d_m / R)
    s2 = s * s
    c3, c5, c7, c9 = _SPHERE_SERIES
    series = s * s2 * (c3 + s2 * (c5 + s2 * (c7 + s2 * c9)))
    return R * R * np.where(s < _SPHERE_SERIES_BELOW, series, (1.0 + t * t) * s - t)


def sneddon_cone(ind: Indenter, d_m: np.ndarray) -> np.ndarray:
    """Cone of half-opening angle alpha (Sneddon 1948/1965):

        F = 2/pi E/(1-nu^2) tan(alpha) d^2"""
    return 2.0 / np.pi * math.tan(ind.half_angle_rad) * d_m * d_m


def bilodeau_pyramid(ind: Indenter, d_m: np.ndarray) -> np.ndarray:
    """Regular pyramid, alpha the face half-angle (axis to the middle of a face, not to an edge)
    (Bilodeau 1992, "Regular pyramid punch problem", J. Appl. Mech. 59:519):

        F = c E/(1-nu^2) tan(alpha) d^2,  c = 0.7453 (four-sided), 0.8887 (three-sided)

    Cross-checked: c = 0.7453 with the half-angle in AtomicJ (HertzianPyramid), c = 0.8887 with the
    face angle in nanite (model hertz_pyr3s, citing Bilodeau 1992). Both lie between the inscribed
    cone (2/pi = 0.637) and the cone through the edges ((2/pi)/cos(pi/n): 0.900, 1.273), which pins
    the face-angle reading. Some tools (PyFMRheo, afmToolkit, after Rico et al. 2005) use
    c = 1/sqrt(2) = 0.7071 for four sides: their E reads 5.4 % higher on the same curve."""
    return PYRAMID_COEFFICIENTS[ind.sides] * math.tan(ind.half_angle_rad) * d_m * d_m


def boussinesq_flat_punch(ind: Indenter, d_m: np.ndarray) -> np.ndarray:
    """Flat cylindrical punch of radius R (Boussinesq 1885; Sneddon 1965), the contact radius fixed:

        F = 2 R E/(1-nu^2) d"""
    return 2.0 * ind.R_m * d_m


LAWS: dict[str, Callable[[Indenter, np.ndarray], np.ndarray]] = {
    "paraboloid": hertz_paraboloid,
    "sphere": sneddon_sphere,
    "cone": sneddon_cone,
    "pyramid": bilodeau_pyramid,
    "cylinder": boussinesq_flat_punch,
}


# the laws that are a power of the depth, F / E* = c d^p: c from the indenter, and p
POWERS = {"paraboloid": 1.5, "cone": 2.0, "pyramid": 2.0, "cylinder": 1.0}


def power_law(ind: Indenter) -> tuple[float, float] | None:
    """(c, p) with F / E* = c d^p at every depth d > 0 when the indenter's law is a power of the
    depth (a sphere's is not), else None."""
    p = POWERS.get(ind.kind)
    return None if p is None else (float(LAWS[ind.kind](ind, np.array([1.0]))[0]), p)


# ------------------------------------------------------------------------------------------- API

def geometry_factor(ind: Indenter, d_m: np.ndarray, nu: float = 0.5) -> np.ndarray:
    """F / E in m^2 at each depth: 0 where d <= 0 (no contact), nan where d is nan.
    F is linear in E, so a fit of E against a force curve is a one-parameter linear fit on this."""
    if not -1.0 < nu <= 0.5:
        raise ValueError(f"Poisson's ratio nu must lie in (-1, 0.5], got {nu!r}")
    d = np.asarray(d_m, dtype=float)
    touching = d > 0
    # the law on every sample (a depth of 1 m where there is no contact: finite for every law)
    # and the free ones set after: picking the touching samples out and back cost more than the law
    with np.errstate(over="ignore"):
        law = LAWS[ind.kind](ind, np.where(touching, d, 1.0))
    return np.where(touching, law / (1.0 - nu * nu), np.where(d <= 0, 0.0, np.nan))


def contact_force(ind: Indenter, E_Pa: float, d_m: np.ndarray, nu: float = 0.5) -> np.ndarray:
    """Force (N) of the indenter pushed d_m (m) into a half-space of Young's modulus E_Pa (Pa);
    0 where d <= 0. Vectorised over d_m."""
    return E_Pa * geometry_factor(ind, d_m, nu)


def apparent_modulus(ind: Indenter, d_m: np.ndarray, F_N: np.ndarray, nu: float = 0.5) -> np.ndarray:
    """E (Pa) that explains the force at each depth on its own: F / geometry_factor, nan where not
    in contact. Flat over depth when the law fits (the AFM users' plateau check)."""
    g = geometry_factor(ind, d_m, nu)
    F, g = np.broadcast_arrays(np.asarray(F_N, dtype=float), g)
    out = np.full(g.shape, np.nan)
    ok = g > 0
    out[ok] = F[ok] / g[ok]
    return out
