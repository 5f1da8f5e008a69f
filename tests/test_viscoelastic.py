"""Viscoelastic contact (rig.models.viscoelastic, rig.models.ting) against an independent computation.

The reference here shares no code with the models: the depth history is the exact piecewise-linear
one (corners where the protocol has them, contact between samples), Ting's t1 is the root (brentq) of
int_t1^t E(t - s) d'(s) ds = 0 written with the modulus's closed-form integral Phi, and the force is
adaptive quadrature (scipy quad, QAWS weights for the d^(1/2) onset of a paraboloid and the
(t - s)^-beta singularity of the power law) of E(t - s) dg/dd d'(s) over the loading side. The
geometric derivative dg/dd is written out: 2 sqrt(R d) for the paraboloid, 2 a(d) for Sneddon's
sphere (the contact stiffness 2 a E*, a solved from d = a/2 ln((R+a)/(R-a))), 4/pi tan(alpha) d
for the cone, 2 R for the flat punch, each over (1 - nu^2).

Measured (dt = 2 ms, a 1 s ramp at 3 um/s, the touch 0.85 of a sample past a sample):
max |model - reference| / peak force <= 3.8e-5 over ramp-hold, approach-retract and
ramp-hold-retract, paraboloid, sphere, cone and flat punch, SLS and power law (beta 0.2 and 0.6): SLS
<= 5.7e-6, beta 0.2 <= 7.2e-6, beta 0.6 <= 3.8e-5 (sphere; paraboloid 3.5e-5, cone 3.3e-6), the
flat punch to ~2e-8 (its force is linear in d, which the model takes exactly). A corner of the
motion between two samples is outside what samples say: there the sampled history itself differs
from the true one for a sample (1.4e-3 of the peak at beta 0.2, 6 % at beta 0.6, 5e-6 for the SLS,
measured while writing this), so the corners here sit on samples.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq

from rig.analysis.workflow.session import AnalyzeRequest, analyze
from rig.errors import RigError
from rig.models.catalogue import build_model
from rig.models.contact import Indenter, geometry_factor
from rig.models.ting import hereditary_force
from rig.models.viscoelastic import modulus_at, power_law_modulus, prony_modulus

ROOT = Path(__file__).resolve().parent.parent
OOCYTE = ROOT.parent / "shared" / "realdata" / "oocyte-cell1" / "cell1-0001.jpk-force"

NU = 0.5
R = 5e-6
DT = 2e-3
V = 3e-6  # m/s
SLS = {"E_inf_Pa": 1e3, "E1_Pa": 2e3, "tau1_s": 0.3}
POWER = {"E0_Pa": 1e3, "beta": 0.2}
CONE_HALF_ANGLE = math.radians(35.0)


# ------------------------------------------------------------------------------ the reference

def closed_modulus(params: dict[str, float]):
    """E(u), its integral Phi(u) from 0, the power law's exponent (0 for Prony) and E(u) u^beta."""
    if "beta" in params:
        E0, b = params["E0_Pa"], params["beta"]
        return (lambda u: E0 * u ** -b), (lambda u: E0 * u ** (1 - b) / (1 - b)), b, (lambda u: E0)
    Ei, E1, tau = params["E_inf_Pa"], params["E1_Pa"], params["tau1_s"]
    return ((lambda u: Ei + E1 * math.exp(-u / tau)), (lambda u: Ei * u - E1 * tau * math.expm1(-u / tau)),
            0.0, None)


def sphere_radius(d: float) -> float:
    return brentq(lambda a: a / 2 * math.log((R + a) / (R - a)) - d, 0.0, R * (1 - 1e-15), xtol=1e-22,
                  rtol=1e-15)


def dg_dd(kind: str, d: float) -> float:
    if kind == "paraboloid":
        return 2.0 * math.sqrt(R * d) / (1 - NU ** 2)
    if kind == "sphere":
        return 2.0 * sphere_radius(d) / (1 - NU ** 2) if d > 0 else 0.0
    if kind == "cone":  # g = 2/pi tan(alpha) d^2 / (1 - nu^2)
        return 4.0 / math.pi * math.tan(CONE_HALF_ANGLE) * d / (1 - NU ** 2)
    return 2.0 * R / (1 - NU ** 2)


def reference_force(t: np.ndarray, knots_t: list[float], knots_d: list[float], params: dict[str, float],
                    kind: str) -> np.ndarray:
    """F at the times `t` for the depth through `knots` (one maximum, first knot the touch)."""
    E, Phi, beta, E_reg = closed_modulus(params)
    segs = [(ta, tb, da, (db - da) / (tb - ta))
            for ta, tb, da, db in zip(knots_t[:-1], knots_t[1:], knots_d[:-1], knots_d[1:], strict=True)]
    top = int(np.argmax(knots_d))
    t_touch, t_top, d_top = knots_t[0], knots_t[top], knots_d[top]
    curved = kind in ("paraboloid", "sphere")  # dg/dd ~ d^(1/2) at the touch

    def loading(t_now: float, upper: float) -> float:
        total = 0.0
        for a, b, d0, slope in segs:
            if slope <= 0 or a >= upper:
                continue
            b = min(b, upper)
            wa = 0.5 if (curved and d0 == 0.0) else 0.0  # d^(1/2) onset: sqrt(s - a) as a weight
            wb = -beta if (beta and b == t_now) else 0.0

            def f(s, a=a, d0=d0, slope=slope, wa=wa, wb=wb):
                depth = d0 + slope * (s - a)
                e = E_reg(t_now - s) if wb else E(t_now - s)
                if not wa:
                    dg = dg_dd(kind, depth)
                elif s > a:
                    dg = dg_dd(kind, depth) / (s - a) ** 0.5
                else:  # the limit of both curved laws at the touch: a = sqrt(R d)
                    dg = 2.0 * math.sqrt(R * slope) / (1 - NU ** 2)
                return e * dg * slope

            if wa or wb:
                total += quad(f, a, b, weight="alg", wvar=(wa, wb), epsabs=0.0, epsrel=1e-11, limit=200)[0]
            else:
                total += quad(f, a, b, epsabs=0.0, epsrel=1e-11, limit=200)[0]
        return total

    def ting(t1: float, t_now: float) -> float:
        return sum(slope * (Phi(t_now - max(a, t1)) - Phi(t_now - min(b, t_now)))
                   for a, b, _, slope in segs if min(b, t_now) > max(a, t1))

    out = []
    for t_now in t:
        depth = float(np.interp(t_now, knots_t, knots_d))
        if t_now <= t_touch:
            out.append(0.0)
        elif t_now <= t_top or depth >= d_top:
            out.append(loading(t_now, t_now))
        elif ting(t_touch, t_now) <= 0.0:
            out.append(0.0)  # the contact is lost
        else:
            out.append(loading(t_now, brentq(lambda s, tn=t_now: ting(s, tn), t_touch, t_top, xtol=1e-15)))
    return np.array(out)


# ------------------------------------------------------------------------------ forward model

def model_force(t, knots_t, knots_d, params, kind) -> np.ndarray:
    ind = Indenter(kind, half_angle_rad=CONE_HALF_ANGLE) if kind == "cone" else Indenter(kind, R_m=R)
    d = np.interp(t, knots_t, knots_d, left=0.0, right=knots_d[-1])
    dt = float(t[1] - t[0])
    if "beta" in params:
        mod = power_law_modulus(params["E0_Pa"], params["beta"], len(t) * dt, dt)
    else:
        mod = prony_modulus(params["E_inf_Pa"], [(params["E1_Pa"], params["tau1_s"])])
    return hereditary_force(d, geometry_factor(ind, d, NU), dt, *mod, exponent=ind.exponent)


T_TOUCH = 0.2037  # between samples
D_TOP = V * (1.2 - T_TOUCH)
PROTOCOLS = {  # depth knots; the corners (end of ramp, start and end of retract) on samples
    "ramp-hold": ([T_TOUCH, 1.2, 4.0], [0.0, D_TOP, D_TOP], 4.0),
    "approach-retract": ([T_TOUCH, 1.2, 2.2 - T_TOUCH, 2.5], [0.0, D_TOP, 0.0, 0.0], 2.5),
    "ramp-hold-retract": ([T_TOUCH, 1.2, 3.0, 4.0 - T_TOUCH, 4.5], [0.0, D_TOP, D_TOP, 0.0, 0.0], 4.5),
}


@pytest.mark.parametrize("kind", ["paraboloid", "sphere", "cone", "cylinder"])
@pytest.mark.parametrize("params", [SLS, POWER, {"E0_Pa": 1e3, "beta": 0.6}],
                         ids=["sls", "power0.2", "power0.6"])
@pytest.mark.parametrize("protocol", list(PROTOCOLS))
def test_the_forward_model_agrees_with_quadrature(kind, params, protocol):
    knots_t, knots_d, end = PROTOCOLS[protocol]
    t = np.arange(0.0, end, DT)
    ref = reference_force(t, knots_t, knots_d, params, kind)
    got = model_force(t, knots_t, knots_d, params, kind)
    err = float(np.max(np.abs(got - ref)) / np.max(ref))
    assert err < 5e-5, err  # the brief asks 5e-4
    if protocol != "ramp-hold":
        # Ting: the force reaches zero while the probe is still in the specimen, where Lee-Radok
        # would pull; the model is zero there too
        lost = (ref == 0.0) & (t > knots_t[1])
        assert lost.any() and np.all(got[lost] == 0.0)


def test_a_constant_modulus_is_the_elastic_law_on_the_way_in_and_out():
    """E(t) = E: Ting's t1 is where d(t1) = d(t), so the force is E g(d) on the retract as well (to
    the interpolation of g within the sample of t1, straight: 5.5e-6 of the peak here)."""
    knots_t, knots_d, end = PROTOCOLS["ramp-hold-retract"]
    t = np.arange(0.0, end, DT)
    d = np.interp(t, knots_t, knots_d, left=0.0)
    ind = Indenter("paraboloid", R_m=R)
    g = geometry_factor(ind, d, NU)
    for mod in (prony_modulus(1.5e3, [(0.0, 0.3)]), power_law_modulus(1.5e3, 0.0, end, DT)):
        F = hereditary_force(d, g, DT, *mod, exponent=1.5)
        assert np.max(np.abs(F - 1.5e3 * g)) < 2e-5 * np.max(F)


def test_the_flat_punch_keeps_lee_radok_until_it_lets_go():
    """Its contact area does not change: Ting's force is Lee-Radok's while it pushes."""
    knots_t, knots_d, end = PROTOCOLS["approach-retract"]
    t = np.arange(0.0, end, DT)
    d = np.interp(t, knots_t, knots_d, left=0.0)
    g = geometry_factor(Indenter("cylinder", R_m=R), d, NU)
    mod = prony_modulus(SLS["E_inf_Pa"], [(SLS["E1_Pa"], SLS["tau1_s"])])
    ting = hereditary_force(d, g, DT, *mod)
    pushing = ting > 0
    c, r, w = mod
    # Lee-Radok written out: sum of E(t_i - s) over the increments of g, exact for g linear per sample
    i = np.arange(len(t))
    W = (c * DT + ((np.exp(-np.outer(i, r * DT)) * -np.expm1(-r * DT)) / r) @ w) / DT
    direct = np.convolve(np.diff(g, prepend=0.0), W)[: len(t)]
    touch = int(np.argmax(d > 0))  # the model puts the touch inside its sample: leave that sample out
    keep = pushing & (i > touch + 1)
    assert np.max(np.abs(ting[keep] - direct[keep])) < 2e-3 * np.max(ting)
    assert np.any(direct[~pushing & (t > 1.2)] < 0)  # where it lets go, Lee-Radok's punch would pull


def test_the_power_law_sum_of_exponentials_matches_the_exact_interval_integrals():
    """The model convolves E(t) = E0 (t/1s)^-beta as exponentials: their interval averages over each
    sample agree with the exact (t^(1-beta)) ones to 1e-7 from beta 0.02 to 0.95."""
    for dt, duration in ((1 / 256, 40.0), (1e-3, 3.0), (1e-2, 300.0)):
        m = np.arange(int(duration / dt))
        for beta in (0.02, 0.2, 0.5, 0.8, 0.95):
            c, r, w = power_law_modulus(1.0, beta, duration, dt)
            exact = (((m + 1) * dt) ** (1 - beta) - (m * dt) ** (1 - beta)) / ((1 - beta) * dt)
            x = r * dt
            soe = c + (np.exp(-np.outer(m, x)) * (-np.expm1(-x) / x)) @ w
            assert np.max(np.abs(soe / exact - 1)) < 1e-7, (dt, beta)
            late = np.array([1.0, 10.0, duration / 2])
            assert np.allclose(modulus_at((c, r, w), late), late ** -beta, rtol=1e-6)


def test_the_force_is_continuous_in_the_contact_point():
    """A fit moves the contact point across samples: the force must not step as it does."""
    t = np.arange(0.0, 2.0, DT)
    x = V * t
    ind = Indenter("paraboloid", R_m=R)
    mod = power_law_modulus(1e3, 0.3, 2.0, DT)
    step = V * DT
    xcs = 0.5e-6 + step * np.linspace(-1.5, 1.5, 61)
    forces = []
    for xc in xcs:
        d = np.maximum(x - xc, 0.0)
        forces.append(hereditary_force(d, geometry_factor(ind, d, NU), DT, *mod, exponent=1.5))
    jumps = np.max(np.abs(np.diff(forces, axis=0)), axis=1) / np.max(forces)
    assert np.max(jumps) < 3 * np.median(jumps), jumps


# ------------------------------------------------------------------------------ recovery by fits

SURFACE = 1.0e-6  # m of travel before the touch
NOISE = 3e-3  # of the peak force
OFFSET = 2e-10  # N


def simulated_record(path: Path, kind: str, params: dict[str, float], protocol: str, seed: int,
                     cache: dict) -> Path:
    """A CSV an AFM user would hand over: the probe from 1 um above the surface at 3 um/s to 4.5 um
    of travel, then a hold (ramp-hold) or straight back (approach-retract); force from the
    reference, white noise and a baseline offset."""
    end = {"rh": 5.0, "ar": 3.0}[protocol]
    t = np.arange(0.0, end, DT)
    knots = [0.0, 1.5, end]
    travel = [0.0, 1.5 * V, 1.5 * V if protocol == "rh" else 0.0]
    x = np.interp(t, knots, travel)
    key = (kind, tuple(params.items()), protocol)
    if key not in cache:
        touch = SURFACE / V
        if protocol == "rh":
            dk = ([touch, 1.5, end], [0.0, 1.5 * V - SURFACE, 1.5 * V - SURFACE])
        else:
            dk = ([touch, 1.5, 3.0 - touch, end], [0.0, 1.5 * V - SURFACE, 0.0, 0.0])
        cache[key] = reference_force(t, *dk, params, kind)
    F = cache[key]
    rng = np.random.default_rng(seed)
    f = F + OFFSET + rng.normal(0.0, NOISE * np.max(F), len(t))
    path.write_text("t_s,position_um,force_nN\n" + "\n".join(
        f"{a:.6f},{b * 1e6:.9f},{c * 1e9:.9f}" for a, b, c in zip(t, x, f, strict=True)) + "\n")
    return path


CASES = {  # model, indenter spec, truth
    "paraboloid-sls": ("ting_sls", "paraboloid", SLS),
    "paraboloid-power": ("ting_power", "paraboloid", POWER),
    "flat-sls": ("ting_sls", "cylinder", SLS),
    "flat-power": ("ting_power", "cylinder", POWER),
    "sphere-sls": ("ting_sls", "sphere", SLS),  # Sneddon's sphere, d/R up to 0.7
    "sphere-power": ("ting_power", "sphere", POWER),
}
# two seeds in the default run; five (the figure, the closing note's) with RIG_FULL_SEEDS=1
SEEDS = range(5 if os.environ.get("RIG_FULL_SEEDS") else 2)


def fit_record(tmp: Path, case: str, protocol: str, seed: int, cache: dict) -> dict:
    model, kind, truth = CASES[case]
    path = simulated_record(tmp / f"{case}-{protocol}-{seed}.csv", kind, truth, protocol, seed, cache)
    out = analyze(AnalyzeRequest([str(path)], model=model, indenter=f"{kind}:R=5um")).json
    return {k: (v["value"], v["stderr"]) for k, v in out["parameters"].items()} | {"adequate": out["adequate"]}


@pytest.fixture(scope="module")
def reference_cache() -> dict:
    return {}


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("case", list(CASES))
def test_fits_recover_the_material_and_both_protocols_agree(tmp_path, reference_cache, case, seed):
    _, _, truth = CASES[case]
    fits = {p: fit_record(tmp_path, case, p, seed, reference_cache) for p in ("rh", "ar")}
    for protocol, res in fits.items():
        assert res["adequate"], (protocol, res)
        for name, true in truth.items():
            value, se = res[name]
            assert 0 < se < 0.05 * abs(true), (protocol, name, value, se)
            assert abs(value - true) < 2 * se, (protocol, name, value, se, true)
    for name in truth:
        (a, sa), (b, sb) = fits["rh"][name], fits["ar"][name]
        assert abs(a - b) < 2 * math.hypot(sa, sb), (name, a, sa, b, sb)


# ------------------------------------------------------------------------------ the models by name

def test_the_models_need_the_indenter_and_say_so():
    for name in ("ting_sls", "ting_prony2", "ting_prony3", "ting_power"):
        with pytest.raises(RigError, match=f"the {name} model needs the indenter's geometry"):
            build_model(name)
    with pytest.raises(RigError, match="did you mean 'ting_sls'"):
        build_model("ting_sl")


def test_the_models_take_their_parameters_in_si_units(tmp_path):
    from rig.analysis.workflow.inputs import load_inputs

    path = simulated_record(tmp_path / "r.csv", "paraboloid", SLS, "rh", 0, {})
    reg = load_inputs([str(path)], [], [], indenter="paraboloid:R=5um").registry
    units = {name: {p.name: p.unit for p in build_model(name, registry=reg).params}
             for name in ("ting_sls", "ting_prony2", "ting_prony3", "ting_power")}
    assert units["ting_sls"] == {"E_inf_Pa": "Pa", "E1_Pa": "Pa", "tau1_s": "s", "x_c_m": "m", "offset_N": "N"}
    assert units["ting_power"] == {"E0_Pa": "Pa", "beta": "1", "x_c_m": "m", "offset_N": "N"}
    assert set(units["ting_prony3"]) >= {"E3_Pa", "tau3_s", "E2_Pa", "tau2_s"}
    # not among the models --compare ranks, nor the effects --explain tries: asked for by name only
    assert not any(n.startswith("viscoelastic_") for n in reg)
    hertz = build_model("hertz", ["viscoelastic_sls"], registry=reg)
    assert hertz.effect_names == ["elastic_contact", "contact_point", "offset", "viscoelastic_sls"]


def test_a_prony_series_of_two_terms_recovers_both(tmp_path):
    truth = {"E_inf_Pa": 1e3, "E1_Pa": 2e3, "tau1_s": 0.1, "E2_Pa": 1e3, "tau2_s": 1.5}
    t = np.arange(0.0, 8.0, DT)
    x = np.interp(t, [0.0, 1.5, 8.0], [0.0, 1.5 * V, 1.5 * V])
    d = np.maximum(x - SURFACE, 0.0)
    terms = [(truth["E1_Pa"], truth["tau1_s"]), (truth["E2_Pa"], truth["tau2_s"])]
    mod = prony_modulus(truth["E_inf_Pa"], terms)
    F = hereditary_force(d, geometry_factor(Indenter("paraboloid", R_m=R), d, NU), DT, *mod, exponent=1.5)
    f = F + OFFSET + np.random.default_rng(1).normal(0.0, NOISE * F.max(), len(t))
    path = tmp_path / "p2.csv"
    path.write_text("t_s,position_um,force_nN\n" + "\n".join(
        f"{a:.6f},{b * 1e6:.9f},{c * 1e9:.9f}" for a, b, c in zip(t, x, f, strict=True)) + "\n")
    out = analyze(AnalyzeRequest([str(path)], model="ting_prony2", indenter="paraboloid:R=5um")).json
    got = {k: (v["value"], v["stderr"]) for k, v in out["parameters"].items()}
    if got["tau1_s"][0] > got["tau2_s"][0]:  # the two terms may come back in either order
        got["tau1_s"], got["tau2_s"], got["E1_Pa"], got["E2_Pa"] = (got["tau2_s"], got["tau1_s"], got["E2_Pa"],
                                                                   got["E1_Pa"])
    for name, true in truth.items():
        assert abs(got[name][0] - true) < 3 * got[name][1], (name, got[name], true)


@pytest.mark.skipif(not OOCYTE.exists(), reason=f"the shared real records are absent ({OOCYTE})")
def test_a_real_oocyte_relaxation_reads_as_a_power_law():
    """cell1-0001 (stress relaxation, 20 um in 1 s, 30 s hold): E0 in Pa, beta dimensionless, both
    determined; at the time of writing E0 = 525.5 +/- 0.4 Pa, beta = 0.2403 +/- 0.0001 (R = 10 um).
    The power law is not the whole story (RMSE ~2 % of the peak, far above the noise)."""
    r = subprocess.run([sys.executable, "-m", "rig", "analyze", str(OOCYTE), "--model", "ting_power",
                        "--indenter", "paraboloid:R=10um", "--json"], capture_output=True, text=True, cwd=ROOT,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    import json

    p = json.loads(r.stdout)["parameters"]
    assert p["E0_Pa"]["unit"] == "Pa" and p["beta"]["unit"] == "1"
    assert 100 < p["E0_Pa"]["value"] < 3000 and 0.05 < p["beta"]["value"] < 0.6, p
    assert p["E0_Pa"]["stderr"] < 0.05 * p["E0_Pa"]["value"] and p["beta"]["stderr"] < 0.02, p
