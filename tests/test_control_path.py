"""The control path in combination: stale readings, limits from where the slider is, moves
with deadlines, a STOP held or lost by the drive, recording failures, the terminal off the
loop thread, and the backstops a real drive needs. In-process devices (virtual time) where
the timing is the point, the simulated devices on real wires where the bytes are."""

from __future__ import annotations

import errno
import os
import resource
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml
from pymodbus.client import ModbusTcpClient
from rig.sim.params import SimParams
from rig.sim.server import WireSim

from rig.clock import RealClock, VirtualClock
from rig.control.devices import open_devices
from rig.control.states import StopMode
from rig.control.trial import Trial
from rig.errors import LimitError
from rig.realtime import Realtime
from rig.recording.logs import read_log
from rig.recording.recorder import TrialInfo
from rig.service.run import RunOptions, run_trial
from rig.specs.config import RigConfig
from rig.specs.protocol import parse_protocol
from rig.views.progress import ProgressBar
from tests.conftest import PROTOCOLS, ROOT, run_sim

FAST = """name: fast ramp
steps:
  - ramp: {to_mm: 12, speed_mm_s: 10}
  - hold: {duration_s: 0.5}
  - return: {speed_mm_s: 10}
"""

DEEP = """name: deep
steps:
  - ramp: {to_mm: 25, speed_mm_s: 5}
  - return: {speed_mm_s: 5}
"""

SHORT = """name: short
steps:
  - ramp: {to_mm: 3, speed_mm_s: 5}
  - hold: {duration_s: 0.3}
  - return: {speed_mm_s: 5}
"""


def inprocess_trial(tmp_path, text: str, config: RigConfig | None = None, name: str = "t.mcap"):
    config = config or RigConfig()
    clock = VirtualClock(0)
    dev = open_devices(config, clock, speed=0)
    trial = Trial(parse_protocol(text, "<test>"), config, dev.slider, dev.loadcell, clock,
                  tmp_path / name, TrialInfo(clock="virtual"))
    return trial, dev


def faults_of(log) -> list[dict]:
    return [e for e in log.events if e["kind"] == "fault"]


# ------------------------------------------------------------------ stale readings

def test_a_failed_position_read_is_not_a_false_overspeed(tmp_path):
    """At 10 mm/s (overspeed at 15), one failed position read used to make the next speed
    estimate span two ticks' motion over one tick's time: 20 mm/s, a false fault."""
    trial, dev = inprocess_trial(tmp_path, FAST)
    seen = {"n": 0}

    def flaky(snap):
        # every 7th tick of the ramp, the next position read fails
        seen["n"] += 1
        dev.slider.unreadable = snap.step_kind == "ramp" and seen["n"] % 7 == 0

    trial.on_tick = flaky
    result = trial.run()
    assert result.outcome == "completed", result.fault
    assert dev.slider.stats.errors >= 10  # the failures happened, and were ridden through


def test_a_position_that_stays_stale_still_stops_on_the_deadline(tmp_path):
    """Stale positions never feed the checks as if fresh: a move whose position is never seen
    again cannot 'arrive'; it ends on its deadline as a fault, and the slider is stopped."""
    trial, dev = inprocess_trial(tmp_path, FAST)
    trial.on_tick = lambda snap: setattr(dev.slider, "unreadable", snap.t_s > 0.8)
    result = trial.run()
    assert result.outcome == "fault"
    fault = faults_of(read_log(result.log_path))[0]
    assert fault["data"]["kind"] == "move" and "deadline" in fault["message"]
    assert not dev.rig.slider.moving


def test_over_range_force_is_a_force_fault_at_once(tmp_path):
    """A reading beyond the cell's range stops the slider on that tick, as a force fault, not
    100 ms later as 'load cell silent'."""
    cfg = RigConfig()
    cfg.loadcell.max_abs_N = 2.0  # the cell's range, below the rig's 20 N force limit
    result = run_sim(DEEP, cfg, tmp_path)
    assert result.outcome == "fault"
    log = read_log(result.log_path)
    fault = faults_of(log)[0]
    assert fault["data"]["kind"] == "force_range", fault
    assert fault["data"]["force_N"] > 2.0
    # no silent gap before it: every earlier sample was within range and fresh
    f = log.samples["force_N"][: fault["data"]["seq"]]
    assert f.max() <= 2.0 and f.max() > 1.5


def test_over_range_line_on_the_wire_is_a_force_fault(tmp_path):
    """The serial driver hands an over-range line to the loop flagged, instead of dropping it."""
    with WireSim(SimParams()) as sim:
        cfg = wired(sim)
        cfg.loadcell.max_abs_N = 2.0
        result = run_trial(parse_protocol(DEEP, "deep.yaml"), cfg,
                           RunOptions(speed=1.0, progress=False, log_path=tmp_path / "range.mcap"))
        log = read_log(result.log_path)
        assert result.outcome == "fault"
        assert faults_of(log)[0]["data"]["kind"] == "force_range"
        assert log.health[-1]["loadcell_lines_ok"] > 0


# ------------------------------------------------------------------ limits from where the slider is

def test_start_deeper_than_the_travel_window_allows_is_refused_before_anything_moves(tmp_path):
    cfg = RigConfig()
    cfg.sim.slider.start_mm = 20.0  # where an earlier 'stop --hold' left it
    text = "name: deep\nsteps:\n  - ramp: {to_mm: 30, speed_mm_s: 5}\n  - return: {speed_mm_s: 5}\n"
    clock = VirtualClock(0)
    dev = open_devices(cfg, clock, speed=0)
    # the check made before the devices are opened passes for a start at 20 mm only if it knows
    # where the slider is; the trial's own check reads the slider
    trial = Trial(parse_protocol(text, "deep.yaml"), cfg, dev.slider, dev.loadcell, clock, tmp_path / "x.mcap")
    with pytest.raises(LimitError, match=r"from the slider's position 20\.000 mm .*outside the travel"):
        trial.run()
    assert dev.rig.slider.position_mm == 20.0 and not dev.rig.slider.moving
    assert not (tmp_path / "x.mcap").exists()


def test_abort_return_honours_the_protocol_speed_limit(tmp_path):
    """Ctrl-C under limits.max_speed_mm_s: 2 used to return at 5 mm/s, trip the overspeed
    check and leave the probe in the tissue."""
    text = ("name: slow\nlimits: {max_speed_mm_s: 2}\nsteps:\n  - ramp: {to_mm: 10, speed_mm_s: 2}\n"
            "  - return: {speed_mm_s: 2}\n")
    trial, _ = inprocess_trial(tmp_path, text)
    fired = threading.Event()

    def stopper(snap):
        if snap.t_s >= 3.0 and not fired.is_set():
            fired.set()
            trial.request_stop(StopMode.ABORT, user="console")

    trial.on_tick = stopper
    result = trial.run()
    assert result.outcome == "aborted", result.fault
    log = read_log(result.log_path)
    assert not faults_of(log)
    assert abs(log.samples["position_mm"][-1]) <= 0.02
    ret = np.array(log.step_kind) == "return"
    v = np.abs(np.diff(log.samples["position_mm"][ret])) * 100.0
    assert v.max() <= 2.0 * 1.05


def test_every_move_goes_through_the_limit_check(tmp_path, monkeypatch):
    """The check before the start is the first line; the second is the check of each move as it
    is issued (the same one `rig move` uses). With the first switched off, a move beyond the
    window (an approach whose contact sits deep) is refused before it is sent."""
    import rig.control.trial

    monkeypatch.setattr(rig.control.trial, "check_limits", lambda *a, **k: None)
    cfg = RigConfig()
    cfg.sim.tissue.surface_mm = 30.0
    text = ("name: a\nsteps:\n  - approach: {speed_mm_s: 5, contact_N: 0.2, max_mm: 40}\n"
            "  - ramp: {to_mm: 12, speed_mm_s: 5}\n")
    result = run_sim(text, cfg, tmp_path)
    assert result.outcome == "fault"
    fault = faults_of(read_log(result.log_path))[0]
    assert fault["data"]["kind"] == "move_limit" and "outside the travel window" in fault["message"]


# ------------------------------------------------------------------ moves and STOP verified

def test_a_drive_that_takes_the_move_but_does_not_move_is_a_fault(tmp_path):
    trial, dev = inprocess_trial(tmp_path, FAST)
    dev.slider.ignore_moves = True
    result = trial.run()
    assert result.outcome == "fault"
    fault = faults_of(read_log(result.log_path))[0]
    assert fault["data"]["kind"] == "move" and "did not start" in fault["message"]
    tare = RigConfig().loop.tare_s
    assert fault["t_s"] <= tare + RigConfig().limits.move_start_s + 0.02


def test_held_stop_makes_the_drive_ignore_a_move_and_the_trial_faults_within_its_deadline(tmp_path):
    """STOP is level-sensitive on the drive: another master leaves it set, the drive ignores the
    trial's move, and the trial ends as a fault within its start deadline instead of waiting."""
    with WireSim(SimParams(), rtu=False) as sim:
        cfg = wired(sim, "tcp")
        other = ModbusTcpClient("127.0.0.1", port=int(sim.endpoints.modbus_tcp.split(":")[1]))
        assert other.connect()
        holder = {"done": False}

        def hold_stop(snap):  # after our connect and tare: the other master sets STOP and leaves it
            if not holder["done"] and snap.t_s >= 0.2:
                holder["done"] = True
                assert not other.write_registers(0x007C, [0, 1 << 5], device_id=1).isError()

        t0 = time.monotonic()
        result = run_trial(parse_protocol(SHORT, "<test>"), cfg,
                           RunOptions(speed=1.0, progress=False, log_path=tmp_path / "held.mcap",
                                      on_tick=hold_stop))
        other.close()
        assert time.monotonic() - t0 < 10
        assert result.outcome == "fault"
        log = read_log(result.log_path)
        fault = faults_of(log)[0]
        assert "did not start" in fault["message"]
        move_t = next(e["t_s"] for e in log.events if e["kind"] == "step_start")
        assert fault["t_s"] - move_t <= cfg.limits.move_start_s + 0.05
        assert sim.drive.ignored_moves == 1 and sim.drive.moves == 0


def test_a_stop_left_set_by_another_process_is_released_on_connect(tmp_path):
    with WireSim(SimParams(), rtu=False) as sim:
        other = ModbusTcpClient("127.0.0.1", port=int(sim.endpoints.modbus_tcp.split(":")[1]))
        assert other.connect()
        other.write_registers(0x007C, [0, 1 << 5], device_id=1)
        other.close()
        assert sim.drive.stop_held
        result = run_trial(parse_protocol(SHORT, "<test>"), wired(sim, "tcp"),
                           RunOptions(speed=1.0, progress=False, log_path=tmp_path / "ok.mcap"))
        assert result.outcome == "completed", result.fault
        assert not sim.drive.stop_held and sim.drive.moves == 2


def test_a_lost_stop_is_resent_until_the_drive_confirms(tmp_path):
    """The drive acknowledges the first STOP and loses it: the loop sees it still moving,
    sends STOP again, and records when the drive confirmed it stands still."""
    with WireSim(SimParams()) as sim:
        cfg = wired(sim)
        done = {"x": False}

        def stop_mid_ramp(snap):
            if not done["x"] and snap.step_kind == "ramp" and snap.position_mm > 1.5:
                done["x"] = True
                sim.params.faults.ignore_stops = 1
                trial_box["trial"].request_stop(StopMode.HOLD, user="tester")

        trial_box = {}
        result = run_trial(parse_protocol(FAST, "<test>"), cfg,
                           RunOptions(speed=1.0, progress=False, log_path=tmp_path / "lost.mcap",
                                      on_tick=stop_mid_ramp,
                                      on_start=lambda trial, dev: trial_box.update(trial=trial)))
        assert result.outcome == "stopped"
        log = read_log(result.log_path)
        confirmed = next(e for e in log.events if e["kind"] == "stop_confirmed")
        assert confirmed["data"]["resends"] >= 1
        assert confirmed["data"]["after_s"] <= 0.5
        assert not sim.rig.slider.moving
        assert log.samples["position_mm"][-1] < 12.0 - 1.0  # it really stopped short of the target


def test_a_drive_that_never_confirms_the_stop_is_reported_as_such(tmp_path):
    with WireSim(SimParams()) as sim:
        cfg = wired(sim)
        cfg.limits.stop_confirm_s = 0.4
        box = {}

        def stop_mid_ramp(snap):
            if "fired" not in box and snap.step_kind == "ramp" and snap.position_mm > 1.5:
                box["fired"] = True
                sim.params.faults.ignore_stops = 1000
                box["trial"].request_stop(StopMode.HOLD, user="tester")

        result = run_trial(parse_protocol(FAST, "<test>"), cfg,
                           RunOptions(speed=1.0, progress=False, log_path=tmp_path / "never.mcap",
                                      on_tick=stop_mid_ramp, on_start=lambda t, d: box.update(trial=t)))
        sim.params.faults.ignore_stops = 0
        assert result.outcome == "fault"
        assert "STOP not confirmed by the drive within 0.4 s" in result.fault


def test_rig_move_that_does_not_happen_is_an_error_not_a_success(tmp_path):
    with WireSim(SimParams()) as sim:
        cfg_path = tmp_path / "rig.yaml"
        cfg_path.write_text(yaml.safe_dump(wired_dict(sim)))
        sim.params.faults.ignore_moves = True
        r = rig("move", "--to-mm", "5", "--config", str(cfg_path))
        assert r.returncode == 2, r.stdout + r.stderr
        assert "did not start the move" in r.stderr and "moved" not in r.stdout
        sim.params.faults.ignore_moves = False
        r = rig("move", "--to-mm", "5", "--speed-mm-s", "5", "--config", str(cfg_path))
        assert r.returncode == 0, r.stderr
        assert "to 5.000 mm" in r.stdout
        # the same limit check as a trial's moves
        r = rig("move", "--to-mm", "60", "--config", str(cfg_path))
        assert r.returncode == 2 and "outside the travel window" in r.stderr


# ------------------------------------------------------------------ recording failures

def test_disk_full_mid_trial_stops_the_slider_and_ends_as_a_fault(tmp_path, monkeypatch):
    """The writer's error used to be stored and never read: 'trial completed'."""
    import rig.recording.recorder as recorder

    real_fsync = os.fsync
    calls = {"n": 0}

    def fsync(fd):
        calls["n"] += 1
        if calls["n"] > 6:  # header, attachments and about a second of samples reach the disk
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    monkeypatch.setattr(recorder.os, "fsync", fsync)
    cfg = RigConfig()
    cfg.recorder.flush_s = 0.3
    cfg.loop.realtime = "off"
    clock = RealClock(cfg.loop.spin_ms / 1000.0)
    dev = open_devices(cfg, clock, speed=0)  # in-process devices, real time: the writer flushes mid-trial
    trial = Trial(parse_protocol(FAST, "<t>"), cfg, dev.slider, dev.loadcell, clock, tmp_path / "full.mcap")
    result = trial.run()
    assert result.outcome == "fault"
    assert "No space left on device" in result.fault and "rig replay" in result.fault
    assert not dev.rig.slider.moving
    fault_t = result.duration_s
    assert fault_t < 3.0  # it ended early, on the failure, not at the end of the protocol (3.9 s)
    monkeypatch.setattr(recorder.os, "fsync", real_fsync)
    log = read_log(result.log_path)  # what was flushed is readable
    assert len(log.samples["t_s"]) > 30


def test_recorder_queue_past_its_bound_is_a_fault(tmp_path):
    cfg = RigConfig()
    cfg.recorder.max_queue = 100
    trial, dev = inprocess_trial(tmp_path, (PROTOCOLS / "demo.yaml").read_text(), cfg)
    stall = threading.Event()

    def block_writer(snap):  # the disk stops answering: nothing leaves the queue
        if snap.t_s > 1.0 and not stall.is_set():
            stall.set()
            trial.recorder._q.put(("__stall__", 0, {}))

    original = trial.__class__.run

    def patched_write(item, _orig=None):
        if item[0] == "__stall__":
            time.sleep(1.5)
            return False
        return _orig(item)

    trial.on_tick = block_writer
    from rig.recording import recorder as recmod

    orig_write = recmod.Recorder._write
    recmod.Recorder._write = lambda self, item: patched_write(item, lambda it: orig_write(self, it))
    try:
        result = original(trial)
    finally:
        recmod.Recorder._write = orig_write
    assert result.outcome == "fault"
    assert "cannot keep up" in result.fault
    assert not dev.rig.slider.moving


def test_rig_run_on_a_full_disk_exits_non_zero_and_keeps_what_was_flushed(tmp_path):
    """A real file-size limit (RLIMIT_FSIZE: writes past it fail with EFBIG, as a full disk
    fails with ENOSPC) through the CLI."""
    args = [sys.executable, "-m", "rig", "run", str(PROTOCOLS / "demo.yaml"), "--speed", "4", "--quiet"]
    full = subprocess.run([*args, "--out", str(tmp_path / "full")], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert full.returncode == 0, full.stderr
    size = next((tmp_path / "full").glob("*.mcap")).stat().st_size
    out = tmp_path / "trials"

    def limit():  # the disk fills when the log is half written
        resource.setrlimit(resource.RLIMIT_FSIZE, (size // 2, size // 2))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    r = subprocess.run([*args, "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=120,
                       preexec_fn=limit)
    assert r.returncode == 3, r.stdout + r.stderr
    assert "trial fault" in r.stdout and "recording failed: File too large" in r.stdout
    assert "Traceback" not in r.stderr
    log_path = next(out.glob("*.mcap"))
    rep = subprocess.run([sys.executable, "-m", "rig", "replay", str(log_path)], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert rep.returncode == 0, rep.stderr
    assert read_log(log_path).samples["t_s"][-1] > 2.0


# ------------------------------------------------------------------ the loop and the terminal

def test_a_blocked_terminal_never_stalls_the_loop(tmp_path):
    """The progress display writes from its own thread: a stream that blocks for good costs
    the loop nothing."""
    class Blocked:
        def __init__(self):
            self.release = threading.Event()
            self.writes = 0

        def isatty(self):
            return True

        def write(self, text):
            self.writes += 1
            self.release.wait()

        def flush(self):
            pass

    cfg = RigConfig()
    cfg.loop.realtime = "off"
    clock = RealClock(cfg.loop.spin_ms / 1000.0)
    dev = open_devices(cfg, clock, speed=0)  # in-process devices on the real clock
    text = "name: s\nsteps:\n  - ramp: {to_mm: 2, speed_mm_s: 5}\n  - hold: {duration_s: 0.5}\n"
    trial = Trial(parse_protocol(text, "<t>"), cfg, dev.slider, dev.loadcell, clock, tmp_path / "b.mcap")
    stream = Blocked()
    bar = ProgressBar(2.0, lambda: trial.snapshot, stream=stream, every_s=0.05).start()
    result = trial.run()
    assert stream.writes >= 1  # it did try to write, and stayed blocked
    stream.release.set()
    bar.close()
    assert result.outcome == "completed"
    assert result.missed_ticks == 0 and result.duration_s < 3.0


def test_realtime_is_asked_for_and_recorded(tmp_path):
    cfg = RigConfig()
    cfg.sim.wire = "none"
    result = run_trial(parse_protocol(SHORT, "<t>"), cfg,
                       RunOptions(speed=1.0, progress=False, log_path=tmp_path / "rt.mcap"))
    rt = read_log(result.log_path).trial["realtime"]
    if os.geteuid() == 0:
        assert rt.startswith("SCHED_FIFO 50")
    else:
        assert rt.startswith("normal") and "refused" in rt
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # given back after the trial


def test_realtime_required_without_privilege_is_refused():
    code = ("import os\nfrom rig.realtime import Realtime\nfrom rig.errors import RigError\n"
            "if os.geteuid() == 0:\n    os.setuid(65534)  # an unprivileged user: no CAP_SYS_NICE\n"
            "try:\n    Realtime('required').enter()\nexcept RigError as e:\n    print('refused:', e)\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert "refused: loop.realtime is 'required' but SCHED_FIFO refused" in r.stdout, r.stdout + r.stderr


def test_realtime_off_leaves_scheduling_alone():
    state = Realtime("off").enter()
    assert state.policy == "normal" and not state.granted


# ------------------------------------------------------------------ backstops

def test_profile_without_comm_timeout_is_refused_unless_allowed(tmp_path):
    with WireSim(SimParams()) as sim:
        d = wired_dict(sim)
        d["slider"]["profile"] = "oriental_az"  # the real map: its comm-timeout register is unknown
        cfg_path = tmp_path / "real.yaml"
        cfg_path.write_text(yaml.safe_dump(d))
        r = rig("run", str(PROTOCOLS / "demo.yaml"), "--config", str(cfg_path), "--quiet",
                "--out", str(tmp_path / "t"))
        assert r.returncode == 2
        assert "communication-timeout register" in r.stderr and "allow_no_comm_timeout" in r.stderr
        assert not (tmp_path / "t").exists() or not list((tmp_path / "t").glob("*.mcap"))
        d["slider"]["allow_no_comm_timeout"] = True
        cfg_path.write_text(yaml.safe_dump(d))
        proto = tmp_path / "short.yaml"
        proto.write_text(SHORT)
        for _ in range(2):  # warned on every start
            r = rig("run", str(proto), "--config", str(cfg_path), "--quiet", "--out", str(tmp_path / "t"))
            assert r.returncode == 0, r.stderr
            assert "WARNING" in r.stderr and "nothing stops the drive" in r.stderr
        log = read_log(sorted((tmp_path / "t").glob("*.mcap"))[-1])
        assert log.trial["backstop"] == "none"


def test_reset_alarm_clears_a_drive_alarm_and_says_when_it_cannot(tmp_path):
    with WireSim(SimParams()) as sim:
        cfg_path = tmp_path / "rig.yaml"
        cfg_path.write_text(yaml.safe_dump(wired_dict(sim)))
        sim.params.faults.alarm_code = 0x30
        r = rig("reset-alarm", "--config", str(cfg_path))
        assert r.returncode == 0, r.stderr
        assert "alarm 0x30 before, none now" in r.stdout
        assert sim.params.faults.alarm_code == 0
        sim.params.faults.drop_replies = 10_000  # the drive stops answering
        r = rig("reset-alarm", "--config", str(cfg_path))
        sim.params.faults.drop_replies = 0
        assert r.returncode == 2 and "error" in r.stderr


# ------------------------------------------------------------------ helpers

def wired_dict(sim: WireSim, transport: str = "rtu") -> dict:
    ep = sim.endpoints
    slider = {"profile": "oriental_az_sim"}
    if transport == "tcp":
        slider.update(backend="modbus-tcp", host="127.0.0.1", tcp_port=int(ep.modbus_tcp.split(":")[1]))
    else:
        slider.update(backend="modbus-rtu", port=ep.modbus_rtu)
    return {"slider": slider, "loadcell": {"backend": "serial", "port": ep.loadcell}}


def wired(sim: WireSim, transport: str = "rtu") -> RigConfig:
    from rig.specs.config import parse_config

    return parse_config(yaml.safe_dump(wired_dict(sim, transport)), "<wired>")


def rig(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def test_speed_is_measured_over_two_ticks_not_between_a_late_tick_and_the_next():
    """A late tick followed by one on time leaves half a millisecond between two readings: one
    0.01 mm encoder step over that reads as 20 mm/s. The meter spans at least two periods."""
    from rig.drivers.base import Reading

    from rig.control.safety import SpeedMeter

    meter = SpeedMeter(0.02)
    speeds = []
    t = 0.0
    for k in range(60):
        t = k * 0.01 + (0.0095 if k % 7 == 3 else 0.0)  # every 7th tick 9.5 ms late
        x = round(5.0 * t * 100) / 100  # 5 mm/s, whole 0.01 mm steps
        v = meter.update(Reading(x, t))
        if v is not None:
            speeds.append(v)
    assert len(speeds) >= 50
    assert max(abs(v - 5.0) for v in speeds) <= 1.0
    assert meter.update(Reading(9.0, t + 0.01, fresh=False)) is None  # stale: no estimate
