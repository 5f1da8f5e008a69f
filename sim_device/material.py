"""A material under an indenter: the simulated tissue as a relaxation modulus E(t) and a contact
geometry, in place of the paper's lumped model, so a trial carries a material truth in pascals.

Geometry (a rigid axisymmetric indenter on a half-space of Poisson's ratio nu, elastic force
F = E/(1 - nu^2) C psi(d) at depth d):

    paraboloid:R=...        psi = d^1.5   C = 4/3 sqrt(R)         (Hertz)
    cone:half_angle=...     psi = d^2     C = 2 tan(alpha) / pi   (Sneddon)
    cylinder:R=...          psi = d       C = 2 R                 (the flat punch)

Relaxation: the standard linear solid E(t) = E_inf + (E0 - E_inf) exp(-t/tau), or a power law
E(t) = E0 (t/t0)^-beta (`beta` > 0). The power law is a continuous mixture of exponentials,
t^-beta = 1/Gamma(beta) int_0^inf r^(beta-1) exp(-r t) dr, held here as one mode per cell of rates
with the cell's exact weight, from rates far slower than any trial to ten per sub-step (faster
ones relax within a step).

While the contact grows (or holds) the force is Lee and Radok's (1960) hereditary integral,
F(t) = C/(1 - nu^2) int_0^t E(t - s) dpsi(s), one recursion per mode. Where it shrinks it is
Ting's (1966): F(t) = C/(1 - nu^2) int_0^t1 E(t - s) dpsi(s), t1 the earlier time at which the
contact was as large, found from int_t1^t E(t - s) dd(s) = 0, by bisection over the kept history
of every mode's state (stored every `KEEP_EVERY` sub-steps, interpolated between). Ting's rule is
taken from the deepest point of the current contact: a reloading past it is Lee and Radok's
again. The probe leaving the surface ends a contact and its history.
"""

from __future__ import annotations

import math
import re

import numpy as np

KEEP_EVERY = 4  # sub-steps between kept history points (2 ms at the default 0.5 ms sub-step)
MODES_PER_DECADE = 6
SLOWEST_RATE_PER_S = 1e-6

_LENGTH = {"nm": 1e-9, "um": 1e-6, "µm": 1e-6, "mm": 1e-3, "m": 1.0}


def parse_geometry(spec: str) -> tuple[str, float, float]:
    """(kind, exponent of psi, C) from 'paraboloid:R=5mm', 'cone:half_angle=35deg' or
    'cylinder:R=2mm' (the simulator's own reading; ValueError says what is wrong)."""
    kind, _, rest = spec.partition(":")
    kind = kind.strip().lower()
    args = {}
    for part in filter(None, (p.strip() for p in rest.split(","))):
        key, _, value = part.partition("=")
        args[key.strip()] = value.strip()
    if kind in ("paraboloid", "cylinder"):
        m = re.fullmatch(r"([0-9.eE+-]+)\s*(nm|um|µm|mm|m)", args.get("R", ""))
        if not m:
            raise ValueError(f"indenter {spec!r}: expected R=<length with unit>, e.g. {kind}:R=5mm")
        R = float(m.group(1)) * _LENGTH[m.group(2)]
        return (kind, 1.5, 4.0 / 3.0 * math.sqrt(R)) if kind == "paraboloid" else (kind, 1.0, 2.0 * R)
    if kind == "cone":
        m = re.fullmatch(r"([0-9.eE+-]+)\s*(deg|rad)", args.get("half_angle", ""))
        if not m:
            raise ValueError(f"indenter {spec!r}: expected half_angle=<angle>deg, e.g. cone:half_angle=35deg")
        a = float(m.group(1)) * (math.pi / 180.0 if m.group(2) == "deg" else 1.0)
        return kind, 2.0, 2.0 * math.tan(a) / math.pi
    raise ValueError(f"indenter {spec!r}: the simulated material takes a paraboloid, a cone or a cylinder "
                     "(flat punch)")


def relaxation_modes(mat, dt: float) -> tuple[float, np.ndarray, np.ndarray]:
    """(E_inf, weights, rates) of E(t) = E_inf + sum_k w_k exp(-r_k t)."""
    if mat.beta > 0:
        b = mat.beta
        hi = 10.0 / dt
        n = max(2, math.ceil(math.log10(hi / SLOWEST_RATE_PER_S) * MODES_PER_DECADE))
        edges = np.logspace(math.log10(SLOWEST_RATE_PER_S), math.log10(hi), n + 1)
        edges[0] = 0.0  # the slowest cell reaches down to rest: E tends to nought, never below
        scale = mat.E0_Pa * mat.t0_s ** b / math.gamma(b)
        w = scale * np.diff(edges ** b) / b
        r = np.sqrt(np.maximum(edges[:-1], SLOWEST_RATE_PER_S / 10.0) * edges[1:])
        return 0.0, w, r
    return mat.E_inf_Pa, np.array([mat.E0_Pa - mat.E_inf_Pa]), np.array([1.0 / mat.tau_s])


class Material:
    """The force of a material under an indenter, one sub-step at a time (see the module)."""

    def __init__(self, mat, dt: float) -> None:
        self.kind, self.power, self.C = parse_geometry(mat.indenter)
        self.C /= 1.0 - mat.poisson ** 2
        self.dt = dt
        self.E_inf, self.w, self.r = relaxation_modes(mat, dt)
        self.decay = np.exp(-self.r * dt)
        # exact for psi (and d) linear over the sub-step
        rdt = self.r * dt
        self.gain = np.where(rdt > 1e-12, -np.expm1(-rdt) / np.maximum(rdt, 1e-300), 1.0)
        self._reset()

    def _reset(self) -> None:
        n = len(self.r)
        self.d = 0.0
        self.P = np.zeros(n)  # int exp(-r (t - s)) dpsi(s): the force's modes
        self.H = np.zeros(n)  # int exp(-r (t - s)) dd(s): the depth's, for Ting's condition
        self.n = 0  # sub-steps into the contact
        self.deepest = (0.0, 0)  # depth and sub-step of the deepest point of this contact
        self.kept_t: list[int] = [0]
        self.kept_d: list[float] = [0.0]
        self.kept_psi: list[float] = [0.0]
        self.kept_P: list[np.ndarray] = [self.P.copy()]
        self.kept_H: list[np.ndarray] = [self.H.copy()]

    def trial(self, d_m: float) -> tuple[float, dict]:
        """The force if the next sub-step ends at depth `d_m`, and the state to commit."""
        if d_m <= 0.0:
            return 0.0, {"reset": True}
        psi0, psi1 = self.d ** self.power, d_m ** self.power
        P = self.decay * self.P + self.gain * (psi1 - psi0)
        H = self.decay * self.H + self.gain * (d_m - self.d)
        n = self.n + 1
        state = {"d": d_m, "P": P, "H": H, "n": n}
        if d_m >= self.deepest[0]:
            state["deepest"] = (d_m, n)
            return self.C * (self.E_inf * psi1 + float(self.w @ P)), state
        return self._ting(d_m, P, H, n), state

    def commit(self, state: dict) -> None:
        if state.get("reset"):
            if self.n:
                self._reset()
            return
        self.d, self.P, self.H, self.n = state["d"], state["P"], state["H"], state["n"]
        if "deepest" in state:
            self.deepest = state["deepest"]
        if self.n % KEEP_EVERY == 0 or "deepest" in state:
            self.kept_t.append(self.n)
            self.kept_d.append(self.d)
            self.kept_psi.append(self.d ** self.power)
            self.kept_P.append(self.P.copy())
            self.kept_H.append(self.H.copy())

    def _at(self, i: int, n: int, d: float, H: np.ndarray) -> float:
        """int_t1^t E(t - s) dd(s) for t1 the kept point i."""
        lag = (n - self.kept_t[i]) * self.dt
        fade = np.exp(-self.r * lag)
        return self.E_inf * (d - self.kept_d[i]) + float(self.w @ (H - fade * self.kept_H[i]))

    def _ting(self, d: float, P: np.ndarray, H: np.ndarray, n: int) -> float:
        # kept points up to the deepest: the condition falls as t1 moves later while the contact
        # grew, so the root is bracketed by the first kept point and the deepest
        last = next(i for i in range(len(self.kept_t) - 1, -1, -1) if self.kept_t[i] <= self.deepest[1])
        lo, hi = 0, last
        g_lo = self._at(lo, n, d, H)
        if g_lo <= 0.0:
            return 0.0  # shrunk to nothing: the surface has let go of the probe
        g_hi = self._at(hi, n, d, H)
        if g_hi >= 0.0:
            lo = hi
        while hi - lo > 1:
            mid = (lo + hi) // 2
            g = self._at(mid, n, d, H)
            lo, hi, g_lo, g_hi = (mid, hi, g, g_hi) if g > 0 else (lo, mid, g_lo, g)
        # between the two kept points, linearly in the condition
        u = 0.0 if hi == lo or g_lo == g_hi else g_lo / (g_lo - g_hi)
        F = []
        for i in (lo, hi):
            lag = (n - self.kept_t[i]) * self.dt
            modes = float(self.w @ (np.exp(-self.r * lag) * self.kept_P[i]))
            F.append(self.C * (self.E_inf * self.kept_psi[i] + modes))
        return max((1.0 - u) * F[0] + u * F[1], 0.0)
