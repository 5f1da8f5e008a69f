"""Stops that cannot be lost: a stop or estop reaches the drive whether the trial is starting,
running or closing its log, and the reply says what happened; Ctrl-C only sets a flag.

The daemon runs in this process (its socket and its Modbus link are real, the drive is the
simulated one on the wire) so a test can make the trial's start or close slow."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import pytest
import yaml
from rig.sim.params import SimParams
from rig.sim.server import WireSim

from rig.clock import VirtualClock
from rig.control.devices import open_devices
from rig.control.states import StopMode
from rig.control.trial import Trial
from rig.recording.logs import read_log
from rig.recording.recorder import Recorder
from rig.service.client import request
from rig.service.daemon import Daemon
from rig.service.run import RunOptions, run_trial
from rig.specs.config import RigConfig, parse_config
from rig.specs.protocol import parse_protocol
from tests.conftest import PROTOCOLS, ROOT

RAMP = "name: ramp\nsteps:\n  - ramp: {to_mm: 10, speed_mm_s: 5}\n  - return: {speed_mm_s: 10}\n"
SHORT = "name: short\nsteps:\n  - ramp: {to_mm: 1, speed_mm_s: 5}\n  - return: {speed_mm_s: 5}\n"


class InProcessDaemon:
    """`rig daemon` in this process, on a WireSim's Modbus TCP drive and serial load cell."""

    def __init__(self, tmp, sim: WireSim) -> None:
        cfg = {"slider": {"profile": "oriental_az_sim", "comm_timeout_s": 0.3, "backend": "modbus-tcp",
                          "host": "127.0.0.1", "tcp_port": int(sim.endpoints.modbus_tcp.split(":")[1])},
               "loadcell": {"backend": "serial", "port": sim.endpoints.loadcell},
               "recorder": {"out_dir": str(tmp / "trials")}}
        self.sim = sim
        self.sock = tmp / "rigd.sock"
        self.log = open(tmp / "daemon.log", "w")  # noqa: SIM115 - closed in close()
        self.daemon = Daemon(parse_config(yaml.safe_dump(cfg)), self.sock, log=self.log)
        self.daemon.start()
        self.thread = threading.Thread(target=self.daemon.serve_forever, daemon=True)
        self.thread.start()

    def req(self, obj: dict) -> dict:
        return request(self.sock, obj, 10.0)

    def wait_idle(self, timeout_s: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            st = self.req({"cmd": "status"})
            if st["state"] == "idle":
                return st
            time.sleep(0.05)
        raise AssertionError("trial did not end")

    def close(self) -> None:
        self.daemon.request_shutdown()
        self.thread.join(60)
        self.log.close()


@pytest.fixture
def daemon(tmp_path):
    with WireSim(SimParams(), rtu=False) as sim:
        d = InProcessDaemon(tmp_path, sim)
        try:
            yield d
        finally:
            d.close()


def _stops_seen(sim: WireSim) -> int:
    return sim.drive.stops


@pytest.mark.parametrize("cmd", [{"cmd": "estop"}, {"cmd": "stop", "mode": "hold"}])
def test_a_stop_while_the_trial_starts_reaches_the_drive_and_nothing_moves(daemon, monkeypatch, cmd):
    """Before the loop's first tick (here a load cell slow to give its first reading) a stop
    used to wait for the loop, be answered 'did not send the STOP within 1 s', and the trial
    then ran its protocol."""
    priming = threading.Event()
    original = Trial._prime_loadcell

    def slow_prime(self, timeout_s=3.0):
        priming.set()
        time.sleep(1.5)
        original(self, timeout_s)

    monkeypatch.setattr(Trial, "_prime_loadcell", slow_prime)
    sim = daemon.sim
    r = daemon.req({"cmd": "start", "protocol_text": RAMP, "protocol_path": "t.yaml"})
    assert r["ok"], r
    assert priming.wait(10)
    before, sent = _stops_seen(sim), time.monotonic()
    reply = daemon.req(cmd)
    assert reply["ok"], reply
    assert "acknowledged by the drive" in reply["message"] and "before its first tick" in reply["message"]
    assert _stops_seen(sim) > before and sim.drive.first_stop_s - sent < 0.5
    last = daemon.wait_idle()["last"]
    assert last["outcome"] == ("estopped" if cmd["cmd"] == "estop" else "stopped"), last
    log = read_log(last["log"])
    assert log.complete
    assert abs(log.samples["position_mm"]).max() <= 0.02  # the ramp never started
    assert sim.rig.slider.position_mm == pytest.approx(0.0, abs=0.02)


@pytest.mark.parametrize("cmd", [{"cmd": "estop"}, {"cmd": "stop", "mode": "hold"}])
def test_a_stop_while_the_trial_closes_its_log_reaches_the_drive(daemon, monkeypatch, cmd):
    """While the log was being closed (up to 30 s on a slow disk) the loop was gone: the stop
    was answered 'did not send the STOP within 1 s' and no STOP went to the drive."""
    closing = threading.Event()
    original = Recorder.close

    def slow_close(self, outcome=None, timeout_s=30.0):
        closing.set()
        time.sleep(2.0)
        return original(self, outcome, timeout_s)

    monkeypatch.setattr(Recorder, "close", slow_close)
    sim = daemon.sim
    r = daemon.req({"cmd": "start", "protocol_text": SHORT, "protocol_path": "t.yaml"})
    assert r["ok"], r
    assert closing.wait(30)
    before, sent = _stops_seen(sim), time.monotonic()
    reply = daemon.req(cmd)
    assert reply["ok"], reply
    assert "while it closed its log" in reply["message"] and "acknowledged by the drive" in reply["message"]
    assert _stops_seen(sim) > before and time.monotonic() - sent < 1.0
    last = daemon.wait_idle()["last"]
    assert last["outcome"] == "completed"  # the trial had finished: the stop came after it
    assert read_log(last["log"]).complete


def test_a_stop_refused_is_answered_as_refused(daemon):
    """A hold then an abort: the abort is not carried out, and the reply says so (it used to be
    'ok'). An estop on top always goes out, and is what the trial ends with."""
    r = daemon.req({"cmd": "start", "protocol_text": RAMP, "protocol_path": "t.yaml"})
    assert r["ok"], r
    while daemon.sim.rig.slider.position_mm < 2.0:
        time.sleep(0.005)
    assert daemon.req({"cmd": "stop", "mode": "hold"})["ok"]
    refused = daemon.req({"cmd": "stop", "mode": "abort"})
    assert not refused["ok"] and refused["error"] == "abort: refused: already stopping (hold in progress)"
    again = daemon.req({"cmd": "estop"})
    assert again["ok"] and again["message"].startswith("STOP sent in")
    assert daemon.wait_idle()["last"]["outcome"] == "estopped"


# ------------------------------------------------------------------ Ctrl-C


class SignallingLock:
    """Stands in for the trial's lock: once armed, entering it delivers SIGINT to this (the
    main) thread, so the handler runs while the lock is held, as it can between two bytecodes
    of the loop. A second acquire from the same thread would deadlock: it times out instead and
    says so, so the test fails rather than hangs."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.armed = False
        self.fired = False
        self.deadlocked = False

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        if not self._lock.acquire(timeout=3.0):
            self.deadlocked = True
            raise RuntimeError("deadlock: the lock was taken again by the thread holding it")
        if self.armed and not self.fired:
            self.fired = True
            signal.raise_signal(signal.SIGINT)
        return True

    def release(self) -> None:
        self._lock.release()

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals: main thread")
def test_ctrl_c_while_the_loop_holds_its_lock_aborts(tmp_path):
    """The SIGINT handler used to call request_stop, which takes the lock the loop (the same
    thread) holds every tick: a Ctrl-C landing there hung `rig run` for good."""
    lock = SignallingLock()

    def on_start(trial, devices):
        trial._lock = lock

    def on_tick(snap):
        lock.armed = snap.t_s >= 2.0

    result = run_trial(parse_protocol((PROTOCOLS / "demo.yaml").read_text(), "demo.yaml"), RigConfig(),
                       RunOptions(speed=0, progress=False, log_path=tmp_path / "t.mcap", on_start=on_start,
                                  on_tick=on_tick), warn=lambda _: None)
    assert lock.fired and not lock.deadlocked
    assert result.outcome == "aborted", result.fault
    log = read_log(result.log_path)
    assert log.complete and log.outcome == "aborted"
    ev = next(e for e in log.events if e["kind"] == "stop_requested")
    assert ev["data"]["user"] == "console" and ev["t_s"] <= 2.0 + 0.02  # on the next tick
    assert abs(log.samples["position_mm"][-1]) <= 0.02  # back at the start


def test_ctrl_c_twice_in_the_handler_is_an_estop_without_any_lock():
    from rig.service.run import sigint_handler

    cfg = RigConfig()
    clock = VirtualClock(0)
    dev = open_devices(cfg, clock)
    try:
        trial = Trial(parse_protocol(SHORT, "t.yaml"), cfg, dev.slider, dev.loadcell, clock, "/tmp/unused.mcap")
        handler = sigint_handler(trial)
        with trial._lock:  # held, as by the loop: the handler must not need it
            handler(signal.SIGINT, None)
            assert trial.signal_stop is StopMode.ABORT
            handler(signal.SIGINT, None)
            assert trial.signal_stop is StopMode.ESTOP
    finally:
        dev.close()


def test_ctrl_c_to_rig_run_aborts_with_a_complete_log(tmp_path):
    out = tmp_path / "trials"
    p = subprocess.Popen([sys.executable, "-m", "rig", "run", str(PROTOCOLS / "demo.yaml"), "--out", str(out)],
                         cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 30
    while not list(out.glob("*.mcap")) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(2.0)  # tare, then into the ramp
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=60)
    assert p.returncode == 130, stdout + stderr
    assert "trial aborted" in stdout and "returning to the start position" in stderr
    log = read_log(next(out.glob("*.mcap")))
    assert log.complete and log.outcome == "aborted"
    assert abs(log.samples["position_mm"][-1]) <= 0.02


def test_a_start_replies_with_the_log_it_writes_when_the_planned_name_is_taken(daemon, monkeypatch):
    """Two trials in one second with the same protocol and specimen plan the same name: the
    second's recorder takes the next free one, and the reply, the status and the end all name
    that file, never the earlier trial's."""
    import rig.service.daemon as daemon_module

    planned = daemon.daemon.out_dir / "planned.mcap"
    planned.parent.mkdir(parents=True, exist_ok=True)
    planned.write_bytes(b"an earlier trial's log")
    monkeypatch.setattr(daemon_module, "default_log_path", lambda out_dir, proto, specimen: planned)
    r = daemon.req({"cmd": "start", "protocol_text": SHORT, "protocol_path": "short.yaml"})
    assert r["ok"], r
    assert r["log"] == str(planned.with_name("planned_2.mcap")), r
    st = daemon.wait_idle()
    assert st["last"]["log"] == r["log"] and st["last"]["outcome"] == "completed", st
    assert planned.read_bytes() == b"an earlier trial's log"
    assert read_log(r["log"]).complete


def test_a_start_that_fails_before_its_log_opens_is_answered_as_failed(daemon, monkeypatch):
    """A trial that ends before it opens its log (here its log's folder cannot be written) did
    not start: the reply says so and names no log."""
    import rig.control.trial as trial_module

    def no_log(*args, **kwargs):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(trial_module, "Recorder", no_log)
    r = daemon.req({"cmd": "start", "protocol_text": SHORT, "protocol_path": "short.yaml"})
    assert not r["ok"] and "log" not in r, r
    assert r["error"].startswith("the trial did not start: ") and "Read-only file system" in r["error"], r
    assert daemon.req({"cmd": "status"})["state"] == "idle"
