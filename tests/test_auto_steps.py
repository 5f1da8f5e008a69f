"""`--auto` and `--explain` on what the user reads: a suggestion whose fit turns any of the model's
parameters negative is not made, a drop is judged at the simpler model's N_eff, and a bound on
the steps says it ended the search. That a step is no worse than its model fitted on its own is
checked on the real gel, where a step once stayed in the first step's basin, in
tests/bench/test_bench_auto_steps.py (minutes long); `refit` keeps that fit among its candidates."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rig.cli import main

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
GEL = REALDATA / "polymergel-creep.jpk-force"


def _jpk(path: Path) -> None:
    if not path.is_file():
        pytest.skip(f"the real measurement is not at {path}")
    pytest.importorskip("afmformats", reason="reading JPK files needs the afm extra (afmformats)")


def _run(capsys, *args: str) -> dict:
    # the gel's force form, where these cases were measured (creep form: tests/test_creep_form.py)
    assert main(["analyze", *args, "--form", "force", "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_no_suggestion_turns_a_parameter_of_the_model_negative(capsys):
    """Hunt-Crossley on the gel: fractional relaxation was named first although its fit turns the
    base model's damping (hc_damping.b, not a parameter of the effect) negative. It may be offered
    only as a swap, with the damping it turns negative dropped, and every suggestion's model is
    physical when fitted on its own."""
    _jpk(GEL)
    base = _run(capsys, str(GEL), "--model", "hunt_crossley", "--explain")
    assert not any("negative" in w for w in base["warnings"])  # the base model's fit is physical
    named = {s["effect"]: s for s in base["suggestions"]}
    assert named
    frac = named.get("fractional_relaxation")
    assert frac is None or frac["dropped"] == ["hc_damping"], frac
    if base["diagnosis"]["best"] == "fractional_relaxation":
        said = base["diagnosis"]["text"]
        assert said.startswith("most likely missing: fractional_relaxation, with hc_damping dropped"), said
    # what it was offered without the damping for: fitted with it, the model's damping turns negative
    added = _run(capsys, str(GEL), "--model", "hunt_crossley", "--add", "fractional_relaxation")
    negative = [w for w in added["warnings"] if w.startswith("hc_damping.b_N_s_per_m_n1 is negative")]
    assert negative, added["warnings"]
    # and the answer it names is physical when fitted on its own, as its evidence says to fit it
    first = base["suggestions"][0]
    how = first["why"].rpartition("(fit it: ")[2].rstrip(")").split() if first["dropped"] else \
        ["--model", "hunt_crossley", "--add", first["effect"]]
    best = _run(capsys, str(GEL), *how)
    assert not any("is negative" in w for w in best["warnings"]), (first["effect"], best["warnings"])


def test_a_stand_in_is_dropped_at_the_simpler_models_count(tmp_path, monkeypatch):
    """Drift and friction hidden together; the first step is made to take a stand-in
    (compliance, which explain ranks seventh here). Once the true effects come in, the stand-in
    is dropped (here by a swap: an offset in its place), and the drop is judged as every
    delta_BIC is: at the simpler model's N_eff (on the previous main it was the fuller model's,
    which the README did not say)."""
    from dataclasses import replace

    from rig.analysis.diagnosis import explain as explain_module
    from rig.analysis.fitting.fit import fit
    from rig.analysis.stats.criterion import delta_bic
    from rig.analysis.trials.data import load_trial
    from rig.models import CATALOGUE, build_model
    from tests.test_explain import simulate

    real = explain_module.explain
    calls = {"n": 0}

    def first_takes_a_stand_in(base, registry, trials=None):
        ex = real(base, registry, trials)
        calls["n"] += 1
        if calls["n"] == 1:
            stand_in = next(s for s in ex.ranked if s.effect == "compliance")
            ex = replace(ex, suggestions=[stand_in])
        return ex

    monkeypatch.setattr(explain_module, "explain", first_takes_a_stand_in)
    effects = {"drift": {"rate_N_per_s": 0.003}, "friction": {"force_N": 0.2}}
    trials = [load_trial(p) for p in simulate(tmp_path, "A", effects, 22)]
    steps = explain_module.auto(fit(build_model("proposed"), trials), dict(CATALOGUE))
    stand_in = steps[1]["added"]
    assert stand_in == "compliance"
    removals = [i for i, s in enumerate(steps) if s["removed"] == stand_in]
    assert removals, [(s["added"], s["removed"]) for s in steps]
    i = removals[0]
    fuller, slimmer = steps[i - 1]["fit"], steps[i]["fit"]
    assert stand_in in fuller.model.effect_names and stand_in not in slimmer.model.effect_names
    assert slimmer.n_eff != pytest.approx(fuller.n_eff, rel=1e-3)  # the two counts tell the rules apart
    rss = [float(sum((r ** 2).sum() for r in f.residuals)) for f in (fuller, slimmer)]
    dk = len(fuller.model.params) - len(slimmer.model.params)
    assert steps[i]["delta_bic"] == pytest.approx(-delta_bic(rss[0] / rss[1], dk, slimmer.n_eff), rel=1e-9)
    assert steps[i]["delta_bic"] < 0  # what the user reads: the simpler model is better
    assert {"drift", "friction"} <= set(steps[-1]["fit"].model.effect_names)


def test_auto_steps_bounds_the_search_and_says_where_it_stopped(tmp_path, capsys):
    """Two effects hidden, one step allowed: the search says it was the bound that stopped it,
    not the record; the bound alone, without --auto, is refused before any work."""
    from tests.test_explain import simulate

    logs = [str(p) for p in simulate(tmp_path, "A", {"drift": {"rate_N_per_s": 0.003},
                                                     "friction": {"force_N": 0.2}}, 22)]
    assert main(["analyze", *logs, "--auto-steps", "1"]) == 2
    assert "--auto-steps N bounds --auto's search: give --auto with it" in capsys.readouterr().err
    steps = _run(capsys, *logs, "--auto", "--auto-steps", "1")["auto"]
    assert [s["step"] for s in steps] == [0, 1], steps
    assert steps[-1]["stopped"] == ("stopped after 1 step, the most allowed (--auto-steps); the model "
                                    "is not adequate yet")


QI = REALDATA / "afm-fd" / "fmt-jpk-fd_2020.02.07-16.29.05.036.jpk-qi-data"


def test_auto_goes_past_an_adequate_model_while_explain_still_names_an_effect(capsys):
    """A real JPK QI curve whose Hertz fit is adequate: `--explain` names a drift on decisive
    evidence, so `--auto` must not stop at the adequate model before it; its final model is one
    on which `--explain` names nothing, and the text says what it added."""
    _jpk(QI)
    hertz = ["--curve", "2", "--model", "hertz", "--indenter", "paraboloid:R=10um", "--segment", "approach"]
    assert main(["analyze", str(QI), *hertz, "--explain", "--json"]) == 0
    ex = json.loads(capsys.readouterr().out)
    assert ex["adequate"] and ex["diagnosis"]["best"] in ("drift", "tilt")
    assert main(["analyze", str(QI), *hertz, "--auto", "--json"]) == 0
    auto = json.loads(capsys.readouterr().out)
    added = [s["added"] for s in auto["auto"][1:] if s["added"]]
    assert added and added[0] == ex["diagnosis"]["best"]
    own = ("elastic_contact", "contact_point", "offset")
    adds = [a for e in auto["auto_final"]["effects"] if e not in own for a in ("--add", e)]
    assert main(["analyze", str(QI), *hertz, *adds, "--explain", "--json"]) == 0
    assert not json.loads(capsys.readouterr().out)["suggestions"]
    assert main(["analyze", str(QI), *hertz, "--auto"]) == 0
    text = capsys.readouterr().out
    assert f"+{added[0]}" in text and "final model" in text and "adequate" in text
