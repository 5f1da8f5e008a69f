"""Parameters in the record's own units: every parameter is fitted as a number of order one.

A parameter's unit string (`N/m^3`, `N s/m^(n+1)`, `s`, `mm`, `Hz`...) says how it scales
with force F, length L and time T; its fit variable is its value divided by F^a L^b T^c,
with the record's own F, L and T. Catalogue parameters give their starting values and
bounds in those units (`relative=True`), so a cell in nN over seconds and a stomach in N
over minutes start from the same place; a plugin's parameters are in SI and are converted.

A model with a lag (f + tau df/dt = g) is fitted in its rate form, df/dt = g/tau - f/tau:
the fit variables are the rate 1/tau and the drive's amplitudes divided by tau. A creep
that never settles wants tau far beyond the record with the drive growing in proportion;
in (tau, amplitudes) that optimum lies at infinity along a flat valley, in the rate form
it is an ordinary point near zero rate, and the fit converges to it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from rig.analysis.trials.data import Scales
from rig.models.core import Model

_BASE = {"N": (1, 0, 0, 1.0), "m": (0, 1, 0, 1.0), "mm": (0, 1, 0, 1e-3), "um": (0, 1, 0, 1e-6),
         "Pa": (1, -2, 0, 1.0), "s": (0, 0, 1, 1.0), "ms": (0, 0, 1, 1e-3), "Hz": (0, 0, -1, 1.0),
         "1": (0, 0, 0, 1.0),
         "rad": (0, 0, 0, 1.0), "deg": (0, 0, 0, 1.0), "%": (0, 0, 0, 1.0)}
_TOKEN = re.compile(r"^(?P<base>[A-Za-z%1]+)(?:\^(?P<exp>\(?[-+0-9.n ]+\)?))?$")


@dataclass(frozen=True)
class Dim:
    """value_SI = z * F^a * L^(b + bn*n) * T^c * factor (bn: exponents that follow a shape parameter n)."""

    a: float = 0.0
    b: float = 0.0
    c: float = 0.0
    bn: float = 0.0
    factor: float = 1.0
    known: bool = True

    def scale(self, s: Scales, n: float = 0.0) -> float:
        return (s.force_N ** self.a * s.length_m ** (self.b + self.bn * n) * s.time_s ** self.c) / self.factor


def parse_unit(unit: str) -> Dim:
    """'N s/m^(n+1)' -> F^1 L^-(n+1) T^1; an unknown unit scales as 1 (known=False)."""
    num, _, den = unit.strip().partition("/")
    a = b = c = bn = 0.0
    factor = 1.0
    for part, sign in ((num, 1.0), (den, -1.0)):
        for tok in part.split():
            m = _TOKEN.match(tok)
            if not m or m["base"] not in _BASE:
                return Dim(known=False)
            ea, eb, ec, fac = _BASE[m["base"]]
            e, en = _exponent(m["exp"])
            if en and m["base"] not in ("m", "mm", "um"):
                return Dim(known=False)
            a += sign * ea * e
            b += sign * eb * e
            c += sign * ec * e
            bn += sign * eb * en
            factor *= fac ** (sign * e)
    return Dim(a, b, c, bn, factor)


def _exponent(text: str | None) -> tuple[float, float]:
    """'3' -> (3, 0); 'n' -> (0, 1); '(n+1)' -> (1, 1)."""
    if not text:
        return 1.0, 0.0
    t = text.replace("(", "").replace(")", "").replace(" ", "")
    if "n" not in t:
        return float(t), 0.0
    const = t.replace("n", "", 1)
    return (float(const) if const not in ("", "+", "-") else 0.0), 1.0


@dataclass
class ParamScaling:
    """Maps a model's fit variables z (order one) to SI values and back, for given scales."""

    model: Model
    scales: Scales

    def __post_init__(self) -> None:
        self.dims = [parse_unit(p.unit) for p in self.model.params]
        names = self.model.param_names
        self._n_index = names.index("n") if "n" in names else None
        # A polynomial's monomials x/L, (x/L)^2, (x/L)^3 are nearly collinear on [0, 1]: fitted as
        # they are, their coefficients trade off and the last digits are left to rounding. The fit
        # works on coefficients of an orthonormal basis of the same span instead.
        poly = [f"k{i}_N_per_m{'' if i == 3 else 4 - i}" for i in (3, 2, 1)]  # degree 1, 2, 3
        self._poly = [names.index(p) for p in poly] if all(p in names for p in poly) else None
        params = self.model.params
        free = self._poly and all(not np.isfinite(params[i].lo) and not np.isfinite(params[i].hi)
                                  for i in self._poly)
        if free:
            gram = np.array([[1.0 / (i + j + 1) for j in (1, 2, 3)] for i in (1, 2, 3)])
            self._chol = np.linalg.cholesky(gram)  # monomial m = L^-T c, c = L^T m
        else:
            self._poly = None
        self._lag, self._drive = self._rate_form()

    def _rate_form(self) -> tuple[int | None, list[int]]:
        """Index of the lag's time constant and of the drive amplitudes it divides, when the
        rate form applies (a lag with one time parameter; drive bounds only at 0 or infinity)."""
        model = self.model
        lags = [e for e in model.effects if e.stage == "lag"]
        if len(lags) != 1 or len(lags[0].params) != 1 or parse_unit(lags[0].params[0].unit).c != 1:
            return None, []
        names = model.param_names
        drive = sorted({names.index(p.name) for e in model.effects if e.stage == "drive"
                        for p in e.params if parse_unit(p.unit).a != 0})
        shared = {p.name for e in model.effects if e.stage != "drive" for p in e.params}
        params = model.params
        if any(params[i].name in shared or (np.isfinite(params[i].lo) and params[i].lo != 0)
               or (np.isfinite(params[i].hi) and params[i].hi != 0) for i in drive):
            return None, []
        return names.index(lags[0].params[0].name), drive

    def _to_rate(self, rel: np.ndarray) -> np.ndarray:
        if self._lag is None:
            return rel
        out = np.array(rel, dtype=float)
        r = 1.0 / out[self._lag]
        out[self._drive] *= r
        out[self._lag] = r
        return out

    def _from_rate(self, z: np.ndarray) -> np.ndarray:
        if self._lag is None:
            return z
        out = np.array(z, dtype=float)
        r = out[self._lag]
        out[self._drive] /= r
        out[self._lag] = 1.0 / r
        return out

    def at_bound(self, z: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float) -> np.ndarray:
        """Which fit variables sit within `tol` (order-one units) of a bound; the rate, whose
        lower bound is near zero, relative to the bound itself."""
        ref_lo = np.maximum(1.0, np.abs(lo))
        ref_hi = np.maximum(1.0, np.abs(hi))
        if self._lag is not None:
            ref_lo[self._lag] = abs(lo[self._lag])
            ref_hi[self._lag] = abs(hi[self._lag])
        with np.errstate(invalid="ignore"):
            return ((np.isfinite(lo) & (z - lo <= tol * ref_lo))
                    | (np.isfinite(hi) & (hi - z <= tol * ref_hi)))

    @property
    def rate_form(self) -> tuple[int | None, list[int]]:
        """Index of the lag's time constant and of the drive amplitudes fitted over it."""
        return self._lag, list(self._drive)

    def integrator(self, z: np.ndarray) -> bool:
        """The lag's rate is at its lower bound: the fit turned the lag into an integrator."""
        return self._lag is not None and float(z[self._lag]) < 0.5  # the upper bound is 1e4

    def _n(self, vals: np.ndarray) -> float:
        return float(vals[self._n_index]) if self._n_index is not None else 0.0

    def scale_vector(self, n: float) -> np.ndarray:
        return np.array([d.scale(self.scales, n) if d.known else 1.0 for d in self.dims])

    def _monomial(self, z: np.ndarray) -> np.ndarray:
        if self._poly is None:
            return z
        m = np.array(z, dtype=float)
        m[self._poly] = np.linalg.solve(self._chol.T, z[self._poly])
        return m

    def _orthonormal(self, m: np.ndarray) -> np.ndarray:
        if self._poly is None:
            return m
        z = np.array(m, dtype=float)
        z[self._poly] = self._chol.T @ m[self._poly]
        return z

    def to_si(self, z: np.ndarray) -> np.ndarray:
        n = self._n(z)  # a shape exponent is dimensionless: its z is its value
        return self._from_rate(self._monomial(z)) * self.scale_vector(n)

    def to_z(self, si: np.ndarray) -> np.ndarray:
        return self._orthonormal(self._to_rate(si / self.scale_vector(self._n(si))))

    def jacobian(self, z: np.ndarray) -> np.ndarray:
        """d(SI values)/dz, for standard errors."""
        h = 1e-6 * np.maximum(1.0, np.abs(z))
        cols = []
        for j in range(len(z)):
            dz = np.zeros_like(z)
            dz[j] = h[j]
            cols.append((self.to_si(z + dz) - self.to_si(z - dz)) / (2 * h[j]))
        return np.array(cols).T

    def start_and_bounds(self, initial: dict[str, float] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """z of the starting point and the bounds: relative parameters as written, SI ones converted."""
        params = self.model.params
        n0 = next((p.init for p in params if p.name == "n"), 0.0)
        sv = self.scale_vector(n0)
        init = self._orthonormal(self._to_rate(np.array([p.init if p.relative else p.init / s
                                                         for p, s in zip(params, sv, strict=True)])))
        lo = np.array([p.lo if p.relative else p.lo / s for p, s in zip(params, sv, strict=True)])
        hi = np.array([p.hi if p.relative else p.hi / s for p, s in zip(params, sv, strict=True)])
        if self._lag is not None:  # the rate's bounds are the time constant's, inverted
            i = self._lag
            lo[i], hi[i] = (1.0 / hi[i] if hi[i] > 0 else 0.0), (1.0 / lo[i] if lo[i] > 0 else np.inf)
        if initial:
            si = np.array([initial.get(p.name, np.nan) for p in params])
            z_prev = self.to_z(np.where(np.isnan(si), init * sv, si))
            init = np.where(np.isnan(si), init, z_prev)
        return init, lo, hi


def values_dict(model: Model, si: np.ndarray) -> dict[str, float]:
    """Parameter values in SI by name, in the model's order."""
    return {k: float(v) for k, v in zip(model.param_names, si, strict=True)}

