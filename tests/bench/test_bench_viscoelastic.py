"""Viscoelastic contact beyond the default tests:

    python -m pytest -p no:cacheprovider tests/bench/test_bench_viscoelastic.py -s -q

- corners of the motion between samples (the end of the ramp at 1.5037 s, 2 ms samples), as real
  motion has them: the sampled history then differs from the true one for a sample after each
  corner, yet the material still comes back within two standard errors for the SLS and the power
  law at beta 0.2 and 0.6 (five seeds, ramp-hold and approach-retract);
- the fifteen stress-relaxation repeats on one oocyte (../shared/realdata/oocyte-cell1) through
  ting_power and ting_prony2 with a 10 um paraboloid: E0, beta and the Prony terms curve by curve,
  their spread, and how much better the two-term series fits than the power law.
"""

from __future__ import annotations

import statistics
from pathlib import Path

import numpy as np
import pytest

from rig.analysis.workflow.session import AnalyzeRequest, analyze
from tests.test_viscoelastic import DT, NOISE, OFFSET, POWER, SLS, SURFACE, V, reference_force

OOCYTES = sorted((Path(__file__).resolve().parents[3] / "shared" / "realdata" / "oocyte-cell1")
                 .glob("cell1-*.jpk-force"))
CORNER = 1.5037  # s: between the 2 ms samples


def off_grid_record(path: Path, truth: dict, protocol: str, seed: int, cache: dict) -> Path:
    end = {"rh": 5.0, "ar": 3.0}[protocol]
    t = np.arange(0.0, end, DT)
    x = np.interp(t, [0.0, CORNER, end], [0.0, CORNER * V, CORNER * V if protocol == "rh" else 0.0])
    key = (tuple(truth.items()), protocol)
    if key not in cache:
        touch, top = SURFACE / V, CORNER * V - SURFACE
        if protocol == "rh":
            knots = ([touch, CORNER, end], [0.0, top, top])
        else:
            back = CORNER + top / (CORNER * V / (end - CORNER))
            knots = ([touch, CORNER, back, end], [0.0, top, 0.0, 0.0])
        cache[key] = reference_force(t, *knots, truth, "paraboloid")
    F = cache[key]
    f = F + OFFSET + np.random.default_rng(seed).normal(0.0, NOISE * np.max(F), len(t))
    path.write_text("t_s,position_um,force_nN\n" + "\n".join(
        f"{a:.6f},{b * 1e6:.9f},{c * 1e9:.9f}" for a, b, c in zip(t, x, f, strict=True)) + "\n")
    return path


@pytest.fixture(scope="module")
def cache() -> dict:
    return {}


@pytest.mark.parametrize("protocol", ["rh", "ar"])
@pytest.mark.parametrize(("model", "truth"), [("ting_sls", SLS), ("ting_power", POWER),
                                              ("ting_power", {"E0_Pa": 1e3, "beta": 0.6})],
                         ids=["sls", "power0.2", "power0.6"])
def test_corners_between_samples_still_give_the_material_back(tmp_path, cache, model, truth, protocol):
    worst = 0.0
    for seed in range(5):
        path = off_grid_record(tmp_path / f"{seed}.csv", truth, protocol, seed, cache)
        p = analyze(AnalyzeRequest([str(path)], model=model, indenter="paraboloid:R=5um")).json["parameters"]
        for name, true in truth.items():
            z = (p[name]["value"] - true) / p[name]["stderr"]
            worst = max(worst, abs(z))
            assert abs(z) < 2.0, (seed, name, p[name], true)
    print(f"\n{model} {truth} {protocol}: max |z| over 5 seeds {worst:.2f}")


@pytest.mark.skipif(not OOCYTES, reason="the shared oocyte records are absent (../shared/realdata/)")
def test_the_oocyte_repeats_read_as_material_parameters():
    rows = []
    for path in OOCYTES:
        power = analyze(AnalyzeRequest([str(path)], model="ting_power", indenter="paraboloid:R=10um")).json
        prony = analyze(AnalyzeRequest([str(path)], model="ting_prony2", indenter="paraboloid:R=10um")).json
        pp, pq = power["parameters"], prony["parameters"]
        rows.append((path.name, pp["E0_Pa"]["value"], pp["beta"]["value"], power["fit"]["rmse_N"],
                     pq["E_inf_Pa"]["value"], prony["fit"]["rmse_N"]))
        v = {k: p["value"] for k, p in (pp | pq).items()}
        print(f"{path.name}: E0 = {v['E0_Pa']:.1f} +/- {pp['E0_Pa']['stderr']:.2g} Pa, beta = {v['beta']:.4f} "
              f"+/- {pp['beta']['stderr']:.2g}, RMSE {power['fit']['rmse_N'] * 1e9:.2f} nN | prony2 E_inf "
              f"{v['E_inf_Pa']:.1f} Pa, E1 {v['E1_Pa']:.1f} Pa tau1 {v['tau1_s']:.3g} s, "
              f"E2 {v['E2_Pa']:.1f} Pa tau2 {v['tau2_s']:.3g} s, RMSE {prony['fit']['rmse_N'] * 1e9:.2f} nN")
    E0 = [r[1] for r in rows]
    beta = [r[2] for r in rows]
    print(f"E0 {statistics.median(E0):.1f} Pa (range {min(E0):.1f}-{max(E0):.1f}), "
          f"beta {statistics.median(beta):.4f} (range {min(beta):.4f}-{max(beta):.4f}); "
          "prony2 RMSE / power RMSE median "
          f"{statistics.median(r[5] / r[3] for r in rows):.2f}")
    assert all(0.0 < b < 0.99 for b in beta) and all(e > 0 for e in E0)
