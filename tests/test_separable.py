"""Variable projection: a contact law over a baseline is fitted as a cost of the contact point
alone, and that fit is the general solver's optimum, found from anywhere, without scipy."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from rig.analysis.fitting import fit as fit_module
from rig.analysis.fitting import separable
from rig.analysis.fitting.fit import fit
from rig.analysis.workflow.inputs import load_inputs
from rig.models.catalogue import CATALOGUE, build_model
from tests.test_material import E_TRUE, ROOT, hertz_curve


def inputs(tmp_path, seed: int, indenter: str = "paraboloid:R=5um", **kw):
    path = hertz_curve(tmp_path / f"c{seed}.csv", seed, **kw)
    return load_inputs([str(path)], [], [], indenter=indenter)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("indenter", ["paraboloid:R=5um", "sphere:R=3um", "cone:half_angle=35deg"])
def test_the_projected_optimum_is_the_general_solvers(tmp_path, monkeypatch, seed, indenter):
    inp = inputs(tmp_path, seed, indenter)
    model = build_model("hertz", registry=inp.registry)
    assert separable.split(model) is not None
    fast = fit(model, inp.trials)
    monkeypatch.setattr(separable, "split", lambda m: None)
    general = fit(model, inp.trials)
    # the same least-squares problem: the same parameters to a small part of their errors, and
    # never a higher cost
    for name, v in general.values.items():
        assert abs(fast.values[name] - v) <= 1e-3 * general.stderr[name], (name, fast.values, general.values)
        assert fast.stderr[name] == pytest.approx(general.stderr[name], rel=1e-3)
    assert fast.overall.rmse_N <= general.overall.rmse_N * (1 + 1e-9)
    assert fast.adequate == general.adequate


@pytest.mark.parametrize("seed", range(3))
def test_the_answer_does_not_depend_on_where_the_fit_starts(tmp_path, seed):
    inp = inputs(tmp_path, seed)
    model = build_model("hertz", registry=inp.registry)
    travel = float(np.ptp(inp.trials[0].motion.x_m))
    answers = [fit(model, inp.trials, initial={"x_c_m": s * travel, "E_Pa": e}).values
               for s, e in ((-0.5, 10.0), (0.0, 1e6), (0.8, 1e3))]
    for a in answers[1:]:
        for k, v in answers[0].items():
            assert a[k] == pytest.approx(v, rel=1e-9, abs=1e-18)
    assert abs(answers[0]["E_Pa"] - E_TRUE) < 0.05 * E_TRUE


def test_a_curve_that_pulls_is_handed_to_the_general_solver(tmp_path, monkeypatch):
    """A force that falls with depth would need E < 0: the bound binds, the projection steps aside,
    and the general solver says the modulus sits at its bound."""
    inp = inputs(tmp_path, 0)
    pulled = replace(inp.trials[0], force_N=-inp.trials[0].force_N, scales=None)
    model = build_model("hertz", registry=inp.registry)
    handed = []
    real_solve = fit_module._solve
    monkeypatch.setattr(fit_module, "_solve", lambda *a, **k: handed.append(1) or real_solve(*a, **k))
    res = fit(model, [pulled])
    assert handed, "the general solver was not used"
    assert res.values["E_Pa"] < 1e-3 * E_TRUE
    assert any("E_Pa" in w and "bound" in w for w in res.warnings), res.warnings


def test_which_models_are_projected(tmp_path):
    reg = inputs(tmp_path, 0).registry
    assert separable.split(build_model("hertz", registry=reg)) is not None
    assert separable.split(build_model("hertz", ["drift"], registry=reg)) is not None
    for name, extra in (("hertz", ["relaxation"]), ("hertz", ["delay"]), ("hertz", ["contact_offset"]),
                        ("proposed", []), ("hooke", [])):
        assert separable.split(build_model(name, extra, registry=reg)) is None, (name, extra)
    assert separable.split(build_model("offset", registry=CATALOGUE)) == (None, [0])


@pytest.mark.parametrize("centre", [-0.7, 0.1, 0.85])
def test_the_scan_finds_the_deeper_of_two_valleys(centre):
    # a shallow valley at the far end of the range, the global one at `centre`
    cost = lambda c: min((c - centre) ** 2, 0.05 + 0.5 * (c - (0.9 if centre < 0 else -0.9)) ** 2)  # noqa: E731
    c = separable._minimise(cost, -1.0, 1.0)
    assert c == pytest.approx(centre, abs=1e-7)


def test_a_one_curve_hertz_analysis_does_not_import_scipy(tmp_path):
    """What makes `rig analyze --model hertz` quick to start: the fit needs numpy alone."""
    path = hertz_curve(tmp_path / "c.csv", 0)
    argv = ["analyze", str(path), "--model", "hertz", "--indenter", "paraboloid:R=5um"]
    code = ("import sys, rig.cli\n"
            f"rc = rig.cli.main({argv!r})\n"
            "print('scipy' in sys.modules, rc)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "E = 12" in out.stdout, out.stdout
    assert out.stdout.strip().splitlines()[-1] == "False 0", out.stdout[-500:]


def test_several_records_are_fitted_by_the_general_solver(tmp_path):
    """A contact point per record is more than one nonlinear parameter: the general solver fits
    them, each record placed, one modulus for all."""
    trials = [inputs(tmp_path, s).trials[0] for s in (0, 1)]
    reg = inputs(tmp_path, 2).registry
    model = build_model("hertz", registry=reg)
    res = fit(model, trials)
    assert separable.split(res.model) is None and res.model.records == 2
    assert {"x_c_m@0", "x_c_m@1", "offset_N@0", "offset_N@1"} <= set(res.values)
    assert abs(res.values["E_Pa"] - E_TRUE) < 2 * res.stderr["E_Pa"] and res.adequate
