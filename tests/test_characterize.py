"""`rig characterize`: the campaign on the simulated rig, through the command line and the
journal, and a stop in the middle of it (rig.service.characterize); its first trial on specimens
ten times softer and stiffer than the default, and the margins its designed trials keep. The
campaigns of the issue's figures (five hidden effects, five seeds each; against the paper's fixed
set) are in tests/bench/test_bench_characterize.py."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from rig.cli import main
from rig.control.trial import TrialResult
from rig.errors import RigError
from rig.recording.logs import read_log
from rig.service.characterize import Request, characterize
from rig.service.run import RunOptions, run_trial
from rig.specs.config import RigConfig, parse_config
from rig.specs.frames import Frame
from rig.specs.protocol import Approach, Return, check_limits, parse_protocol

SHORT = ("name: short ramp-hold\nsteps:\n  - ramp: {to_mm: 20, speed_mm_s: 2}\n  - hold: {duration_s: 20}\n"
         "  - return: {to_mm: 0, speed_mm_s: 5}\n")


def _events(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_a_campaign_names_the_hidden_drift_and_journals_every_decision(tmp_path, capsys):
    cfg = tmp_path / "rig.yaml"
    cfg.write_text("sim:\n  seed: 4\n  effects:\n    drift: {rate_N_per_s: 0.004}\n")
    first = tmp_path / "first.yaml"
    first.write_text(SHORT)
    code = main(["characterize", "--specimen", "liver-3", "--config", str(cfg), "--protocol", str(first),
                 "--max-trials", "2", "--speed", "0", "--out", str(tmp_path), "--json"])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert "drift" in out["model"]["effects"]
    assert out["model"]["adequate"] is True
    drift = out["model"]["parameters"]["drift_N_per_s"]
    assert abs(drift["value"] - 0.004) < 3 * drift["stderr"]
    assert len(out["trials"]) == 2 and out["status"] == "budget"
    assert out["trials"][0]["why"].startswith("given") and out["trials"][1]["why"]
    assert Path(out["figure"]).is_file()
    events = _events(Path(out["journal"]))
    kinds = [e["event"] for e in events]
    assert kinds[0] == "start" and kinds[-1] == "end"
    assert kinds.count("trial") == 2 and kinds.count("ran") == 2 and kinds.count("fit") == 2
    assert any(e["event"] == "model" and e["added"] == "drift" for e in events)
    decision = next(e for e in events if e["event"] == "decision")
    assert decision["kind"] in ("inform", "separate") and decision["considered"]
    if decision["kind"] == "inform":  # both forecasts, the white-noise one and the calibrated one
        assert all(c["expected_max_rse"] > 0 and c["expected_max_rse_noise_as_so_far"] > 0
                   for c in decision["considered"])
        assert "if its samples are worth what the earlier trials' were" in out["trials"][1]["why"]
    for t in out["trials"]:
        assert read_log(t["log"]).samples["force_N"].size > 100


def test_a_stop_in_the_second_trial_ends_the_campaign_cleanly(tmp_path):
    config = parse_config("sim:\n  seed: 5\n")
    first = tmp_path / "first.yaml"
    first.write_text(SHORT)
    stopper: list[threading.Thread] = []

    def options(n: int) -> dict:
        if n != 2:
            return {}
        held = {}

        def on_start(trial, devices):
            held["trial"] = trial

        def on_tick(snap):
            if snap.t_s > 4.0 and not stopper:  # partway down the ramp
                stopper.append(threading.Thread(target=held["trial"].request_stop))
                stopper[0].start()

        return {"on_start": on_start, "on_tick": on_tick}

    camp = characterize(Request("kidney-1", config, tmp_path, first=str(first), max_trials=4, speed=0,
                                say=lambda _: None, trial_options=options))
    stopper[0].join()
    assert camp.status == "stopped" and "trial 2 ended aborted" in camp.reason
    assert [t.outcome for t in camp.turns] == ["completed", "aborted"]
    events = _events(camp.journal)
    assert events[-1]["event"] == "end" and events[-1]["status"] == "stopped"
    assert events[-2]["event"] == "ran" and events[-2]["outcome"] == "aborted"
    # the aborted trial returned the probe to where it started
    log = read_log(camp.turns[1].log)
    assert abs(log.samples["position_mm"][-1] - log.samples["position_mm"][0]) < 0.05
    assert camp.final is not None and len(camp.final.trials) == 1  # the stopped trial is not fitted


def test_the_next_trial_is_chosen_within_the_budget_left(tmp_path):
    """A candidate longer than the specimen time left is refused (and journaled so); the trial
    chosen fits, and the campaign ends on its budget, not past it."""
    from rig.specs.protocol import parse_protocol, plan

    config = parse_config("sim:\n  seed: 4\n  effects:\n    drift: {rate_N_per_s: 0.004}\n")
    first = tmp_path / "first.yaml"
    first.write_text(SHORT)
    d1 = plan(parse_protocol(SHORT, "<t>"), config).duration_s
    rest_s = 10.0
    budget_s = d1 + rest_s + 45.0  # 45 s for a second trial: the long candidates cannot come
    camp = characterize(Request("liver-4", config, tmp_path, first=str(first), max_trials=3, speed=0,
                                rest_s=rest_s, budget_min=budget_s / 60.0, say=lambda _: None))
    assert camp.elapsed_s <= budget_s + 1e-6
    assert len(camp.turns) == 2 and camp.status == "budget"
    events = _events(camp.journal)
    decision = next(e for e in events if e["event"] == "decision")
    assert decision["kind"] in ("inform", "separate")
    assert any("the budget leaves" in r for r in decision["refused"])
    second = next(e for e in events if e["event"] == "trial" and e["n"] == 2)
    assert second["duration_s"] <= budget_s - d1 - rest_s


def test_the_calibrated_forecast_discounts_a_trial_as_the_trials_so_far_were_discounted():
    """`_as_so_far` maps white-noise information to what the trials' own covariance proved it
    worth: unchanged when that covariance is the white-noise one, divided by k when it is k
    times larger, and direction by direction when only one parameter's variance is inflated."""
    import numpy as np

    from rig.service.characterize import _as_so_far

    rng = np.random.default_rng(3)
    J = rng.standard_normal((400, 3))
    W = J.T @ J
    white = np.linalg.inv(W)
    info = rng.standard_normal((50, 3))
    info = info.T @ info
    assert np.allclose(_as_so_far(white, W)(info), info)
    assert np.allclose(_as_so_far(9.0 * white, W)(info), info / 9.0)
    D = np.diag([1.0, 1.0, 4.0])  # the third parameter's error 4x, alone (an orthogonal design)
    W_diag = np.diag(np.diag(W))
    got = _as_so_far(D @ np.linalg.inv(W_diag) @ D, W_diag)(np.eye(3))
    assert np.allclose(got, np.diag([1.0, 1.0, 1.0 / 16.0]))
    assert _as_so_far(np.zeros((3, 3)), W) is None
    # a covariance that does not share the white-noise information's axes: W itself is mapped to
    # C^-1, the information the trials so far actually carry
    C = rng.standard_normal((3, 3))
    C = C @ C.T + 0.1 * np.eye(3)
    assert np.allclose(_as_so_far(C, W)(W), np.linalg.inv(C))


def test_the_rest_runs_while_the_trials_are_fitted():
    """The rest before the next trial begins when the last one ended: the fits and the choice
    that follow run while the specimen recovers, so only what is left of the rest is waited, and
    a fit longer than the rest counts as rest. At speed 0 (simulation) no specimen time passes
    while fitting: the whole rest is still to come."""
    import time

    from rig.service.characterize import Campaign, Turn, _rest_before_next

    config = parse_config("sim:\n  seed: 4\n")
    camp = Campaign("liver-5")
    req = Request("liver-5", config, Path("."), rest_s=60.0, speed=1.0)
    assert _rest_before_next(req, camp) == (0.0, 0.0)  # before the first trial
    camp.turns.append(Turn("first", "given"))
    for gone, expected in ((20.0, (60.0, 40.0)), (90.0, (90.0, 0.0))):
        camp.trial_ended = time.monotonic() - gone
        rest, wait = _rest_before_next(req, camp)
        assert abs(rest - expected[0]) < 0.5 and abs(wait - expected[1]) < 0.5
    camp.trial_ended = time.monotonic() - 20.0
    simulated = Request("liver-5", config, Path("."), rest_s=60.0, speed=0.0)
    assert _rest_before_next(simulated, camp) == (60.0, 60.0)


# ------------------------------------------------------------------ a campaign that respects the specimen

def _scaled(scale: float, seed: int = 1) -> RigConfig:
    """The simulated rig with its tissue `scale` times the default's stiffness (and damping), as
    tests/test_force_control.py scales it."""
    cfg = RigConfig()
    t = cfg.sim.tissue
    for k in ("k1_N_per_m3", "k2_N_per_m2", "k3_N_per_m", "tau2_N_s_per_m2"):
        setattr(t, k, getattr(t, k) * scale)
    cfg.sim.seed = seed
    return cfg


def _first_then_planned(tmp_path: Path, cfg: RigConfig, **more) -> tuple:
    """A campaign whose first trial runs on the simulated rig, the force the tissue carries (the
    simulator's own, noise-free) watched every tick, and whose second trial is only planned: its
    protocol is kept and nothing runs ("aborted" ends the campaign)."""
    true_peak_N: list[float] = []
    planned = []

    def runner(proto, n: int, log: Path) -> TrialResult:
        if n > 1:
            planned.append(proto)
            return TrialResult("aborted", log, 0, 0, 0, 0.0, fault="planned only")
        sim = {}

        def on_start(trial, devices):
            sim["rig"] = devices.rig
            devices.rig.take_peak_force_N()

        def on_tick(_snapshot):
            true_peak_N.append(sim["rig"].take_peak_force_N())

        return run_trial(proto, cfg, RunOptions(speed=0, progress=False, log_path=log, on_start=on_start,
                                                on_tick=on_tick), warn=lambda _: None)

    camp = characterize(Request("scaled", cfg, tmp_path, max_trials=2, speed=0, say=lambda _: None,
                                runner=runner, **more))
    return camp, max(true_peak_N), planned


@pytest.mark.parametrize("scale", [0.1, 1.0, 10.0])
def test_the_first_trial_respects_a_specimen_of_unknown_stiffness(scale, tmp_path):
    """On specimens 0.1x, 1x and 10x the default's stiffness, the campaign's own first trial finds
    the surface by force and loads by force to its budget: it completes, the force the tissue
    carries stays under the budget (a quarter of the force limit), and the probe stays the margin
    short of the end of travel. A designed second trial is planned the margin short of the end of
    travel wherever its approach finds the surface, its predicted peak within the force margin,
    and the journal says why each trial is its size. Before: the first trial was a position ramp to
    two thirds of the travel, and on the stiffer specimen it faulted at 20.1 N; on the default one
    the second went to 42.8 mm of the 45."""
    cfg = _scaled(scale)
    limit_N, far_mm = cfg.limits.max_force_N, cfg.limits.travel_mm[1]
    margin_mm = 5.0
    camp, true_peak_N, planned = _first_then_planned(tmp_path, cfg, travel_margin_mm=margin_mm)
    first = camp.turns[0]
    assert first.outcome == "completed", camp.reason
    assert true_peak_N < 0.25 * limit_N, true_peak_N
    log = read_log(first.log)
    assert log.samples["force_N"].max() < 0.25 * limit_N
    assert log.position_mm(Frame.SLIDER).max() <= far_mm - margin_mm + 0.05
    assert "approach" in log.step_kind and "ramp_force" in log.step_kind
    events = _events(camp.journal)
    trials = [e for e in events if e["event"] == "trial"]
    assert trials[0]["sizing"]["force_budget_N"] == 0.25 * limit_N and "force budget 5 N" in trials[0]["size"]
    # each trial carries the margin as its own travel window (checked from wherever the slider is)
    for e in trials:
        assert parse_protocol(e["yaml"]).limits.travel_mm == (cfg.limits.travel_mm[0], far_mm - margin_mm + 0.5)
    assert planned, camp.reason
    for proto in planned:
        steps = proto.steps
        assert isinstance(steps[0], Approach) and isinstance(steps[-1], Return) and steps[-1].to_mm is None
        # the rig's own check, with the travel ending the margin early: the deepest point counted
        # from the far end of the approach's search
        tight = RigConfig()
        tight.limits.travel_mm = (cfg.limits.travel_mm[0], far_mm - margin_mm)
        check_limits(proto, tight)
        sizing = trials[1]["sizing"]
        assert sizing["predicted_peak_N"] <= 0.8 * limit_N
        assert sizing["deepest_mm"] <= far_mm - margin_mm
        assert proto.limits.max_force_N <= limit_N
        assert "mm short of the end of travel (5 mm kept)" in trials[1]["size"]


def test_a_campaign_refuses_margins_it_cannot_meet(tmp_path):
    for more, message in (({"first_force_share": 0.0}, "first_force_share 0: expected a share"),
                          ({"force_margin_share": 1.5}, "force_margin_share 1.5: expected a share"),
                          ({"travel_margin_mm": 50.0}, "travel_margin_mm 50 leaves no travel"),
                          ({"first_force_share": 0.01}, "budget, 0.2 N, is too small")):
        with pytest.raises(RigError, match=message):
            characterize(Request("x", RigConfig(), tmp_path / "never", speed=0, say=lambda _: None, **more))
    assert not (tmp_path / "never").exists()  # refused before the journal, before anything moved
