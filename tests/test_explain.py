"""Diagnosis on data with hidden effects: the simulator switches an effect on as a physical
mechanism, the analysis is not told, and `--explain` must name it. Specimens and effect
sizes vary between cases (fixed seeds); the thresholds are the tool's own, not tuned here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rig.analysis.diagnosis.explain import auto, explain, format_explain
from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import load_trial
from rig.cli import main
from rig.models import CATALOGUE, build_model
from rig.recording.logs import export_csv, read_log
from rig.specs.config import RigConfig
from tests.conftest import FULL, PROTOCOLS, calibration_seeds, per_seed, run_sim

SPECIMENS = {
    "A": {},
    "B": {"k1_N_per_m3": 7.3e4, "tau1_s": 6.0, "k3_N_per_m": 20.0},
    "C": {"tau2_N_s_per_m2": 1.8e5, "k2_N_per_m2": 300.0, "tau1_s": 11.0},
}

CASES = {
    # name: (specimen, {effect: params}, seed of the paper-protocol runs)
    "relaxation2": ("A", {"relaxation2": {"k_m_N_per_m": 60.0, "tau_m_s": 40.0}}, 11),
    "drift": ("B", {"drift": {"rate_N_per_s": 0.004}}, 12),
    "offset": ("C", {"offset": {"force_N": 0.3}}, 13),
    "contact_offset": ("A", {"contact_offset": {"x0_mm": 1.5}}, 14),
    "delay": ("B", {"delay": {"delay_s": 0.08}}, 15),
    "friction": ("C", {"friction": {"force_N": 0.15}}, 16),
    "compliance": ("A", {"compliance": {"k_frame_N_per_m": 2000.0}}, 17),
    "relaxation2_small": ("C", {"relaxation2": {"k_m_N_per_m": 35.0, "tau_m_s": 25.0}}, 18),
    "delay_long": ("C", {"delay": {"delay_s": 0.12}}, 19),
}
SEEDS = (1, 2, 3, 4, 5)  # every case at several seeds: a case won by a hair flips with the seed
# Short trials keep five seeds of every case affordable: two speeds, a 30 s hold (60 s where
# the hidden relaxation is slow: a 40 s time constant needs a hold as long to show)
SPEEDS = ("1.5", "3")
HOLD_S = {"relaxation2": 60.0, "relaxation2_small": 60.0}
# How many of the SEEDS runs must name the hidden effect; below SEEDS only where the README
# says the effect at this size is not reliably found (measured, not tuned)
MIN_FOUND: dict[str, int] = {"contact_offset": 4, "relaxation2_small": 3}
# The suite runs the cases found in every seed, at its seeds (tests/conftest.py); a rate below
# every seed is a calibration, measured by the benchmark over all of them
RUN = calibration_seeds(SEEDS)
SUITE_CASES = sorted(CASES) if FULL else sorted(set(CASES) - set(MIN_FOUND))


def _protocol(speed: str, hold_s: float) -> str:
    return (f"name: ramp {speed} mm/s, hold {hold_s:g} s\nsteps:\n"
            f"  - ramp: {{to_mm: 30, speed_mm_s: {speed}}}\n  - hold: {{duration_s: {hold_s}}}\n"
            "  - return: {to_mm: 0, speed_mm_s: 5}\n")


def simulate(tmp, specimen: str, effects: dict, seed: int, speeds=("0.75", "1.5", "3"),
             hold_s: float | None = None) -> list:
    """Trials on the simulated rig: the paper's protocols, or ramps at `speeds` with a `hold_s` hold."""
    paths = []
    for i, v in enumerate(speeds):
        cfg = RigConfig()
        for k, val in SPECIMENS[specimen].items():
            setattr(cfg.sim.tissue, k, val)
        for name, params in effects.items():
            cls = type(getattr(cfg.sim.effects, name) or _default(name))
            setattr(cfg.sim.effects, name, cls(**params))
        cfg.sim.seed = seed * 10 + i
        proto = PROTOCOLS / f"paper-{v}mm_s.yaml" if hold_s is None else _protocol(v, hold_s)
        paths.append(run_sim(proto, cfg, tmp, name=f"{v}.mcap").log_path)
    return paths


def _default(name):
    from rig.sim import params as P

    return {"relaxation2": P.Relaxation2Params, "drift": P.DriftParams, "offset": P.OffsetParams,
            "contact_offset": P.ContactOffsetParams, "delay": P.DelayParams,
            "compliance": P.ComplianceParams, "friction": P.FrictionParams}[name]()


def _check_verdict(ex, hidden: str) -> str:
    """What the user reads: the "=>" line and the JSON `diagnosis` name the hidden effect first,
    with its evidence; empty when they do, else what was read instead."""
    v = json.loads(json.dumps(ex.verdict()))  # as `--json` prints it
    line = format_explain(ex).splitlines()[-1]
    expected = f"=> most likely missing: {hidden} (dBIC "
    if v["best"] != hidden or not line.startswith(expected) or v["text"] != ex.summary:
        return f"best {v['best']}: {line}"
    assert set(v) >= {"best", "lookalikes", "unexplained", "text"}
    assert isinstance(v["lookalikes"], list)
    assert v["unexplained"] is False or isinstance(v["unexplained"], str)
    assert ex.suggestions[0].effect == hidden  # the ranking agrees with the verdict
    assert "RMSE" in line and "error down" in line
    for pair in v["lookalikes"]:  # a look-alike comes after the answer, with its protocol
        assert hidden in pair["effects"] and pair["separate_with"]
        assert "; look-alike: " in line and "to separate them" in line
    if v["unexplained"]:
        assert "still unexplained" in line
    else:  # adding it brings the error to within 1.2x the sensor noise
        assert ex.suggestions[0].rmse_N <= 1.2 * ex.base.noise_N
    return ""


def _one_seed(seed: int, case: str, tmp_path: Path) -> str:
    """The verdict on one seed of a case: '' when it names the hidden effect, else what it read."""
    specimen, effects, _ = CASES[case]
    (hidden,) = effects
    tmp = tmp_path / str(seed)
    tmp.mkdir()
    paths = simulate(tmp, specimen, effects, seed, SPEEDS, HOLD_S.get(case, 30.0))
    trials = [load_trial(p) for p in paths]
    base = fit(build_model("proposed"), trials)
    assert not base.adequate
    ex = explain(base, dict(CATALOGUE))
    miss = _check_verdict(ex, hidden)
    return (f"seed {seed}: {miss}; ranked {[(s.effect, round(s.delta_bic, 1)) for s in ex.ranked[:3]]}"
            if miss else "")


@pytest.mark.parametrize("case", SUITE_CASES)
def test_hidden_effect_is_named_by_the_verdict(case, tmp_path):
    misses = [m for m in per_seed(_one_seed, RUN, case, tmp_path) if m]
    found = len(RUN) - len(misses)
    assert found >= MIN_FOUND.get(case, len(RUN)), f"{case}: found {found}/{len(RUN)}\n" + "\n".join(misses)


def test_no_hidden_effect_control_stays_clean(tmp_path):
    trials = [load_trial(p) for p in simulate(tmp_path, "B", {}, 21)]
    base = fit(build_model("proposed"), trials)
    ex = explain(base, dict(CATALOGUE))
    assert base.adequate
    assert ex.suggestions == []
    assert all(s.rmse_drop <= 0.05 for s in ex.ranked)
    assert "adequate" in ex.summary
    assert ex.verdict()["best"] is None and ex.verdict()["unexplained"] is False


def test_auto_finds_two_hidden_effects(tmp_path):
    effects = {"drift": {"rate_N_per_s": 0.003}, "friction": {"force_N": 0.2}}
    trials = [load_trial(p) for p in simulate(tmp_path, "A", effects, 22)]
    steps = auto(fit(build_model("proposed"), trials), dict(CATALOGUE))
    final = steps[-1]["fit"]
    assert final.adequate
    assert {"drift", "friction"} <= set(final.model.effect_names)
    rmse = [s["fit"].overall.rmse_N for s in steps]
    assert rmse[-1] < rmse[0] and rmse[-1] <= 1.2 * final.noise_N


PUMP = '''
import numpy as np
from rig.models import Param, effect

PUMP_HZ = 0.51  # the inflation pump's stroke rate, from its data sheet


@effect(stage="sensor", params=[Param("pump_N", "N", 0.05, -1.0, 1.0),
                                Param("pump_phase", "rad", 0.0, -3.2, 3.2)],
        equation="a sin(2 pi f_pump t + phase)", signature="residual oscillating at the pump's rate")
def pump(m, force, pump_N, pump_phase):
    return pump_N * np.sin(2 * np.pi * PUMP_HZ * m.t_s + pump_phase)
'''


def test_plugin_effect_not_in_the_catalogue(tmp_path, capsys):
    """An inflation pump ripples the force: without the plugin the model is inadequate and the
    residual shows where; with it, --explain names the plugin effect."""
    logs = simulate(tmp_path, "A", {}, 23)
    csvs = []
    for k, p in enumerate(logs):
        log = read_log(p)
        # the pump runs at 0.51 Hz, started with each trial
        log.samples["force_N"] = log.samples["force_N"] + 0.12 * np.sin(2 * np.pi * 0.51 * log.samples["t_s"])
        out = tmp_path / f"pumped{k}.csv"
        export_csv(log, out)
        csvs.append(str(out))
    plugin = tmp_path / "pump.py"
    plugin.write_text(PUMP)
    assert main(["analyze", *csvs, "--explain", "--json"]) == 0
    without = json.loads(capsys.readouterr().out)
    assert without["adequate"] is False
    assert all(s["rmse_drop"] < 0.3 for s in without["suggestions"])  # nothing in the catalogue fits it
    assert max(v["rmse_N"] for v in without["phases"].values()) > 1.2 * without["fit"]["noise_N"]
    # whatever ranks first, the verdict says a structured residual is left
    assert isinstance(without["diagnosis"]["unexplained"], str) and without["diagnosis"]["unexplained"]
    assert main(["analyze", *csvs, "--explain", "--plugin", str(plugin), "--json"]) == 0
    with_plugin = json.loads(capsys.readouterr().out)
    assert with_plugin["suggestions"][0]["effect"] == "pump"
    assert with_plugin["diagnosis"]["best"] == "pump"
    assert with_plugin["diagnosis"]["text"].startswith("most likely missing: pump (dBIC ")
    assert with_plugin["diagnosis"]["unexplained"] is False
    assert with_plugin["suggestions"][0]["rmse_N"] <= 1.2 * with_plugin["fit"]["noise_N"]


def test_explain_and_auto_on_the_command_line(tmp_path, capsys):
    logs = simulate(tmp_path, "B", {"drift": {"rate_N_per_s": 0.004}}, 24)
    rep = tmp_path / "rep"
    assert main(["analyze", *map(str, logs), "--explain", "--auto", "--report", str(rep)]) == 0
    text = text_explain = capsys.readouterr().out
    assert "=> most likely missing: drift (dBIC " in text
    assert "+drift" in text and "final model" in text
    assert (rep / "auto_steps.png").exists()
    assert main(["analyze", *map(str, logs), "--add", "drift"]) == 0
    text = capsys.readouterr().out
    assert "adding drift: before and after" in text and "error falls by" in text
    assert main(["analyze", *map(str, logs), "--explain", "--json"]) == 0
    verdict = json.loads(capsys.readouterr().out)["diagnosis"]
    assert verdict["best"] == "drift" and verdict["unexplained"] is False
    assert verdict["text"].startswith("most likely missing: drift (dBIC ")
    assert "=> " + verdict["text"] in text_explain


def test_look_alikes_on_one_ramp_are_reported_as_such(tmp_path):
    """Frame compliance against the cubic stiffness on a single ramp: no confident wrong answer,
    but the pair, and the protocol that would separate them."""
    cfg_effects = {"compliance": {"k_frame_N_per_m": 2000.0}}
    logs = simulate(tmp_path, "A", cfg_effects, 27)
    ex = explain(fit(build_model("proposed"), [load_trial(logs[2])]), dict(CATALOGUE))  # the 3 mm/s ramp
    assert ex.suggestions == [] or ex.suggestions[0].effect == "compliance"
    assert ex.indistinguishable, ex.summary
    pair = ex.indistinguishable[0]
    assert set(pair["effects"]) == {"compliance", "poly_elastic"}
    assert "depth" in pair["separate_with"]
    assert "cannot be told apart" in ex.summary
    v = ex.verdict()
    assert v["best"] in (None, "compliance") and v["lookalikes"] == ex.indistinguishable
    if v["best"] is None:  # no confident answer: the note is the verdict
        assert ex.summary.startswith(("the model is adequate", "the model is NOT adequate"))
    else:  # the answer first, the look-alike after it
        assert ex.summary.startswith("most likely missing: compliance")
        assert "; look-alike: poly_elastic" in ex.summary
