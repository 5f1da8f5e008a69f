"""The daemon as a lab uses it all day: trials back to back, stops and holds between them, a
polled load cell, alarms reset, faults injected; and `rig run` interrupted from the keyboard.
Everything over real wires (Modbus RTU on a pseudo-terminal, the load cell on another)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from dataclasses import dataclass

import pytest
from rig.sim.params import LoadCellParams, SimParams
from rig.sim.server import WireSim

from rig.recording.logs import read_log
from tests.conftest import ROOT
from tests.test_daemon import DaemonProc

RAMP30 = "name: ramp to 30\nsteps:\n  - ramp: {to_mm: 30, speed_mm_s: 10}\n  - return: {speed_mm_s: 10}\n"
SHORT = ("name: short\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: 5}\n  - hold: {duration_s: 0.3}\n"
         "  - return: {speed_mm_s: 5}\n")
TRAVEL = (-5.0, 45.0)


def wait_position(sim: WireSim, at_least_mm: float, timeout_s: float = 10.0,
                  d: DaemonProc | None = None) -> None:
    """Until the slider passes `at_least_mm` (or, given the daemon, its trial has ended: the
    outcome check that follows then says what happened)."""
    deadline = time.monotonic() + timeout_s
    polls = 0
    while sim.rig.slider.position_mm < at_least_mm:
        assert time.monotonic() < deadline, f"slider never reached {at_least_mm} mm"
        polls += 1
        if d is not None and polls % 20 == 0 and d.req({"cmd": "status"})["state"] == "idle":
            return
        time.sleep(0.005)


def test_hold_then_deeper_start_is_refused_before_anything_moves(tmp_path):
    """`stop --hold` at 20 mm, then a protocol ramping 30 mm from there: refused at once (it
    used to run to 45 mm, the edge of the travel window). A protocol that fits still runs."""
    with WireSim(SimParams(), rtu=False) as sim:
        d = DaemonProc(tmp_path, sim)
        try:
            assert d.start_trial(RAMP30)["ok"]
            wait_position(sim, 20.0)
            assert d.req({"cmd": "stop", "mode": "hold"})["ok"]
            assert d.wait_idle()["last"]["outcome"] == "stopped"
            held = sim.rig.slider.position_mm
            assert 20.0 <= held <= 21.5
            moves, logs = sim.drive.moves, sorted(d.out.glob("*.mcap"))
            refused = d.start_trial(RAMP30, specimen="deeper")
            assert not refused["ok"]
            assert f"from the slider's position {held:.2f}" in refused["error"]
            assert "outside the travel window" in refused["error"]
            time.sleep(0.3)
            assert sim.drive.moves == moves and sim.rig.slider.position_mm == held
            assert sorted(d.out.glob("*.mcap")) == logs  # no trial, no log
            # from there, a protocol that fits runs, and returns to where it started
            r = d.start_trial(SHORT, specimen="fits")
            assert r["ok"], r
            assert d.wait_idle()["last"]["outcome"] == "completed"
            log = read_log(r["log"])
            assert float(log.trial["start_mm"]) == pytest.approx(held, abs=0.01)
            assert abs(sim.rig.slider.position_mm - held) <= 0.02
        finally:
            d.stop()


def test_three_polled_trials_in_a_row_with_a_5ms_reply(tmp_path):
    """A reading left over from the last trial used to pass as fresh: the second trial faulted
    at tick 0 ('load cell silent')."""
    params = SimParams(loadcell=LoadCellParams(mode="poll", reply_ms=5.0))
    with WireSim(params) as sim:
        d = DaemonProc(tmp_path, sim, transport="rtu")
        try:
            for i in range(3):
                r = d.start_trial(SHORT, specimen=f"p{i}")
                assert r["ok"], r
                last = d.wait_idle()["last"]
                assert last["outcome"] == "completed", last
                log = read_log(r["log"])
                assert log.complete and log.health[-1]["loadcell_age_ms"] < 100
                time.sleep(0.5)  # the technician between trials: the last reading ages
        finally:
            d.stop()


def test_estop_on_an_idle_daemon_tells_the_truth(tmp_path):
    with WireSim(SimParams(), rtu=False) as sim:
        d = DaemonProc(tmp_path, sim)
        try:
            r = rig_client("estop", d)
            assert r.returncode == 0 and "STOP acknowledged by the drive" in r.stdout
            sim.params.faults.drop_replies = 100_000  # the drive stops answering
            r = rig_client("estop", d)
            sim.params.faults.drop_replies = 0
            assert r.returncode == 2, r.stdout
            assert "did not acknowledge STOP" in r.stderr or "STOP not sent" in r.stderr
        finally:
            d.stop()


def test_reset_alarm_through_the_daemon(tmp_path):
    with WireSim(SimParams(), rtu=False) as sim:
        d = DaemonProc(tmp_path, sim)
        try:
            sim.params.faults.alarm_code = 0x30
            r = rig_client("reset-alarm", d)
            assert r.returncode == 0, r.stderr
            assert "alarm 0x30 before, none now" in r.stdout and sim.params.faults.alarm_code == 0
            assert d.start_trial(RAMP30)["ok"]
            busy = d.req({"cmd": "reset_alarm"})
            assert not busy["ok"] and "a trial is running" in busy["error"]
            assert d.req({"cmd": "estop"})["ok"]
            d.wait_idle()
        finally:
            d.stop()


def test_ctrl_c_under_a_2mm_s_limit_returns_to_the_start(tmp_path):
    """Ctrl-C used to return at a fixed 5 mm/s, trip the 2 mm/s limit's overspeed check and
    leave the probe 3.65 mm deep with exit 3."""
    proto = tmp_path / "slow.yaml"
    proto.write_text("name: slow\nlimits: {max_speed_mm_s: 2}\nsteps:\n"
                     "  - ramp: {to_mm: 10, speed_mm_s: 2}\n  - hold: {duration_s: 5}\n"
                     "  - return: {speed_mm_s: 2}\n")
    out = tmp_path / "trials"
    p = subprocess.Popen([sys.executable, "-m", "rig", "run", str(proto), "--out", str(out)], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 30
    while not list(out.glob("*.mcap")) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(3.0)  # tare, then about 5 mm into the ramp
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=60)
    assert p.returncode == 130, stdout + stderr
    assert "trial aborted" in stdout and "returning to the start position" in stderr
    log = read_log(next(out.glob("*.mcap")))
    assert log.outcome == "aborted"
    assert not [e for e in log.events if e["kind"] == "fault"]
    assert log.samples["position_mm"].max() > 3.0
    assert abs(log.samples["position_mm"][-1]) <= 0.02


# ------------------------------------------------------------------ soak


@dataclass
class Step:
    action: str  # complete, abort, hold, estop, alarm, silent, stall, drop, garbage
    outcome: str


SOAK = [Step("complete", "completed"), Step("abort", "aborted"), Step("hold", "stopped"),
        Step("complete", "completed"), Step("estop", "estopped"), Step("alarm", "fault"),
        Step("drop", "completed"), Step("silent", "fault"), Step("hold", "stopped"),
        Step("stall", "fault"), Step("garbage", "completed"), Step("abort", "aborted"),
        Step("complete", "completed"), Step("estop", "estopped"), Step("alarm", "fault"),
        Step("complete", "completed")]
# every kind once, in the order of the first occurrences above (the sixteen-trial soak per mode is
# tests/bench/test_bench_soak.py's, with the longer soaks: in the suite it held the machine alone
# for a minute of the default run's fifteen)
SOAK_ONCE = [step for i, step in enumerate(SOAK) if step.action not in {s.action for s in SOAK[:i]}]


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["stream", "poll"])
def test_soak_the_daemon_over_rtu(tmp_path, mode):
    """Every kind of ending once per load-cell mode, back to back on one daemon over Modbus RTU:
    every log complete and readable, every outcome right, the slider inside the travel window
    and standing still after every one."""
    soak_the_daemon(tmp_path, mode, SOAK_ONCE)


def soak_the_daemon(tmp_path, mode: str, steps: list[Step]) -> None:
    params = SimParams(loadcell=LoadCellParams(mode=mode, reply_ms=3.0 if mode == "poll" else 0.0))
    with WireSim(params) as sim:
        d = DaemonProc(tmp_path, sim, transport="rtu")
        faults = sim.params.faults
        try:
            for i, step in enumerate(steps):
                r = d.start_trial(SHORT, specimen=f"{mode}-{i}-{step.action}")
                assert r["ok"], (i, step, r)
                if step.action in ("abort", "hold", "estop"):
                    wait_position(sim, sim.rig.slider.position_mm + 1.0, d=d)
                    cmd = {"cmd": "estop"} if step.action == "estop" else {"cmd": "stop", "mode": step.action}
                    assert d.req(cmd)["ok"]
                elif step.action == "alarm":
                    wait_position(sim, sim.rig.slider.position_mm + 1.0, d=d)
                    faults.alarm_code = 0x30
                elif step.action == "silent":
                    wait_position(sim, sim.rig.slider.position_mm + 1.0, d=d)
                    faults.loadcell_silent = True
                elif step.action == "stall":
                    faults.ignore_moves = True
                elif step.action == "drop":
                    time.sleep(1.0)
                    faults.drop_replies = 1
                elif step.action == "garbage":
                    time.sleep(1.0)
                    faults.garbage_lines = 1
                last = d.wait_idle()["last"]
                faults.loadcell_silent = faults.ignore_moves = False
                assert last["outcome"] == step.outcome, (i, step, last, d.log_text()[-2000:])
                log = read_log(r["log"])
                assert log.complete and log.outcome == step.outcome, (i, step)
                assert log.n > 50 and (log.samples["seq"] == range(log.n)).all()
                pos = sim.rig.slider.position_mm
                assert TRAVEL[0] <= pos <= TRAVEL[1] and not sim.rig.slider.moving, (i, step, pos)
                if step.action == "alarm":
                    assert d.req({"cmd": "reset_alarm"})["ok"]
                if step.action in ("complete", "abort", "drop", "garbage"):
                    assert abs(pos - float(log.trial["start_mm"])) <= 0.02  # back where it started
        finally:
            d.stop()


def rig_client(command: str, d: DaemonProc) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig", command, "--socket", str(d.sock)], cwd=ROOT,
                          capture_output=True, text=True, timeout=30)
