"""One owner per drive and bus: a second process gets a one-line error naming the holder and
puts nothing on the wire; a killed holder does not block; a second daemon touches no log; the
socket directory must be ours."""

from __future__ import annotations

import io
import os
import signal
import stat
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest
import yaml
from rig.sim.params import SimParams
from rig.sim.server import WireSim

from rig.control import manual
from rig.control.devices import make_slider, open_loadcell
from rig.control.ownership import DeviceInUse
from rig.errors import DeviceError, RigError
from rig.recording.logs import read_log
from rig.specs.config import parse_config
from tests.conftest import ROOT
from tests.test_daemon import DaemonProc

TRIAL = "name: four seconds\nsteps:\n  - ramp: {to_mm: 8, speed_mm_s: 4}\n  - hold: {duration_s: 1}\n" \
        "  - return: {speed_mm_s: 5}\n"


def wired_dict(sim: WireSim, transport: str) -> dict:
    ep = sim.endpoints
    slider = {"profile": "oriental_az_sim"}
    if transport == "tcp":
        slider.update(backend="modbus-tcp", host="127.0.0.1", tcp_port=int(ep.modbus_tcp.split(":")[1]))
    else:
        slider.update(backend="modbus-rtu", port=ep.modbus_rtu)
    return {"slider": slider, "loadcell": {"backend": "serial", "port": ep.loadcell,
                                           "mode": sim.params.loadcell.mode}}


def rig(*args: str, timeout: float = 60, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout, env=env)


HOLDER = """
import sys, time, yaml
from rig.control.devices import make_slider, open_loadcell
from rig.specs.config import parse_config
cfg = parse_config(sys.argv[1], "<holder>")
held = make_slider(cfg) if sys.argv[2] == "slider" else open_loadcell(cfg, None)
print("holding", flush=True)
time.sleep(120)
"""


def holder(cfg_text: str, what: str) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", HOLDER, cfg_text, what], cwd=ROOT, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    line = p.stdout.readline().strip()
    assert line == "holding", p.stderr.read()
    return p


@pytest.fixture
def rtu_sim():
    with WireSim(SimParams(), tcp=False) as s:
        yield s


@pytest.fixture
def tcp_sim():
    with WireSim(SimParams(), rtu=False) as s:
        yield s


@pytest.mark.parametrize("transport", ["rtu", "tcp"])
def test_a_second_process_on_the_same_drive_is_refused_naming_the_holder(transport, rtu_sim, tcp_sim):
    sim = rtu_sim if transport == "rtu" else tcp_sim
    text = yaml.safe_dump(wired_dict(sim, transport))
    first = holder(text, "slider")
    try:
        before = sim.drive.requests
        with pytest.raises(DeviceInUse) as err:
            make_slider(parse_config(text, "<second>"))
        msg = str(err.value)
        where = sim.endpoints.modbus_rtu if transport == "rtu" else sim.endpoints.modbus_tcp.split(":")[1]
        assert msg.startswith("the slider ") and where in msg and "\n" not in msg
        assert f"in use by pid {first.pid} (user " in msg and "make_slider" in msg  # its command line
        assert sim.drive.requests == before  # not a byte to the drive
    finally:
        first.kill()
        first.wait(10)
    # a killed holder's lock is gone with it: the next one gets the drive
    slider = make_slider(parse_config(text, "<third>"))
    try:
        assert slider.read_position_mm() == pytest.approx(0.0)
    finally:
        slider.close()
    make_slider(parse_config(text, "<fourth>")).close()  # and close() released it


def test_the_same_tcp_drive_by_another_name_is_one_drive(tcp_sim):
    cfg = wired_dict(tcp_sim, "tcp")
    slider = make_slider(parse_config(yaml.safe_dump(cfg), "<a>"))
    try:
        cfg["slider"]["host"] = "localhost"
        with pytest.raises(DeviceInUse, match=f"in use by pid {os.getpid()} "):
            make_slider(parse_config(yaml.safe_dump(cfg), "<b>"))
    finally:
        slider.close()


def test_a_second_reader_of_the_load_cell_is_refused(rtu_sim):
    text = yaml.safe_dump(wired_dict(rtu_sim, "rtu"))
    first = holder(text, "loadcell")
    try:
        with pytest.raises(DeviceInUse, match=rf"the load cell on .* in use by pid {first.pid} "):
            open_loadcell(parse_config(text, "<second>"), None)
    finally:
        first.kill()
        first.wait(10)
    open_loadcell(parse_config(text, "<third>"), None).close()


def test_cli_commands_beside_a_daemon_are_refused_and_write_nothing(tmp_path, tcp_sim):
    d = DaemonProc(tmp_path, tcp_sim)
    try:
        assert d.req({"cmd": "estop"})["ok"]  # the daemon holds a STOP on the drive
        assert tcp_sim.drive.stop_held
        before = tcp_sim.drive.requests
        for args in (["position"], ["move", "--to-mm", "2"], ["reset-alarm"], ["home"]):
            r = rig(*args, "--config", str(d.cfg_path))
            assert r.returncode == 2, (args, r.stdout, r.stderr)
            line = r.stderr.strip()
            assert "\n" not in line and "Traceback" not in r.stderr, r.stderr
            assert f"is in use by pid {d.proc.pid} (user " in line and " daemon --config " in line, line
            assert f"it is a rig daemon serving {d.sock}" in line, line
        assert tcp_sim.drive.stop_held, "a connect released the daemon's STOP"
        assert tcp_sim.drive.requests == before, "something was written to the drive"
        # through the daemon instead
        r = rig("position", "--socket", str(d.sock))
        assert r.returncode == 0 and r.stdout.startswith("position 0.000 mm, daemon idle"), r.stderr
    finally:
        d.stop()


def test_a_second_daemon_leaves_the_running_trial_and_its_log_alone(tmp_path, tcp_sim):
    d = DaemonProc(tmp_path, tcp_sim)
    try:
        started = d.start_trial(TRIAL, specimen="pig-1")
        assert started["ok"], started
        time.sleep(1.0)
        log_path = Path(started["log"])
        # the same config and socket: refused by the socket
        r = rig("daemon", "--config", str(d.cfg_path), "--socket", str(d.sock), timeout=30)
        assert r.returncode == 2 and f"another daemon is serving {d.sock}" in r.stderr, r.stderr
        assert "recovered" not in r.stderr
        # the same config on a socket of its own: refused by the devices
        r = rig("daemon", "--config", str(d.cfg_path), "--socket", str(tmp_path / "other.sock"), timeout=30)
        assert r.returncode == 2, r.stderr
        assert f"is in use by pid {d.proc.pid}" in r.stderr and "recovered" not in r.stderr, r.stderr
        assert not (tmp_path / "other.sock").exists()
        st = d.wait_idle()
    finally:
        d.stop()
    assert st["last"]["outcome"] == "completed", st
    log = read_log(log_path)
    assert log.complete and log.outcome == "completed" and not log.metadata["outcome"].get("recovered")
    assert log.n == st["last"]["samples"]


def test_rig_daemon_beside_rig_run_does_not_touch_its_log(tmp_path):
    out = tmp_path / "trials"
    proto = tmp_path / "p.yaml"
    proto.write_text(TRIAL)
    cfg = tmp_path / "rig.yaml"
    cfg.write_text(yaml.safe_dump({"recorder": {"out_dir": str(out)}}))
    run = subprocess.Popen([sys.executable, "-m", "rig", "run", str(proto), "--config", str(cfg), "--quiet"],
                           cwd=ROOT, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 20
        while not list(out.glob("*.mcap")) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)  # past its first flushes: a log without a footer yet
        (log_path,) = out.glob("*.mcap")
        daemon = subprocess.Popen([sys.executable, "-m", "rig", "daemon", "--config", str(cfg), "--socket",
                                   str(tmp_path / "d.sock")], cwd=ROOT, text=True,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        said = ""
        deadline = time.monotonic() + 20
        while "listening on" not in said and time.monotonic() < deadline and daemon.poll() is None:
            said += daemon.stdout.readline()
        daemon.send_signal(signal.SIGTERM)
        said += daemon.communicate(timeout=30)[0]
        assert f"left {log_path} alone: another process is writing it" in said, said
        assert "recovered" not in said
        _, stderr = run.communicate(timeout=60)
        assert run.returncode == 0, stderr
    finally:
        run.kill()
    log = read_log(log_path)
    assert log.complete and log.outcome == "completed" and not log.metadata["outcome"].get("recovered")
    assert log.n == int(log.metadata["outcome"]["samples"])


def test_rig_move_stops_the_drive_on_a_device_error_mid_move(tcp_sim):
    cfg = parse_config(yaml.safe_dump(wired_dict(tcp_sim, "tcp")), "<move>")
    errors: list[BaseException] = []

    def go():
        try:
            manual.move(cfg, 10.0, 2.0, out=io.StringIO())
        except BaseException as exc:  # noqa: BLE001 - the test looks at it
            errors.append(exc)

    t = threading.Thread(target=go)
    t.start()
    deadline = time.monotonic() + 10
    while tcp_sim.rig.slider.position_mm < 0.5 and time.monotonic() < deadline:
        time.sleep(0.01)
    # the drive stops answering for exactly as many replies as the driver rides through
    tcp_sim.params.faults.drop_replies = cfg.slider.max_consecutive_errors
    t.join(20)
    assert errors and isinstance(errors[0], DeviceError), errors
    assert "failed transactions in a row" in str(errors[0])
    assert tcp_sim.drive.stop_held, "no STOP went to the drive"
    assert tcp_sim.params.faults.alarm_code == 0  # stopped by us, not by the comm timeout
    time.sleep(0.3)
    assert tcp_sim.rig.slider.position_mm < 5.0


# ------------------------------------------------------------------ the socket directory

def _fallback(monkeypatch, tmp_path, uid: int) -> None:
    from rig.service import daemon

    for var in ("XDG_RUNTIME_DIR", "RIG_SOCKET"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(daemon.os, "geteuid", lambda: uid)


@pytest.mark.skipif(os.geteuid() != 0, reason="chown to other users needs root")
def test_a_socket_directory_not_ours_or_open_to_others_is_refused(tmp_path, monkeypatch):
    from rig.service.daemon import default_socket_path

    _fallback(monkeypatch, tmp_path, 4242)
    d = tmp_path / "rig-4242"
    d.mkdir(mode=0o700)
    os.chown(d, 4242, 4242)
    assert default_socket_path() == d / "rig" / "rigd.sock"
    os.chmod(d, 0o777)
    with pytest.raises(RigError, match=r"rig-4242 is writable by group or others \(mode 0777\)"):
        default_socket_path()
    os.chmod(d, 0o700)
    os.chown(d, 4343, 4343)
    with pytest.raises(RigError, match=r"rig-4242 belongs to user .*4343.*, not to you"):
        default_socket_path()
    os.rmdir(d)
    os.symlink(tmp_path, d)
    with pytest.raises(RigError, match="is not a directory"):
        default_socket_path()


def test_an_absent_socket_directory_is_made_private(tmp_path):
    from rig.service.control_socket import private_dir

    d = private_dir(tmp_path / "rig-new")
    st = os.lstat(d)
    assert stat.S_ISDIR(st.st_mode) and st.st_uid == os.geteuid() and stat.S_IMODE(st.st_mode) == 0o700


@pytest.mark.skipif(os.geteuid() != 0, reason="chown to other users needs root")
def test_a_client_refuses_a_socket_directory_another_user_made(tmp_path, monkeypatch, capsys):
    from rig.cli import main

    _fallback(monkeypatch, tmp_path, 4242)
    d = tmp_path / "rig-4242"
    d.mkdir()
    os.chmod(d, 0o777)  # made by root before user 4242 came, open to all
    assert main(["status"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("rig status: error: socket directory ") and "belongs to user root" in err
    assert "\n" not in err and not (d / "rig").exists()
