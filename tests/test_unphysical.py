"""Unphysical means significantly so: a parameter that must not be negative (a damping, a
stiffness) is physically meaningless only when it is below zero by more than two of its own
standard errors. Before, any negative value rejected a candidate effect: a damping that a spring's
record leaves at zero came out slightly negative on a third of the seeds, and `--explain` threw
the candidate away as "physically meaningless". The other way round, a standard error that spans
zero does not make a term's sign unsettled: a Hunt-Crossley damping that takes most of a real AFM
curve's ramp error with its amplitude negative is meaningless, whatever its standard error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rig.analysis.diagnosis.explain import meaningless
from rig.analysis.fitting.fit import UNPHYSICAL_SE, fit
from rig.analysis.trials.data import prepare
from rig.cli import main
from rig.models import build_model
from rig.records.record import Record


def record(seed: int, damping_N_s_per_m: float = 0.0) -> list:
    """A ramp to 3 mm at 2 mm/s and a hold, 100 Hz: a spring of 50 N/m, `damping` on the velocity,
    noise of 10 mN."""
    rng = np.random.default_rng(seed)
    dt = 0.01
    t = np.arange(0.0, 20.0, dt)
    x = np.minimum(2e-3 * t, 3e-3)
    v = np.where(t < 1.5, 2e-3, 0.0)
    f = 50.0 * x + damping_N_s_per_m * v + 0.01 * rng.normal(size=len(t))
    return [prepare(Record(f"spring-{seed}", "csv", t, x, f))]


def test_a_damping_negative_within_its_error_is_not_meaningless():
    slight = 0
    for seed in range(12):
        trials = record(seed)
        base, res = fit(build_model("hooke"), trials), fit(build_model("voigt"), trials)
        eta, se = res.values["eta_N_s_per_m"], res.stderr["eta_N_s_per_m"]
        assert eta + UNPHYSICAL_SE * se > 0, (seed, eta, se)  # the truth is zero: within the errors
        if eta < 0:
            slight += 1
            assert meaningless(res, base) == "", (seed, eta, se)
            said = [w for w in res.warnings if w.startswith("viscous.eta_N_s_per_m is negative")]
            assert said and "consistent with a physical value" in said[0], res.warnings
            assert not any("meaningless" in w for w in res.warnings), res.warnings
    assert slight >= 2, slight  # the case this is about happened


def test_a_damping_negative_beyond_its_error_is_meaningless_and_says_why():
    trials = record(0, damping_N_s_per_m=-8.0)
    base, res = fit(build_model("hooke"), trials), fit(build_model("voigt"), trials)
    eta, se = res.values["eta_N_s_per_m"], res.stderr["eta_N_s_per_m"]
    assert eta + UNPHYSICAL_SE * se < 0, (eta, se)
    why = meaningless(res, base)
    assert why.startswith("viscous.eta_N_s_per_m is negative") and "beyond 2 standard errors" in why, why
    assert why.endswith("physically meaningless"), why


AFM = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "afm-fd"
MAP = AFM / "fmt-jpk-fd_map2x2_extracted.jpk-force-map"
CURVE = ["--curve", "3", "--model", "hertz", "--indenter", "paraboloid:R=10um", "--segment", "approach"]


@pytest.mark.skipif(not MAP.is_file(), reason=f"the real measurement is not at {MAP}")
def test_a_negative_damping_the_curve_needs_is_meaningless_though_its_error_spans_zero(capsys):
    pytest.importorskip("afmformats", reason="reading JPK maps needs the afm extra (afmformats)")
    import json

    # the case: fitted with Hunt-Crossley, its amplitude b comes out negative within two standard
    # errors (b trades off with its exponent n), so the standard error alone calls it physical
    assert main(["analyze", str(MAP), *CURVE, "--add", "relaxation", "--add", "hc_damping", "--json"]) == 0
    b = json.loads(capsys.readouterr().out)["parameters"]["b_N_s_per_m_n1"]
    assert b["value"] < 0 and b["value"] + UNPHYSICAL_SE * b["stderr"] > 0, b

    # yet the term is needed (without it the ramp error is ten times larger): meaningless, said so
    assert main(["analyze", str(MAP), *CURVE, "--add", "relaxation", "--explain"]) == 0
    text = capsys.readouterr().out
    row = next(line for line in text.splitlines() if line.strip().startswith("hc_damping"))
    assert "hc_damping.b_N_s_per_m_n1 is negative" in row and "its term is needed" in row, row
    assert "physically meaningless" in row and "consistent with a physical value" not in row, row
    verdict = next(line for line in text.splitlines() if line.startswith("=> "))
    assert not verdict.startswith("=> most likely missing: hc_damping"), verdict

    # and --auto does not build it into the curve's model (before, its second step did)
    assert main(["analyze", str(MAP), *CURVE, "--auto", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert "hc_damping" not in out["auto_final"]["effects"], out["auto_final"]["effects"]
    assert not any("consistent with a physical value" in (s["why"] or "") for s in out["auto"]), out["auto"]
