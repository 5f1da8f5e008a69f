"""Every catalogue effect as the models evaluate it (vectorised, one sample per step) against
the same mechanism integrated here independently, in small explicit steps on the exact motion.
The integration is written out per mechanism and never calls rig.models."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from rig.sim.params import ComplianceParams
from scipy.optimize import brentq

from rig.cli import main
from rig.models import CATALOGUE, Motion, build_model
from rig.specs.config import RigConfig
from tests.conftest import calibration_seeds, run_sim

DT_S = 0.01
SUBSTEPS = 50  # fine steps per sample
DEPTH_M = 0.03
RAMP_S = 10.0
HOLD_S = 20.0
BACK_S = 6.0
TISSUE = {"k1_N_per_m3": 5.6e4, "k2_N_per_m2": 550.0, "k3_N_per_m": 14.0, "tau2_N_s_per_m2": 2.3e5,
          "tau1_s": 8.0}
# each effect's parameters (SI), at a size that shows clearly against the tissue force
EFFECT = {
    "linear_elastic": {"k_N_per_m": 80.0},
    "poly_elastic": {},
    "power_elastic": {"k_N_per_m_n": 900.0, "n": 1.5},
    "viscous": {"eta_N_s_per_m": 150.0},
    "hc_damping": {"b_N_s_per_m_n1": 4e4, "n": 1.5},
    "nonlinear_damping": {},
    "relaxation": {},
    "relaxation2": {"k_m_N_per_m": 60.0, "tau_m_s": 5.0},
    "offset": {"offset_N": 0.3},
    "drift": {"drift_N_per_s": 0.004},
    "contact_offset": {"x0_mm": 1.5},
    "delay": {"delay_s": 0.08},
    "compliance": {"k_frame_N_per_m": 5e4},
    "friction": {"friction_N": 0.15},
}
FRICTION_ROUNDING = 0.02  # the catalogue's definition: tanh(v / (2 % of the record's speed))


def _x(t: float) -> tuple[float, float]:
    """A smooth ramp (raised cosine), a hold, a smooth return: position and velocity."""
    if t < RAMP_S:
        w = math.pi / RAMP_S
        return 0.5 * DEPTH_M * (1 - math.cos(w * t)), 0.5 * DEPTH_M * w * math.sin(w * t)
    if t < RAMP_S + HOLD_S:
        return DEPTH_M, 0.0
    s = t - RAMP_S - HOLD_S
    if s < BACK_S:
        w = math.pi / BACK_S
        return 0.5 * DEPTH_M * (1 + math.cos(w * s)), -0.5 * DEPTH_M * w * math.sin(w * s)
    return 0.0, 0.0


def _integrate(effect: str, p: dict, speed_m_s: float, t_s: np.ndarray) -> np.ndarray:
    """The proposed tissue plus `effect`, explicit small steps; the sensor reading at `t_s`."""
    # the frame's implicit step costs a root search: fewer, still small, steps for it
    substeps = 10 if effect == "compliance" else SUBSTEPS
    h = DT_S / substeps
    k1, k2, k3, tau2, tau1 = (TISSUE[k] for k in ("k1_N_per_m3", "k2_N_per_m2", "k3_N_per_m",
                                                   "tau2_N_s_per_m2", "tau1_s"))
    a1 = math.exp(-h / tau1)
    state = {"f1": 0.0, "f2": 0.0, "x": 0.0}

    def tissue_at(x: float, v: float) -> tuple[float, float, float]:
        """Both branches and the total after a step ending at indentation x, speed v."""
        contact = x > 0
        xi, vi = (x, v) if contact else (0.0, 0.0)
        drive = ((k1 * xi + k2) * xi + k3) * xi + tau2 * xi * vi
        if effect == "linear_elastic":
            drive += p["k_N_per_m"] * xi
        elif effect == "power_elastic":
            drive += p["k_N_per_m_n"] * xi ** p["n"]
        elif effect == "viscous":
            drive += p["eta_N_s_per_m"] * vi
        elif effect == "hc_damping":
            drive += p["b_N_s_per_m_n1"] * xi ** p["n"] * vi
        if not contact:
            drive = 0.0
        # neither the lag nor the branch stores tension: driven to pull, the tissue separates
        # (as the simulated tissue does)
        f1 = max(drive + (state["f1"] - drive) * a1, 0.0)
        f2 = state["f2"]
        if "k_m_N_per_m" in p:  # Maxwell branch: f2' = k v - f2 / tau
            f2 = max(f2 + h * (p["k_m_N_per_m"] * vi - f2 / p["tau_m_s"]), 0.0)
        return f1, f2, max(f1 + f2, 0.0)

    history: list[tuple[float, float]] = []
    out = []
    for i in range(len(t_s) * substeps + 1):
        t = i * h
        x, v = _x(t)
        if effect == "contact_offset":
            x = x - p["x0_mm"] / 1000.0
        if effect == "compliance":
            # the frame spring carries the tissue force: indentation and force found together
            # in each step (force grows with indentation, so the bracketed root is unique)
            k_frame = p["k_frame_N_per_m"]

            def gap(xc: float, x: float = x, first: bool = i == 0, k_frame: float = k_frame) -> float:
                return xc - x + tissue_at(xc, 0.0 if first else (xc - state["x"]) / h)[2] / k_frame

            lo = x - tissue_at(x, (x - state["x"]) / h if i else 0.0)[2] / k_frame
            x = brentq(gap, lo, x, xtol=1e-15, rtol=1e-15) if lo < x else x
            v = (x - state["x"]) / h if i else 0.0
        f1, f2, tissue = tissue_at(x, v)
        state.update(f1=f1, f2=f2, x=x)
        sensed = tissue
        if effect == "offset":
            sensed += p["offset_N"]
        elif effect == "drift":
            sensed += p["drift_N_per_s"] * t
        elif effect == "friction":
            sensed += p["friction_N"] * math.tanh(_x(t)[1] / (FRICTION_ROUNDING * speed_m_s))
        history.append((t, sensed))
        if i % substeps == 0:
            out.append(sensed)
    out = np.array(out[: len(t_s)])
    if effect == "delay":
        ts, fs = np.array(history).T
        out = np.interp(t_s - p["delay_s"], ts, fs, left=fs[0])
    return out


# a frame softer than the tissue (the plain fixed point diverges there), and one behind a
# tissue with a second, parallel relaxation branch (which Newton's step includes)
FRAMES = [*(pytest.param("compliance", {"k_frame_N_per_m": k}, id=f"compliance-{k:g}N_per_m")
            for k in (300.0, 500.0)),
          pytest.param("compliance", {"k_frame_N_per_m": 300.0, **EFFECT["relaxation2"]},
                       id="compliance-300N_per_m+relaxation2")]


# the fractional and the speed-dependent relaxation have their own fine-step integrations
# (Grünwald-Letnikov, Euler) in tests/test_beyond_catalogue.py
ELSEWHERE = {"fractional_relaxation", "speed_relaxation"}


def test_every_catalogue_effect_has_a_fine_step_check():
    assert set(CATALOGUE) == set(EFFECT) | ELSEWHERE


@pytest.mark.parametrize(("effect", "params"), [*((e, EFFECT[e]) for e in sorted(EFFECT)), *FRAMES])
def test_effect_matches_a_fine_step_integration(effect, params):
    t_s = np.arange(0.0, RAMP_S + HOLD_S + BACK_S + 4.0, DT_S)
    xv = np.array([_x(t) for t in t_s])
    motion = Motion(t_s, xv[:, 0], np.gradient(xv[:, 0], DT_S), DT_S)
    extra = [] if effect in ("poly_elastic", "nonlinear_damping", "relaxation") else [effect]
    model = build_model("proposed", extra + (["relaxation2"] if "k_m_N_per_m" in params else []))
    values = {**TISSUE, **params}
    predicted = model.predict({k: values[k] for k in model.param_names}, motion)
    reference = _integrate(effect, params, motion.speed_m_s, t_s)
    peak = float(np.max(np.abs(reference)))
    err = np.abs(predicted - reference)
    # within 0.2 % of the peak force everywhere: what one sample per step costs against the
    # mechanism itself (measured: 0.004 % for most effects, whose lags are exact for a drive
    # linear between samples; 0.07 % for the softest frame; 0.1 % for friction, whose sign
    # follows the sampled velocity). A lag that held each sample's drive over the step before
    # it would lead by half a sample: 0.2 to 0.5 % here, and a bias in a stiff frame.
    assert float(np.max(err)) <= 0.002 * peak, (effect, float(np.max(err)), peak, int(np.argmax(err)))


# A frame spring in series with the tissue takes f / k_frame of the slider's travel; it shows
# only through that share, and the tissue's own stiffness terms absorb most of what it does to
# the force at any one depth (fitted jointly over several depths they cannot). Against this
# tissue (about 200 N/m at 30 mm) a 0.5 N/mm frame takes a third of the travel and stands far
# out of the default rig's noise. A 50 N/mm frame takes 0.4 %, 0.2 mm at 10 N; what the tissue
# cannot absorb of it is a few hundredths of a newton, so its error follows the instruments:
# with the default 0.08 N load cell the standard error of k_frame is about 19 % on these
# trials (none of the protocols tried within the rig's 20 N and 10 mm/s brought it under
# 12 %), and the 10 um encoder steps bias it by -2.4 % even without force noise. A lab with a
# stiff frame measures with a precision load cell (0.005 N) and a fine encoder (1 um): then it
# is about 1 %, and the five seeds here land within 5 %.
FRAMES_HIDDEN = [pytest.param(500.0, 0.08, 100.0, id="soft-0.5N_per_mm"),
                 pytest.param(5e4, 0.005, 1000.0, id="stiff-50N_per_mm-precision-rig")]


@pytest.mark.parametrize("seed", calibration_seeds(range(5)))
@pytest.mark.parametrize(("k_frame_N_per_m", "noise_N", "steps_per_mm"), FRAMES_HIDDEN)
def test_hidden_frame_is_recovered_by_add_compliance(k_frame_N_per_m, noise_N, steps_per_mm, seed,
                                                     tmp_path, capsys):
    """A frame spring hidden in trials made by the simulated rig to three depths: `rig analyze
    --add compliance` gives its stiffness within 10 % at every seed."""
    paths = []
    for i, depth in enumerate((10, 20, 30)):
        cfg = RigConfig()
        cfg.sim.effects.compliance = ComplianceParams(k_frame_N_per_m=k_frame_N_per_m)
        cfg.sim.loadcell.noise_N = noise_N
        cfg.sim.slider.steps_per_mm = steps_per_mm
        cfg.sim.substep_ms = 1.0
        cfg.sim.seed = 100 * seed + i
        proto = (f"name: ramp to {depth} mm\nsteps:\n  - ramp: {{to_mm: {depth}, speed_mm_s: 3}}\n"
                 "  - hold: {duration_s: 10}\n  - return: {to_mm: 0, speed_mm_s: 5}\n")
        paths.append(str(run_sim(proto, cfg, tmp_path, name=f"d{depth}.mcap").log_path))
    assert main(["analyze", *paths, "--add", "compliance", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert "compliance" in out["effects"]
    k = out["parameters"]["k_frame_N_per_m"]["value"]
    assert abs(k / k_frame_N_per_m - 1) <= 0.10, k
    assert out["fit"]["rmse_over_noise"] <= 1.2
