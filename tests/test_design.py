"""Settling a tie on the simulator: a frame spring (2000 N/m) hidden in one ramp-and-hold
is a look-alike of the cubic stiffness on that trial; `--design` writes a protocol, the
simulated rig with the same hidden frame runs it, and the two trials analysed together name
the frame with no look-alike left. Repeating the original protocol instead does not."""

from __future__ import annotations

import json

import pytest

from rig.analysis.diagnosis.explain import explain
from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import load_trial
from rig.cli import main
from rig.models import CATALOGUE, build_model
from rig.specs.config import RigConfig, load_config
from rig.specs.protocol import load_protocol
from tests.conftest import calibration_seeds
from tests.test_explain import simulate

HIDDEN = {"compliance": {"k_frame_N_per_m": 2000.0}}
PAIR = {"compliance", "poly_elastic"}
SEEDS = (1, 2, 3, 4, 5)


def _one_ramp(tmp, effects: dict, seed: int):
    """A 3 mm/s ramp to 30 mm with a 10 s hold: one trial, one speed, one depth."""
    return simulate(tmp, "A", effects, seed, speeds=("3",), hold_s=10.0)[0]


def _run(protocol, tmp, seed: int, capsys, hidden: str = "compliance: {k_frame_N_per_m: 2000}") -> str:
    """`rig run` on the built-in simulated rig with the same hidden effect; the log's path."""
    cfg = tmp / "hidden.yaml"
    cfg.write_text(f"sim: {{seed: {seed}, effects: {{{hidden}}}}}\n")
    assert main(["run", str(protocol), "--config", str(cfg), "--speed", "0", "--quiet", "--out", str(tmp)]) == 0
    out = capsys.readouterr().out
    assert "trial completed" in out
    return next(line.split("log: ", 1)[1] for line in out.splitlines() if line.startswith("log: "))


@pytest.mark.parametrize("seed", calibration_seeds(SEEDS))
def test_design_separates_a_tie_on_the_simulator(seed, tmp_path, capsys):
    log = str(_one_ramp(tmp_path, HIDDEN, seed))
    target = tmp_path / "separate.yaml"
    assert main(["analyze", log, "--explain", "--design", str(target), "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    # the tie, as the user reads it
    tie = first["diagnosis"]["lookalikes"]
    assert len(tie) == 1 and set(tie[0]["effects"]) == PAIR
    assert "cannot be told apart" in first["diagnosis"]["text"]
    # the protocol: written, in the rig's format, within the rig's limits, and says why
    d = first["design"]
    assert d["file"] == str(target) and set(d["effects"]) == PAIR
    text = target.read_text()
    proto = load_protocol(target, RigConfig())  # refused here if beyond the rig's limits, as `rig run` does
    assert proto.name.startswith("separate compliance from poly_elastic")
    assert f"{d['difference_over_noise']:.1f}x the noise" in text
    assert f"{d['separation_over_noise']:.1f}x the noise" in text
    assert d["predicted_peak_N"] * 1.25 <= min(RigConfig().limits.max_force_N, proto.limits.max_force_N)
    # predicted: the model without the frame, refitted to both, misses the new trial by more than the noise
    assert d["wrong_model"] == "the model without compliance"
    assert d["separation_over_noise"] > 1.0
    assert d["separation_N"] == max(c["separation_N"] for c in d["candidates"] if c["separation_N"] is not None)
    assert main(["check", str(target)]) == 0
    assert "OK" in capsys.readouterr().out
    # run it on the simulated rig with the same hidden frame, then analyse both trials together
    new = _run(target, tmp_path, seed * 10 + 7, capsys)
    assert main(["analyze", log, new, "--explain", "--json"]) == 0
    joint = json.loads(capsys.readouterr().out)["diagnosis"]
    assert joint["best"] == "compliance", joint["text"]
    assert joint["lookalikes"] == []
    assert joint["text"].startswith("most likely missing: compliance (dBIC ")
    assert "look-alike" not in joint["text"] and "cannot be told apart" not in joint["text"]


def test_design_in_text_within_a_smaller_rig_and_repeating_the_protocol_does_not_settle_it(tmp_path, capsys):
    log = str(_one_ramp(tmp_path, HIDDEN, 4))
    target = tmp_path / "separate.yaml"
    rig = tmp_path / "rig.yaml"  # less travel and a lower force limit than the built-in rig
    rig.write_text("limits: {max_force_N: 12, travel_mm: [-5, 36]}\n")
    assert main(["analyze", log, "--explain", "--design", str(target), "--config", str(rig)]) == 0
    out = capsys.readouterr().out
    verdict = next(line for line in out.splitlines() if line.startswith("=> "))
    assert "compliance and poly_elastic cannot be told apart" in verdict
    design = out[out.index("\ndesign: "):]
    assert "design: to tell compliance from poly_elastic, run '" in design and str(target) in design
    assert "the model without compliance still misses it by" in design
    proto = load_protocol(target, load_config(rig))  # within this rig's limits
    assert max(s.to_mm for s in proto.steps if s.kind == "ramp") <= 36
    assert proto.limits.max_force_N <= 12
    peak = float(design.split("peak force about ", 1)[1].split(" N", 1)[0])
    assert peak * 1.25 <= 12
    # the same protocol again, on the same specimen: more data, same tie
    (tmp_path / "again").mkdir()
    again = _one_ramp(tmp_path / "again", HIDDEN, 40)
    trials = [load_trial(log), load_trial(again)]
    ex = explain(fit(build_model("proposed"), trials), dict(CATALOGUE))
    assert [set(p["effects"]) for p in ex.lookalikes] == [PAIR], ex.summary


def test_design_settles_an_answer_and_its_look_alike(tmp_path, capsys):
    """Another kind of tie: a drift is the answer but an offset explains the short trial as
    well (neither model contains the other); the design rests out of contact before and
    after the trial, where a drift shows and an offset does not change."""
    hidden = {"drift": {"rate_N_per_s": 0.004}}
    log = str(_one_ramp(tmp_path, hidden, 5))
    target = tmp_path / "separate.yaml"
    assert main(["analyze", log, "--explain", "--design", str(target), "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["diagnosis"]["best"] == "drift"
    assert [set(p["effects"]) for p in first["diagnosis"]["lookalikes"]] == [{"drift", "offset"}]
    d = first["design"]
    assert d["protocol"] == "rest before and after" and d["separation_over_noise"] > 0.3
    steps = load_protocol(target, RigConfig()).steps
    assert [s.kind for s in steps] == ["hold", "ramp", "hold", "return", "hold"]
    new = _run(target, tmp_path, 57, capsys, "drift: {rate_N_per_s: 0.004}")
    assert main(["analyze", log, new, "--explain", "--json"]) == 0
    joint = json.loads(capsys.readouterr().out)["diagnosis"]
    assert joint["best"] == "drift" and joint["lookalikes"] == [], joint["text"]
    assert joint["text"].startswith("most likely missing: drift (dBIC ") and "look-alike" not in joint["text"]


def test_without_a_tie_there_is_nothing_to_settle(tmp_path, capsys):
    log = str(_one_ramp(tmp_path, {}, 5))  # nothing hidden: the model is adequate, no look-alike
    target = tmp_path / "separate.yaml"
    assert main(["analyze", log, "--explain", "--design", str(target)]) == 0
    out = capsys.readouterr().out
    assert "design: nothing to settle: the diagnosis has no look-alikes (no protocol written)" in out
    assert not target.exists()
    assert main(["analyze", log, "--explain", "--design", str(target), "--json"]) == 0
    j = json.loads(capsys.readouterr().out)
    assert j["diagnosis"]["lookalikes"] == []
    assert j["design"] == {"file": None, "text": "nothing to settle: the diagnosis has no look-alikes "
                                                 "(no protocol written)"}
    assert not target.exists()


@pytest.mark.parametrize("argv, message", [
    (["--design", "{tmp}/d.yaml"], "--design needs --explain"),
    (["--explain", "--design", "{tmp}/missing/d.yaml"], "not a file in an existing directory"),
    (["--explain", "--design", "{tmp}"], "not a file in an existing directory"),
    (["--explain", "--config", "{tmp}/rig.yaml"], "it needs --design"),
])
def test_bad_design_arguments_get_one_line(argv, message, tmp_path, capsys):
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert main(["analyze", str(tmp_path / "none.mcap"), *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and err.startswith("rig analyze: error: ")


def test_a_slowed_candidate_fills_the_time_given_along_the_same_path():
    """`slowed` keeps a candidate's path, holds and return, slows its ramps by one factor so that
    the whole takes the time given (never longer), never below SLOWEST of their speed, and leaves
    a candidate that already takes that long alone."""
    from rig.analysis.diagnosis.design import SLOWEST, Shape, rig_candidates, slowed

    config = RigConfig()
    shape = Shape(depth_m=0.03, speed_m_s=0.0015, hold_s=30.0, return_m_s=0.005, duration_s=60.0)
    cands = {c.name: c for c in rig_candidates(shape, config)}
    for name in ("ramp at 0.75 mm/s", "staircase", "load-unload cycles"):
        c = cands[name]
        took = float(c.trial.motion.t_s[-1])
        s = slowed(c, took + 40.0, config)
        assert s is not None and took + 30.0 <= float(s.trial.motion.t_s[-1]) <= took + 40.0
        assert [k for k, _ in s.steps] == [k for k, _ in c.steps]
        ratios = {round(b["speed"] / a["speed"], 9) for (k, a), (_, b) in zip(c.steps, s.steps, strict=True)
                  if k == "ramp"}
        assert len(ratios) == 1 and SLOWEST <= ratios.pop() < 1.0
        assert all(a == b for (k, a), (_, b) in zip(c.steps, s.steps, strict=True) if k != "ramp")
        assert float(s.trial.motion.x_m.max()) == float(c.trial.motion.x_m.max())
        assert slowed(c, took, config) is None
        floor = slowed(c, 100 * took, config)
        assert all(abs(b["speed"] - SLOWEST * a["speed"]) < 1e-12
                   for (k, a), (_, b) in zip(c.steps, floor.steps, strict=True) if k == "ramp")
        # a floor in m/s (a campaign's: a quarter of its first trial's speed) holds every ramp above it
        least = 0.6 * min(p["speed"] for k, p in c.steps if k == "ramp")
        held = slowed(c, 100 * took, config, least)
        assert min(p["speed"] for k, p in held.steps if k == "ramp") >= least * (1 - 1e-12)
        assert slowed(c, 100 * took, config, 2.0 * least / 0.6) is None  # cannot be slowed at all
