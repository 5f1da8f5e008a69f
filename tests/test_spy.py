"""The wire spy: a trial's frames as the drive saw them, decoded; the spy never holds up the loop."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml
from rig.drivers.spy import WireSpy
from rig.drivers.wireframes import FROM_DEVICE
from rig.sim.params import SimParams
from rig.sim.server import WireSim

from rig.cli import main
from rig.errors import RigError
from rig.recording.logs import read_log
from rig.service.client import request
from rig.service.run import RunOptions, run_trial
from rig.specs.config import RigConfig
from rig.specs.protocol import parse_protocol
from rig.views.spyview import decode, format_spy, read_spy
from tests.conftest import ROOT
from tests.wire_helpers import rtu

SHORT = """name: short
steps:
  - ramp: {to_mm: 4, speed_mm_s: 2}
  - hold: {duration_s: 0.5}
  - return: {to_mm: 0, speed_mm_s: 5}
"""

# the frames tests/test_driver_bytes.py expects, with their CRCs computed independently
POSITION_READ = rtu("01 03 00CC 0002")
STATUS_READ = rtu("01 03 007E 0004")
RELEASE = rtu("01 10 007C 0002 04 0000 0000")
COMM_TIMEOUT = rtu("01 10 0300 0002 04 0000 01F4")  # 500 ms, the simulated drive's register
STOP = rtu("01 10 007C 0002 04 0000 0020")
# ramp to 4 mm at 2 mm/s, 50 mm/s^2, 100 steps/mm: 400 steps, 200 Hz, rate 5000, 100 %
RAMP = rtu("01 10 0058 0010 20 00000000 00000001 00000190 000000C8 00001388 00001388 000003E8 00000001")
RETURN = rtu("01 10 0058 0010 20 00000000 00000001 00000000 000001F4 00001388 00001388 000003E8 00000001")


def spied_trial(tmp_path, wire: str, loadcell_mode: str = "stream"):
    cfg = RigConfig()
    cfg.sim.wire = wire
    cfg.sim.loadcell.mode = loadcell_mode
    spy_path = tmp_path / f"{wire}.spy"
    result = run_trial(parse_protocol(SHORT, "<test>"), cfg,
                       RunOptions(speed=1.0, progress=False, log_path=tmp_path / f"{wire}.mcap",
                                  spy_path=str(spy_path)))
    assert result.outcome == "completed", result.fault
    return result, read_log(result.log_path), read_spy(spy_path)


def test_rtu_trial_spy_holds_the_exact_frames_of_the_driver_tests(tmp_path):
    result, log, spy = spied_trial(tmp_path, "rtu")
    sent = [r.data for r in spy.records if r.channel == "rtu" and r.direction == ">"]
    # connect: position, release STOP, read it back, comm timeout written and read back
    assert sent[0] == POSITION_READ
    assert sent[1] == RELEASE
    assert sent[3] == COMM_TIMEOUT
    assert sent.count(RAMP) == 1 and sent.count(RETURN) == 1
    assert sent.index(RAMP) < sent.index(RETURN)
    # one position read a tick, status every 10th, and every tick while a move nears its target
    # (its arrival needs a fresh "standing still"): the ticks within the tolerance of 4 mm in the
    # ramp and of 0 mm in the return, and a few more for the last STOP's confirmation
    n_pos = sent.count(POSITION_READ)
    assert result.samples <= n_pos <= result.samples + 10
    x = log.samples["position_mm"]
    kinds = np.array(log.step_kind)
    tol = RigConfig().slider.position_tolerance_mm
    near = int(np.sum((kinds == "ramp") & (np.abs(x - 4.0) <= tol))
               + np.sum((kinds == "return") & (np.abs(x) <= tol)))
    assert n_pos / 10 - 3 <= sent.count(STATUS_READ) <= n_pos / 10 + 3 + near + 3, near
    assert set(sent) <= {POSITION_READ, STATUS_READ, RELEASE, COMM_TIMEOUT, RAMP, RETURN, STOP,
                         rtu("01 03 007C 0002"), rtu("01 03 0300 0002")}
    # the replies decode into the positions the loop logged
    decoded = decode(spy)
    steps = {int(m.group(1)) for d in decoded
             if (m := re.search(r"from 0x00CC feedback_position: .*\(int32 (-?\d+)\)", d.text))}
    logged = np.unique(np.round(log.samples["position_mm"] * 100).astype(int))
    assert set(logged) <= steps and max(steps) == 400
    # A reply is cut short only when it came after the driver's timeout (a busy machine holds a
    # pty's bytes now and then): the driver counted each such transaction as failed, and its two
    # pieces (what came in time, the rest read as a late reply) are replies, never requests.
    bad = [d for d in decoded if d.record.channel == "rtu" and d.crc_ok is False]
    errors = result.bus_errors  # the driver's count to the end (the log's last health lags)
    assert errors >= log.health[-1]["bus_errors"]
    assert all(d.record.direction == FROM_DEVICE for d in bad)
    assert len(bad) <= 2 * errors, (len(bad), errors)
    # load-cell lines as the simulated cell writes them, about 200 a second
    lines = [r.data for r in spy.records if r.channel == "cell" and not r.partial]
    assert all(re.fullmatch(rb"[+-]\d+\.\d{4} N\r\n", x) for x in lines)
    duration_s = log.samples["t_s"][-1]
    assert 150 * duration_s <= len(lines) <= 250 * (duration_s + 1)
    text = format_spy(spy)
    assert "FC03 read holding registers 0x00CC feedback_position x2  CRC ok" in text
    assert "FC16 write registers 0x0058 direct_data x16: " in text
    assert "(int32 0, 1, 400, 200, 5000, 5000, 1000, 1)" in text
    assert spy.dropped == 0


def test_tcp_trial_spy_holds_mbap_frames_and_polled_lines(tmp_path):
    result, _, spy = spied_trial(tmp_path, "tcp", loadcell_mode="poll")
    sent = [r.data for r in spy.records if r.channel == "tcp" and r.direction == ">"]
    # MBAP: transaction id, protocol 0, length 6, unit 1, then the PDU
    reads = [f for f in sent if f[2:] == bytes.fromhex("0000 0006 01 03 00CC 0002")]
    assert result.samples <= len(reads) <= result.samples + 10
    tids = [int.from_bytes(f[:2], "big") for f in sent]
    assert len(set(tids[:200])) == min(200, len(tids))  # each request its own transaction id
    ramp_pdu = RAMP[1:-2]
    assert sum(f[7:] == ramp_pdu for f in sent) == 1
    cell_tx = [r.data for r in spy.records if r.channel == "cell" and r.direction == ">"]
    cell_rx = [r.data for r in spy.records if r.channel == "cell" and r.direction == "<"]
    assert set(cell_tx) == {b"?\r\n"} and len(cell_tx) >= result.samples
    assert len(cell_rx) >= result.samples - 5
    text = format_spy(spy, channel="tcp")
    assert "tid " in text and "FC03 read holding registers 0x00CC" in text and "CRC" not in text
    assert not re.search(r"^\s+\d+\.\d+  cell", text, re.M)  # --channel tcp: no load-cell records


def test_bad_crc_and_lost_replies_show_in_the_spy(tmp_path):
    """A corrupted reply is shown with CRC BAD, a dropped one as an unanswered request."""
    from rig.drivers.modbus_slider import ModbusLink, ModbusSlider, open_client
    from rig.drivers.registers import PROFILES

    with WireSim(SimParams(), tcp=False, loadcell=False) as sim:
        spy = WireSpy(tmp_path / "s.spy")
        link = ModbusLink("rtu", port=sim.endpoints.modbus_rtu, timeout_s=0.1)
        slider = ModbusSlider(link, PROFILES["oriental_az_sim"], 100.0, client=open_client(link, spy))
        try:
            assert slider.position().fresh
            sim.params.faults.corrupt_replies = 1
            assert not slider.position().fresh
            sim.params.faults.drop_replies = 1
            assert not slider.position().fresh
            assert slider.position().fresh
        finally:
            slider.close()
            spy.close()
    text = format_spy(read_spy(tmp_path / "s.spy"))
    assert text.count("CRC BAD") == 1
    assert "rtu  4 requests, 3 answered, 1 unanswered, 1 replies with a bad CRC" in text


def test_daemon_spy(tmp_path):
    with WireSim(SimParams(), rtu=False) as sim:
        cfg = {"slider": {"backend": "modbus-tcp", "host": "127.0.0.1", "profile": "oriental_az_sim",
                          "tcp_port": int(sim.endpoints.modbus_tcp.split(":")[1])},
               "loadcell": {"backend": "serial", "port": sim.endpoints.loadcell},
               "recorder": {"out_dir": str(tmp_path / "trials")}}
        (tmp_path / "rig.yaml").write_text(yaml.safe_dump(cfg))
        sock, spy_path = tmp_path / "d.sock", tmp_path / "d.spy"
        proc = subprocess.Popen([sys.executable, "-m", "rig", "daemon", "--config", str(tmp_path / "rig.yaml"),
                                 "--socket", str(sock), "--spy", str(spy_path)], cwd=ROOT,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                try:
                    request(sock, {"cmd": "ping"}, 1.0)
                    break
                except (RigError, OSError):  # not listening yet
                    time.sleep(0.05)
            reply = request(sock, {"cmd": "start", "protocol_text": SHORT, "protocol_path": "s.yaml"}, 10.0)
            assert reply["ok"], reply
            end = time.monotonic() + 30
            while request(sock, {"cmd": "status"}, 10.0)["state"] != "idle" and time.monotonic() < end:
                time.sleep(0.1)
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(20)
    spy = read_spy(spy_path)
    assert spy.dropped == 0  # closed properly on shutdown
    assert sum(r.data[7:] == RAMP[1:-2] for r in spy.records if r.direction == ">") == 1


def test_spy_never_blocks_the_caller_and_writes_on_its_own_thread(tmp_path):
    spy = WireSpy(tmp_path / "slow.spy", max_queue=50)
    writers: set[str] = set()
    real_write = spy._fh.write

    def slow_write(text):  # a disk that stalls
        writers.add(threading.current_thread().name)
        time.sleep(0.002)
        return real_write(text)

    spy._fh.write = slow_write
    worst = 0.0
    for i in range(2000):
        t0 = time.perf_counter()
        spy.record("cell", "<", b"+0.%04d N\r\n" % i)
        worst = max(worst, time.perf_counter() - t0)
    dropped = spy.dropped
    spy.close()
    assert writers == {"wire-spy"}
    assert dropped > 0 and worst < 0.05
    text = (tmp_path / "slow.spy").read_text()
    assert text.rstrip().endswith(f"# dropped {dropped}")
    assert len(read_spy(tmp_path / "slow.spy").records) == 2000 - dropped


def test_spy_refused_without_a_wire(tmp_path, capsys):
    from tests.conftest import PROTOCOLS

    code = main(["run", str(PROTOCOLS / "demo.yaml"), "--speed", "0", "--out", str(tmp_path), "--quiet",
                 "--spy", str(tmp_path / "x.spy")])
    assert code == 2
    assert "--spy needs devices on a wire" in capsys.readouterr().err


@pytest.mark.parametrize("content,fragment", [
    (b"", "not a rig spy file"),
    (b"\x89PNG\r\n\x1a\n\x00\x00", "not a rig spy file (it is not text)"),
    (b"hello\n", "not a rig spy file"),
    (b"# rig spy 1\n0.1 rtu > 01 03\n0.2 rtu < 01 0\n", ":3: not a spy record"),
    (b"# rig spy 1\n0.1 can > 01 03\n", ":2: not a spy record"),
])
def test_corrupt_spy_file_is_one_line(tmp_path, content, fragment):
    path = tmp_path / "bad.spy"
    path.write_bytes(content)
    proc = subprocess.run([sys.executable, "-m", "rig", "spy", str(path)], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2
    assert fragment in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_unwritable_spy_path_is_one_line(tmp_path, capsys):
    assert main(["probe", "--spy", str(tmp_path / "no" / "such" / "dir.spy"), "--seconds", "0.2"]) == 2
    err = capsys.readouterr().err
    assert "cannot write the spy file" in err and len(err.strip().splitlines()) == 1


def test_spy_file_cut_short_still_decodes(tmp_path):
    """A daemon killed mid-trial leaves no footer: what was written still decodes, and says so."""
    path = tmp_path / "cut.spy"
    path.write_text("# rig spy 1\n0.001000 rtu > " + POSITION_READ.hex(" ").upper() + "\n")
    text = format_spy(read_spy(path))
    assert "unit 1  FC03 read holding registers 0x00CC" in text
    assert "1 requests, 0 answered, 1 unanswered" in text
    assert "ends without a footer" in text
    assert os.path.getsize(path) > 0
