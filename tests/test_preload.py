"""A preload counted: the force limit applies to the force the tissue carries, measured from
the load cell's free-air zero, whatever a trial tared away at its start."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
from rig.sim.params import SimParams, SliderParams, TissueParams
from rig.sim.server import WireSim

from rig.recording.logs import read_log
from rig.specs.config import RigConfig, parse_config
from tests.conftest import ROOT, run_sim
from tests.test_daemon import DaemonProc

# 1 N per mm of indentation, no viscosity, a relaxation fast enough to be no lag: the force is
# the depth, so what the tissue carries is known at every position.
TISSUE = TissueParams(k1_N_per_m3=0.0, k2_N_per_m2=0.0, k3_N_per_m=1000.0, tau1_s=0.01, tau2_N_s_per_m2=0.0)
INTO = "name: into the tissue\nsteps:\n  - ramp: {{to_mm: {mm}, speed_mm_s: 4}}\n  - hold: {{duration_s: 60}}\n"
DEEPER = ("name: deeper\nlimits: {{max_force_N: 10}}\nsteps:\n  - ramp: {{to_mm: {mm}, speed_mm_s: 1}}\n"
          "  - return: {{speed_mm_s: 5}}\n")


def preload_in(message: str) -> float:
    assert message.startswith("preload "), message
    return float(message.split()[1])


def hold_at(d: DaemonProc, sim: WireSim, mm: float) -> float:
    """A trial into the tissue, `stop --hold` once it sits at `mm`: the probe stays pressed in."""
    r = d.start_trial(INTO.format(mm=mm), specimen="into")
    assert r["ok"], r
    deadline = time.monotonic() + 20
    while d.req({"cmd": "status"}).get("snapshot", {}).get("step_kind") != "hold":
        assert time.monotonic() < deadline, "never reached the hold"
        time.sleep(0.02)
    assert d.req({"cmd": "stop", "mode": "hold"})["ok"]
    assert d.wait_idle()["last"]["outcome"] == "stopped"
    return sim.rig.slider.position_mm


def test_a_start_in_contact_counts_its_preload_against_the_limit(tmp_path):
    """The issue's case: held where the tissue pushes 4 N, then a ramp 8 mm deeper under a
    10 N limit. The limit used to see only the force after the tare: the trial completed with
    the tissue carrying 12 N. Now it stops where the tissue carries 10 N."""
    with WireSim(SimParams(tissue=TISSUE), rtu=False) as sim:
        d = DaemonProc(tmp_path, sim)
        try:
            held = hold_at(d, sim, 4.0)
            assert sim.rig.tissue_force_N == pytest.approx(4.0, abs=0.1)
            r = d.start_trial(DEEPER.format(mm=8), specimen="deeper")
            assert r["ok"], r
            last = d.wait_idle()["last"]
            assert last["outcome"] == "fault", last
            assert "force" in last["fault"] and "above the limit of 10 N" in last["fault"]
            assert "of it preload at the start" in last["fault"]
            log = read_log(r["log"])
            tare = next(e for e in log.events if e["kind"] == "tare")
            assert tare["data"]["preload_N"] == pytest.approx(held, abs=0.3)  # 1 N/mm from the surface
            assert "earlier trial" not in tare["message"] or "assumed" in tare["message"]
            # MCAP metadata are strings: the tare's figures are written to six significant digits
            assert log.metadata["tare"]["preload_N"] == f"{tare['data']['preload_N']:.6g}"
            fault = next(e for e in log.events if e["kind"] == "fault")
            assert fault["data"]["kind"] == "force_limit"
            carried = log.samples["force_N"] + tare["data"]["preload_N"]  # absolute, as a reader gets it
            # a tick's rise at 1 mm/s is 0.01 N; the rest is the cell's noise (0.08 N)
            assert carried.max() <= 10.0 + 0.01 + 0.4
            assert sim.rig.tissue_force_N <= 10.0 + 0.1
            assert sim.rig.slider.position_mm <= 10.1
        finally:
            d.stop()


def test_a_preload_beyond_its_share_of_the_limit_is_refused_before_anything_moves(tmp_path):
    """Held where the tissue pushes 8 N, a start under a 10 N limit: 8 N is more than half of
    it (limits.max_preload_share). It used to run, tared to 0 N, to 10 N tared (18 N carried
    in the ramp asked for here); now the slider never moves."""
    with WireSim(SimParams(tissue=TISSUE), rtu=False) as sim:
        d = DaemonProc(tmp_path, sim)
        try:
            held = hold_at(d, sim, 8.0)
            moves = sim.drive.moves
            r = d.start_trial(DEEPER.format(mm=10), specimen="pressed")
            assert r["ok"], r
            last = d.wait_idle()["last"]
            assert last["outcome"] == "fault", last
            assert preload_in(last["fault"]) == pytest.approx(held, abs=0.3)
            assert "beyond 0.5 of the force limit 10 N (limits.max_preload_share)" in last["fault"]
            assert "refused before anything moved" in last["fault"]
            assert sim.drive.moves == moves
            assert sim.rig.slider.position_mm == pytest.approx(held, abs=0.01)
            log = read_log(r["log"])
            assert log.complete and log.outcome == "fault"
            assert next(e for e in log.events if e["kind"] == "fault")["data"]["kind"] == "preload"
            assert np.ptp(log.samples["position_mm"]) <= 0.02
        finally:
            d.stop()


def _in_contact_config(tmp_path, **loadcell) -> RigConfig:
    """The in-process simulated rig with the slider starting 8 mm into the 1 N/mm tissue."""
    cfg = parse_config(yaml.safe_dump({"recorder": {"out_dir": str(tmp_path / "trials")},
                                       "loadcell": loadcell}))
    cfg.sim.tissue = TISSUE
    cfg.sim.slider = SliderParams(start_mm=8.0)
    return cfg


PRESSED = "name: pressed\nlimits: {max_force_N: 10}\nsteps:\n  - ramp: {to_mm: 1, speed_mm_s: 1}\n"


def test_the_configured_zero_counts_the_preload(tmp_path):
    result = run_sim(PRESSED, _in_contact_config(tmp_path, zero_N=0.0), tmp_path)
    assert result.outcome == "fault" and preload_in(result.fault) == pytest.approx(8.0, abs=0.3)
    log = read_log(result.log_path)
    assert log.trial["loadcell_zero_source"] == "the config's loadcell.zero_N"
    assert np.ptp(log.samples["position_mm"]) <= 0.02


def test_without_a_known_zero_the_tare_is_assumed_and_the_log_says_so(tmp_path):
    """Nothing known (a fresh machine): the trial runs, counting from its own tare, and says
    what it assumed; the warning reaches the operator."""
    warned = []
    from rig.service.run import RunOptions, run_trial
    from rig.specs.protocol import parse_protocol

    cfg = _in_contact_config(tmp_path)
    result = run_trial(parse_protocol(PRESSED, "<t>"), cfg,
                       RunOptions(speed=0, progress=False, log_path=tmp_path / "t.mcap"), warn=warned.append)
    assert result.outcome == "completed", result.fault
    assert any("no free-air zero known for the load cell" in w for w in warned)
    log = read_log(result.log_path)
    assert log.trial["loadcell_zero_source"] == "none known: the tare is assumed to be taken out of contact"
    tare = next(e for e in log.events if e["kind"] == "tare")
    assert "no free-air zero known: assumed out of contact (preload 0)" in tare["message"]
    assert tare["data"]["zero_assumed"] is True and tare["data"]["preload_N"] == 0.0


def test_rig_tare_saves_the_zero_every_later_run_counts_from(tmp_path):
    cfg_path = tmp_path / "rig.yaml"
    cfg_path.write_text(yaml.safe_dump({"recorder": {"out_dir": str(tmp_path / "trials")}}))
    r = subprocess.run([sys.executable, "-m", "rig", "tare", "--config", str(cfg_path), "--seconds", "0.5"],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("load cell sim: zero ") and ".loadcell-zero.json" in r.stdout
    from rig.control.zero import saved_zero

    zero = saved_zero(parse_config(cfg_path.read_text()))
    assert abs(zero.value_N) < 0.05  # out of contact: the cell's noise only
    result = run_sim(PRESSED, _in_contact_config(tmp_path), tmp_path)  # the same trials folder
    assert result.outcome == "fault" and preload_in(result.fault) == pytest.approx(8.0, abs=0.3)
    assert "`rig tare` at" in read_log(result.log_path).trial["loadcell_zero_source"]
