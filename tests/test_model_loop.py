"""A fitted model in the loop: saved by `rig analyze --save`, run by `rig run --model` from
the measured position, checked offline by `rig replay`; and a rig with no load cell at all."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from rig.models.catalogue import build_model
from rig.models.online import OnlineModel, offline_force
from rig.models.saved import load, loads
from rig.recording.logs import read_log
from rig.specs.config import RigConfig
from rig.views.replay import summarize
from tests.conftest import PROTOCOLS, ROOT, run_sim


def rig(*args: str, cwd=ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """The proposed model fitted on the paper's 3 mm/s trial of the default simulated specimen."""
    tmp = tmp_path_factory.mktemp("model")
    trial = run_sim(PROTOCOLS / "paper-3mm_s.yaml", tmp_path=tmp, name="fit3.mcap")
    r = rig("analyze", str(trial.log_path), "--save", str(tmp / "m.json"))
    assert r.returncode == 0, r.stderr
    assert "model saved:" in r.stdout
    return tmp / "m.json"


def test_saved_model_round_trips_and_shows(fitted):
    saved = load(fitted)
    assert saved.model.effect_names == ["poly_elastic", "nonlinear_damping", "relaxation"]
    assert 7.0 < saved.values["tau1_s"] < 9.0  # the simulated tissue's 8 s
    assert saved.noise_N == pytest.approx(0.08, rel=0.1)
    again = loads(saved.text(), "copy")
    assert again.values == saved.values and again.stderr == saved.stderr
    r = rig("models", "show", str(fitted))
    assert r.returncode == 0 and "tau1_s" in r.stdout and "fitted on" in r.stdout


def test_model_fitted_at_3mm_s_runs_in_the_loop_at_1_5mm_s(fitted, tmp_path):
    cfg = RigConfig()
    result = run_sim(PROTOCOLS / "paper-1.5mm_s.yaml", cfg, tmp_path, model_path=str(fitted))
    assert result.outcome == "completed"
    log = read_log(result.log_path)
    s = log.samples
    assert np.allclose(s["model_error_N"], s["force_N"] - s["force_model_N"])
    summary = summarize(log)["model"]
    assert summary["offline_agrees"] and summary["offline_max_diff_N"] <= 1e-9
    # the paper's Part 2: force from motion alone, within the noise on this specimen in every phase
    for phase, stats in summary["error_by_phase"].items():
        assert stats["rmse_N"] <= 1.3 * 0.08, (phase, stats)
    r = rig("replay", str(result.log_path))
    assert "offline on the logged positions it agrees" in r.stdout and "by phase" in r.stdout


def test_online_steps_match_the_vectorised_model_for_every_online_effect():
    """Every effect with a one-step form, against `Model.predict` on the same motion."""
    rng = np.random.default_rng(3)
    dt = 0.01
    t = np.arange(3000) * dt
    x = np.clip(np.interp(t, [0, 2, 10, 12, 30], [-0.001, 0.02, 0.02, -0.0005, -0.0005]), None, None)
    x = np.round((x + rng.normal(0, 2e-6, len(x))) * 1e5) / 1e5  # whole encoder steps
    cases = {
        "proposed+relaxation2+offset+drift": (["poly_elastic", "nonlinear_damping", "relaxation", "relaxation2",
                                               "offset", "drift"],
                                              {"k1_N_per_m3": 5e4, "k2_N_per_m2": 500, "k3_N_per_m": 14,
                                               "tau2_N_s_per_m2": 2e5, "tau1_s": 8, "k_m_N_per_m": 60,
                                               "tau_m_s": 40, "offset_N": 0.3, "drift_N_per_s": 0.004}),
        "kelvin+contact_offset": (["linear_elastic", "viscous", "relaxation", "contact_offset"],
                                  {"k_N_per_m": 80, "eta_N_s_per_m": 50, "tau1_s": 3, "x0_mm": 1.5}),
        "hunt_crossley": (["power_elastic", "hc_damping"],
                          {"k_N_per_m_n": 3e3, "n": 1.5, "b_N_s_per_m_n1": 2e3}),
    }
    for name, (effects, values) in cases.items():
        model = build_model(effects[0], effects[1:])
        online = OnlineModel(model, values, dt)
        stepped = np.array([online.step(ti, xi) for ti, xi in zip(t, x, strict=True)])
        offline = offline_force(model, values, t, x, dt)
        assert np.max(np.abs(stepped - offline)) <= 1e-9, name
        assert np.max(stepped) > 0.1, name  # it did something


def test_effects_without_a_one_step_form_are_refused(tmp_path):
    model = build_model("proposed", ["compliance"])
    with pytest.raises(Exception, match="compliance cannot run in the loop"):
        OnlineModel(model, {}, 0.01)


def test_a_rig_without_a_load_cell_runs_on_the_estimate(fitted, tmp_path):
    cfg = RigConfig()
    cfg.loadcell.backend = "none"
    result = run_sim(PROTOCOLS / "paper-3mm_s.yaml", cfg, tmp_path, model_path=str(fitted))
    assert result.outcome == "completed"
    log = read_log(result.log_path)
    assert log.trial["force_source"] == "model (no load cell)"
    assert np.array_equal(log.samples["force_N"], log.samples["force_model_N"])
    assert "model_error_N" not in log.samples
    assert 8.0 < log.samples["force_N"].max() < 12.0
    assert summarize(log)["model"]["offline_agrees"]


def test_without_a_load_cell_the_estimate_trips_the_force_limit_within_one_tick(tmp_path):
    """A model fitted on a stiffer specimen: its estimate, with the margin, passes the limit and
    the slider is told to stop on that very tick."""
    stiff = RigConfig()
    stiff.sim.tissue.k1_N_per_m3 *= 3
    stiff.sim.tissue.tau2_N_s_per_m2 *= 2
    trial = run_sim(PROTOCOLS / "paper-3mm_s.yaml", stiff, tmp_path, name="stiff.mcap")
    r = rig("analyze", str(trial.log_path), "--save", str(tmp_path / "stiff.json"))
    assert r.returncode == 0, r.stderr
    cfg = RigConfig()
    cfg.loadcell.backend = "none"
    from rig.specs.protocol import load_protocol

    # the protocol's 15 N; the default specimen's model peaks at about 12 N with the margin
    limit = load_protocol(PROTOCOLS / "paper-3mm_s.yaml").effective_limits(cfg.limits).max_force_N
    result = run_sim(PROTOCOLS / "paper-3mm_s.yaml", cfg, tmp_path, name="nocell.mcap",
                     model_path=str(tmp_path / "stiff.json"))
    assert result.outcome == "fault"
    log = read_log(result.log_path)
    fault = next(e for e in log.events if e["kind"] == "fault")
    assert fault["data"]["kind"] == "force_limit" and "estimated force" in fault["message"]
    est = log.samples["force_N"] * (1 + cfg.limits.model_force_margin)
    first = int(np.argmax(est > limit))
    assert fault["data"]["seq"] == first  # the first tick over the limit
    assert est[first - 1] <= limit < est[first]
    # the slider stops: no more than the stop distance past where the fault was seen
    pos = log.samples["position_mm"]
    assert pos.max() - pos[first] < 0.1


def test_no_load_cell_and_no_model_is_refused(tmp_path):
    cfg_path = tmp_path / "c.yaml"
    cfg_path.write_text("loadcell: {backend: none}\n")
    r = rig("run", str(PROTOCOLS / "demo.yaml"), "--config", str(cfg_path), "--speed", "0", "--quiet",
            "--out", str(tmp_path))
    assert r.returncode == 2 and "the force can only come from a model" in r.stderr


@pytest.mark.parametrize("text,fragment", [
    ("not json", "not JSON"),
    ('{"format": "something else"}', "not a saved model"),
    ('{"format": "indentation-rig model 1", "effects": ["springpot"], "parameters": {}}', "unknown effect"),
    ('{"format": "indentation-rig model 1", "effects": ["relaxation"], "parameters": {"tau1_s": {}}}',
     "needs a numeric"),
])
def test_bad_model_files_get_one_line(tmp_path, text, fragment):
    p = tmp_path / "bad.json"
    p.write_text(text)
    r = rig("run", str(PROTOCOLS / "demo.yaml"), "--model", str(p), "--speed", "0", "--quiet",
            "--out", str(tmp_path))
    assert r.returncode == 2 and fragment in r.stderr and "Traceback" not in r.stderr


def test_the_daemon_runs_a_model_sent_with_start(fitted, tmp_path):
    from rig.sim.params import SimParams
    from rig.sim.server import WireSim

    from tests.test_daemon import DaemonProc

    with WireSim(SimParams(), rtu=False) as sim:
        d = DaemonProc(tmp_path, sim)
        try:
            text = "name: short\nsteps:\n  - ramp: {to_mm: 10, speed_mm_s: 3}\n  - hold: {duration_s: 1}\n" \
                   "  - return: {speed_mm_s: 5}\n"
            r = d.start_trial(text, model_text=fitted.read_text(), model_path=str(fitted))
            assert r["ok"], r
            deadline = time.monotonic() + 15.0  # the first ticks, however busy the machine
            snap: dict = {}
            while time.monotonic() < deadline and not (snap.get("force_model_N") or 0) > 0:
                time.sleep(0.2)
                snap = d.req({"cmd": "status"}).get("snapshot") or {}
            assert snap.get("force_model_N") is not None and snap["force_model_N"] > 0, snap
            assert d.wait_idle()["last"]["outcome"] == "completed"
        finally:
            d.stop()
        rep = json.loads(rig("replay", r["log"], "--json").stdout)
        assert rep["model"]["offline_agrees"]


def test_status_and_watch_show_the_model():
    from io import StringIO

    from rig.views.watch import Watcher, format_status

    snap = {"state": "running", "t_s": 3.0, "step": 0, "step_kind": "ramp", "steps_total": 3,
            "time_left_s": 10.0, "force_N": 2.5, "position_mm": 5.0, "stiffness_N_per_m": 90.0,
            "log_path": "x.mcap", "fault": "", "force_model_N": 2.25}
    text = format_status({"ok": True, "state": "running", "snapshot": snap, "trial": {"log": "x.mcap"}})
    assert "model     2.250 N   error +0.250 N" in text
    out = StringIO()
    Watcher(out).update(snap, {"protocol": "p"})
    assert "model       2.250 N   error +0.250 N" in out.getvalue()
