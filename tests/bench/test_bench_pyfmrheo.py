"""rig's power-law Ting fit (ting_power) beside PyFMRheo's Ting fit, on the same samples:

    python -m pytest -p no:cacheprovider tests/bench/test_bench_pyfmrheo.py -s -q

PyFMRheo (`pip install pyfmrheo`) is a benchmark-only peer: imported here and in pyfmrheo_table.py
(which holds the records, the two fits and the table; see its docstring for PyFMRheo's API), never
by `rig`. The must-show: E0 and beta within 5 %, or the difference explained by a measurement.

Measured while writing this (PyFMRheo 0.1.3):
- its analytical Ting model, evaluated at the true parameters against the independent quadrature
  of tests/test_viscoelastic.py, is exact while loading (1e-15 of the peak) and off after the turn
  by up to 6.5 % of the peak (approach-retract, beta 0.2), 61 % (beta 0.4), 16 % and 92 % (a hold,
  v0r -> 0): its 2F1 is Butler and Wood's saddle-point approximation. With scipy's exact 2F1 in
  its place the same closed form is within 3e-14 of the quadrature on the approach-retract and
  3.4e-9 on the hold (what v0r = 1e-9 v0t, standing for the hold, leaves);
- so where only the loading is fitted the two fits coincide (0.00 %); where the retract or the
  hold is fitted PyFMRheo's beta comes out low (simulated, beta 0.2: -15 % approach-retract, -31 %
  ramp-hold, with 2.4x and 3.5x rig's residual on the same samples; beta 0.4 worse; the oocytes'
  ramp-hold: -26 % to -29 %), while its own model with the exact 2F1 agrees with rig within 2.7 %
  and leaves no lower a residual than rig's. On the oocytes, which are not a power law, PyFMRheo's
  approximated curve (a different law) leaves the lower residual on some curves (11 of 15).
- all 15 oocytes (`python tests/bench/pyfmrheo_table.py --all`): ramp-hold E0 within -1.65 % to
  +2.31 % of rig's (rig 459-603 Pa), beta -25.8 % to -28.9 % (rig 0.157-0.244, PyFMRheo 0.116-0.173),
  every one explained by the 2F1; the extend alone leaves beta undetermined on every one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyfmrheo", reason="pyfmrheo is not installed (pip install pyfmrheo): the peer this "
                    "benchmark compares rig's Ting fit with")

from tests.bench import pyfmrheo_table as bench
from tests.test_viscoelastic import DT, SURFACE, V, reference_force
from tests.test_viscoelastic import R as SIM_R


def _judge(rows: list[dict], allowed: tuple[str, ...]) -> None:
    print("\n" + bench.markdown(rows))
    for r in rows:
        if r["agree"]:
            continue
        assert bench.why(r) in allowed, (r["case"], r)


@pytest.mark.parametrize("beta", [0.2, 0.4])
@pytest.mark.parametrize("protocol", ["ar", "rh"])
def test_pyfmrheo_ting_model_against_the_quadrature(beta, protocol):
    """The difference's cause, measured: PyFMRheo's closed form at the true parameters against
    the independent quadrature, with its own 2F1 and with scipy's exact one."""
    from pyfmrheo.models.ting import TingModel

    truth = {"E0_Pa": 1e3, "beta": beta}
    end = {"rh": 5.0, "ar": 3.0}[protocol]
    t = np.arange(0.0, end, DT)
    touch = SURFACE / V
    top = 1.5 * V - SURFACE
    knots = ([touch, 1.5, end], [0.0, top, top]) if protocol == "rh" else \
        ([touch, 1.5, 3.0 - touch, end], [0.0, top, 0.0, 0.0])
    F = reference_force(t, *knots, truth, "paraboloid")
    turn = round(1.5 / DT)
    v0r = V if protocol == "ar" else V * bench.HOLD
    errs = {}
    for exact in (False, True):
        m = TingModel("paraboloid", SIM_R, "analytical")
        with bench.exact_2f1(exact), np.errstate(all="ignore"):
            G = m.model(t, 1e3, touch, beta, 0.0, bench.T0, F, np.interp(t, *knots), "analytical", 0.0,
                        idx_tm=turn, v0t=V, v0r=v0r)
        err = np.abs(G - F) / np.max(F)
        errs[exact] = (float(np.max(err[t <= 1.5])), float(np.max(err[t > 1.5])))
    print(f"\nPyFMRheo's Ting force, {protocol} beta {beta}: max |error| / peak while loading "
          f"{errs[False][0]:.1e}, after the turn {errs[False][1]:.3g} (its 2F1), "
          f"{errs[True][1]:.1e} (exact 2F1)")
    assert errs[False][0] < 1e-9 and errs[True][0] < 1e-9  # loading: exact in both
    assert errs[True][1] < 1e-7  # the closed form itself is right (the hold: v0r = 1e-9 v0t gives 3e-9)
    assert errs[False][1] > 0.05  # the approximation of 2F1 is what is off (6.5 % to 92 % of the peak)


def test_simulated_curves_of_known_truth(tmp_path):
    """tests/test_viscoelastic.py's generator (paraboloid R = 5 um, E0 1 kPa, beta 0.2 and 0.4,
    seeds 0-2): the loading alone ("ramp"), approach-retract ("ar") and ramp-hold ("rh")."""
    rows = bench.simulated_rows(tmp_path)
    _judge(rows, ("2F1",))
    for r in rows:
        # rig recovers the truth within 3 standard errors; PyFMRheo's own model with the exact 2F1
        # lands on rig's fit; where the power law is the truth rig's residual is the lower one
        truth = r["truth"]
        assert abs(r["rig_E0"] - truth["E0_Pa"]) < 3 * r["rig_E0_se"], r
        assert abs(r["rig_beta"] - truth["beta"]) < 3 * r["rig_beta_se"], r
        assert r["exact_agree"], r
        assert r["rmse_rig"] <= r["rmse_pyfm"] * 1.001, r
        if r["case"].split()[2] == "ramp":  # the loading alone: PyFMRheo's model is exact there
            assert r["agree"], r


@pytest.mark.skipif(not bench.OOCYTES, reason="the shared oocyte records are absent (../shared/realdata/)")
def test_real_oocyte_stress_relaxation(tmp_path):
    """cell1-0001..0005 (R = 10 um paraboloid, Poisson 0.5), read with afmformats (pyfmreader 0.1.3,
    PyFMRheo's reader, fails on them): the extend alone and the ramp-hold (pause, extend, 30 s pause)."""
    pytest.importorskip("afmformats", reason="afmformats reads the JPK files")
    rows = bench.real_rows(tmp_path, bench.OOCYTES[:5])
    _judge(rows, ("2F1", "undetermined"))
    for r in rows:
        if r["case"].endswith("ramp-hold"):
            # the same model (PyFMRheo's with the exact 2F1): within 5 %, and rig's fit no worse
            assert r["exact_agree"], r
            assert r["rmse_rig"] <= r["rmse_exact"] * 1.001, r
    shipped = [r["case"] for r in rows if r["rmse_rig"] > r["rmse_pyfm"]]
    print(f"PyFMRheo as shipped leaves the lower residual on: {', '.join(shipped) or 'none'} (the oocytes are "
          "not a power law; its approximated hold is a different law)")


if __name__ == "__main__":
    raise SystemExit(pytest.main([str(Path(__file__)), "-s", "-q", "-p", "no:cacheprovider"]))
