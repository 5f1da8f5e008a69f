"""`rig probe` against the simulated devices on real wires: each device as it is, each injected
fault named with the config field to look at, and the exit status."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest
import yaml
from rig.sim.params import SimParams
from rig.sim.server import WireSim

from rig.diagnostics.probe import loop_lateness, probe
from rig.specs.config import RigConfig
from rig.views.probe_report import EXIT_OK, EXIT_PROBLEMS, EXIT_SILENT
from tests.conftest import ROOT
from tests.wire_helpers import raw_pty

SECONDS = 1.0


@pytest.fixture
def sim():
    s = WireSim(SimParams())
    s.start()
    yield s
    s.stop()


def config_for(sim: WireSim, transport: str = "rtu", **loadcell) -> RigConfig:
    cfg = RigConfig()
    s = cfg.slider
    s.profile = "oriental_az_sim"
    if transport == "tcp":
        s.backend, s.host, s.tcp_port = "modbus-tcp", "127.0.0.1", int(sim.endpoints.modbus_tcp.split(":")[1])
    else:
        s.backend, s.port = "modbus-rtu", sim.endpoints.modbus_rtu
    cfg.loadcell.backend, cfg.loadcell.port = "serial", sim.endpoints.loadcell
    for k, v in loadcell.items():
        setattr(cfg.loadcell, k, v)
    return cfg


def fields_of(report) -> set[str]:
    return {f for p in report.problems for f in p.fields}


def assert_clean(report) -> None:
    """No problem but, on a machine busy with other work, ticks that ran long."""
    others = [p for p in report.problems if p.device != "timing"]
    assert not others, report.format()
    assert report.exit_status() == (EXIT_PROBLEMS if report.problems else EXIT_OK)


@pytest.mark.parametrize("transport", ["rtu", "tcp"])
def test_healthy_rig_streamed(sim, transport):
    report = probe(config_for(sim, transport), seconds=SECONDS)
    text = report.format()
    assert_clean(report)
    assert f"Modbus {transport.upper()}" in text
    assert "answers       yes: unit 1" in text
    assert "status        ready, standing still, in position, no alarm" in text
    assert "position      0.000 mm (0 steps at 100 steps/mm)" in text
    assert "comm timeout  0.5 s written and read back (register 0x0300)" in text
    assert sim.drive.comm_timeout_s == pytest.approx(0.5)  # it really reached the drive
    assert report.problems or "OK: both devices answer, no problems" in text
    c = report.loadcell
    assert 150 <= c["lines_per_s"] <= 260  # the simulated cell streams 200 lines/s
    assert c["lines_bad"] == 0 and c["lines_ok"] >= 150 * SECONDS
    raw, parsed = c["examples"][0]
    assert raw.endswith("N\\r\\n'") and parsed.endswith(" N") and not parsed.startswith("rejected")
    timing = {t["what"]: t for t in report.as_dict()["timing"]}
    pos = timing["position read"]
    assert pos["count"] == pytest.approx(100 * SECONDS, abs=2) and pos["failed"] <= 1  # a busy machine
    assert pos["median_ms"] < 10.0 and timing["status read"]["count"] >= 9
    assert sim.rig.slider.position_mm == 0.0 and sim.drive.moves == 0  # nothing moved


def test_polled_load_cell(sim):
    sim.params.loadcell.mode = "poll"
    sim.params.loadcell.reply_ms = 3.0
    report = probe(config_for(sim, mode="poll"), seconds=SECONDS)
    assert_clean(report)
    c = report.loadcell
    assert c["requests"] >= 95 * SECONDS and c["lines_ok"] >= c["requests"] - 3
    # the reply leaves 3 ms after the request: the round trip is at least that
    assert 3.0 <= c["reply_median_ms"] < 10.0
    assert "reply to a request: median" in report.format()


def test_drive_alarm_named_with_its_meaning(sim):
    sim.params.faults.alarm_code = 0x30
    report = probe(config_for(sim), seconds=SECONDS)
    text = report.format()
    assert report.exit_status() == EXIT_PROBLEMS
    assert "ALARM 0x30: overload" in text
    assert "the drive reports alarm 0x30" in text and "rig reset-alarm" in text


def test_comm_timeout_alarm_points_at_the_timeout(sim):
    sim.params.faults.alarm_code = 0x85
    report = probe(config_for(sim), seconds=SECONDS)
    assert "RS-485 communication timeout" in report.format()
    assert "slider.comm_timeout_s" in fields_of(report)


def test_silent_load_cell(sim):
    sim.params.faults.loadcell_silent = True
    report = probe(config_for(sim), seconds=SECONDS)
    text = report.format()
    assert report.exit_status() == EXIT_SILENT
    assert report.slider_answers and not report.loadcell_answers
    assert "no line from the load cell in 1 s of listening, nor an answer to '?\\r\\n'" in text
    assert {"loadcell.port", "loadcell.baudrate", "loadcell.mode"} <= fields_of(report)
    assert "FAILED: the load cell did not answer" in text


def test_polled_cell_configured_as_streaming(sim):
    sim.params.loadcell.mode = "poll"
    report = probe(config_for(sim), seconds=SECONDS)
    assert report.exit_status() == EXIT_PROBLEMS
    assert "it answers the request '?\\r\\n': it is a polled cell" in report.format()
    # the mode is the finding; a poll at 115200 on the paced wire also makes ticks run long, which
    # the probe rightly reports as timing (as in assert_clean)
    assert {f for p in report.problems if p.device != "timing" for f in p.fields} == {"loadcell.mode"}


def test_streaming_cell_configured_as_polled(sim):
    report = probe(config_for(sim, mode="poll"), seconds=SECONDS)
    assert "before any request: the cell streams on its own" in report.format()
    assert "loadcell.mode" in fields_of(report)


def test_some_garbage_lines(sim):
    # switched on once the probe listens (lines sent before the port opens are flushed by the open)
    timer = threading.Timer(0.4, lambda: setattr(sim.params.faults, "garbage_lines", 5))
    timer.start()
    try:
        report = probe(config_for(sim), seconds=SECONDS)
    finally:
        timer.join()
    text = report.format()
    assert report.exit_status() == EXIT_PROBLEMS
    assert "5 of " in text and "lines did not parse (last: does not match the line pattern" in text
    assert report.loadcell["lines_bad"] == 5
    assert "loadcell.pattern" in fields_of(report)


def test_only_garbage(sim):
    sim.params.faults.garbage_lines = 10**6
    report = probe(config_for(sim), seconds=SECONDS)
    assert report.exit_status() == EXIT_SILENT
    assert "lines arrive but not one parses" in report.format()
    # the first lines, as received and as parsed
    raw, parsed = report.loadcell["examples"][0]
    assert raw == repr("#\x07garb@ge%%\r\n")
    assert parsed == "rejected: does not match the line pattern: '#\\x07garb@ge%%'"
    assert {"loadcell.pattern", "loadcell.baudrate"} <= fields_of(report)


@pytest.mark.parametrize("transport", ["rtu", "tcp"])
def test_dropped_replies(sim, transport):
    sim.params.faults.drop_replies = 2
    report = probe(config_for(sim, transport), seconds=SECONDS)
    text = report.format()
    assert report.exit_status() == EXIT_PROBLEMS, text
    lost = next(p for p in report.problems if "transactions got no valid answer within 20 ms" in p.message)
    assert 2 <= int(lost.message.split(" of ")[0]) <= 3  # the two dropped (and one to a busy machine)
    assert {"slider.timeout_s", "slider.retries"} <= fields_of(report)


def test_corrupted_replies(sim):
    sim.params.faults.corrupt_replies = 3
    report = probe(config_for(sim), seconds=SECONDS)
    assert report.exit_status() == EXIT_PROBLEMS
    lost = next(p for p in report.problems if "transactions got no valid answer" in p.message)
    assert 3 <= int(lost.message.split(" of ")[0]) <= 4


def test_replies_slower_than_the_timeout(sim):
    sim.params.faults.reply_delay_ms = 40.0
    report = probe(config_for(sim), seconds=SECONDS)
    text = report.format()
    assert report.exit_status() == EXIT_SILENT and not report.slider_answers
    slow = next(p for p in report.problems if "answers, but after" in p.message)
    took_ms = float(slow.message.split("after ")[1].split(" ms")[0])
    assert 40.0 <= took_ms < 200.0
    assert "later than slider.timeout_s (20 ms)" in text
    assert "slider.timeout_s" in slow.fields


def test_replies_slower_than_half_the_period(sim):
    sim.params.faults.reply_delay_ms = 7.0
    report = probe(config_for(sim), seconds=SECONDS)
    assert report.exit_status() == EXIT_PROBLEMS
    timing = next(p for p in report.problems if p.device == "timing")
    assert "more than half the 10 ms loop period" in timing.message
    assert "loop.rate_Hz" in timing.fields


def test_a_tick_the_loop_rides_out_is_not_called_late_but_a_run_of_them_is():
    # the trial loop's rule: a 14 ms tick among 4 ms ones at 10 ms starts the next 4 ms after its
    # slot, within the 5 ms tolerance, and the slack after it catches up
    scattered = [4.0] * 200
    for k in range(5, 200, 20):
        scattered[k] = 14.0
    assert loop_lateness(scattered, 10.0, 5.0) == (0, 0)
    # two in a row push the fourth tick 8 ms behind its slot: late
    assert loop_lateness([4.0, 14.0, 14.0, 4.0, 4.0, 4.0], 10.0, 5.0) == (1, 0)
    # a bus slower than the period falls behind every tick until whole periods are skipped
    late, skipped = loop_lateness([12.0] * 100, 10.0, 5.0)
    assert late > 50 and skipped >= 15
    # one 35 ms stall skips the slots it covered, then the loop is on time again
    assert loop_lateness([4.0, 35.0] + [4.0] * 10, 10.0, 5.0) == (0, 2)


def test_profile_without_comm_timeout_register_is_reported_not_refused(sim):
    cfg = config_for(sim)
    cfg.slider.profile = "oriental_az"
    report = probe(cfg, seconds=SECONDS)
    assert report.exit_status() == EXIT_PROBLEMS and report.slider_answers
    assert [p.device for p in report.problems if p.device != "timing"] == ["slider"]
    assert {"slider.registers.comm_timeout_ms", "slider.allow_no_comm_timeout"} <= fields_of(report)
    cfg.slider.allow_no_comm_timeout = True
    report = probe(cfg, seconds=SECONDS)
    assert_clean(report)
    assert "allowed by slider.allow_no_comm_timeout" in report.format()


def test_nothing_on_the_slider_port():
    master, slave, path = raw_pty()
    with WireSim(SimParams(), tcp=False, rtu=False) as sim:
        cfg = RigConfig()
        cfg.slider.backend, cfg.slider.port, cfg.slider.profile = "modbus-rtu", path, "oriental_az_sim"
        cfg.loadcell.backend, cfg.loadcell.port = "serial", sim.endpoints.loadcell
        try:
            report = probe(cfg, seconds=SECONDS)
        finally:
            import os

            os.close(master)
            os.close(slave)
    text = report.format()
    assert report.exit_status() == EXIT_SILENT and report.loadcell_answers
    assert "no answer from unit 1" in text and "not even within 500 ms" in text
    assert {"slider.port", "slider.baudrate", "slider.parity", "slider.device_id"} <= fields_of(report)
    assert "FAILED: the slider did not answer" in text


def rig(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "rig", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def test_cli_probes_the_built_in_simulated_rig():
    proc = rig("probe", "--seconds", "1")
    assert proc.stdout.startswith("probing   the simulated rig on the wire (a `rig sim` process, Modbus RTU)")
    if "- timing:" in proc.stdout:  # a machine busy with other work
        assert proc.returncode == 1, proc.stdout + proc.stderr
    else:
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert "OK: both devices answer, no problems" in proc.stdout


def test_cli_probe_with_a_simulated_fault_in_the_config(tmp_path):
    path = tmp_path / "alarm.yaml"
    path.write_text(yaml.safe_dump({"sim": {"wire": "tcp", "faults": {"alarm_code": 0x66}}}))
    proc = rig("probe", "--config", str(path), "--seconds", "1")
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "Modbus TCP" in proc.stdout
    assert "ALARM 0x66: hardware overtravel" in proc.stdout


@pytest.mark.parametrize("args,fragment", [
    (["probe", "--seconds", "0"], "must be between 0.2 and 60 s"),
    (["probe", "--config", "nope.yaml"], "config file not found"),
    (["config", "init", "--slider", "/dev/ttyUSB0"], "the following arguments are required: --loadcell"),
])
def test_bad_arguments_give_one_line(args, fragment):
    proc = rig(*args)
    assert proc.returncode == 2
    assert fragment in proc.stderr and "Traceback" not in proc.stderr


def test_ports_that_do_not_exist():
    cfg = RigConfig()
    cfg.slider.backend, cfg.slider.port = "modbus-rtu", "/dev/ttyUSB-not-here"
    cfg.loadcell.backend, cfg.loadcell.port = "serial", "/dev/ttyUSB-not-here-either"
    report = probe(cfg, seconds=0.2)
    text = report.format()
    assert report.exit_status() == EXIT_SILENT
    assert "/dev/ttyUSB-not-here does not exist: `rig ports` lists the serial ports" in text
    assert "/dev/ttyUSB-not-here-either does not exist" in text
    assert {"slider.port", "loadcell.port"} <= fields_of(report)
    assert "FAILED: the slider and the load cell did not answer" in text


def test_cli_json_report(sim, tmp_path, capsys):
    from rig.cli import main

    cfg = {"slider": {"backend": "modbus-tcp", "host": "127.0.0.1", "profile": "oriental_az_sim",
                      "tcp_port": int(sim.endpoints.modbus_tcp.split(":")[1])},
           "loadcell": {"backend": "serial", "port": sim.endpoints.loadcell}}
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(cfg))
    sim.params.faults.alarm_code = 0x10
    assert main(["probe", "--config", str(path), "--seconds", "0.5", "--json"]) == EXIT_PROBLEMS
    import json

    report = json.loads(capsys.readouterr().out)
    assert report["exit_status"] == EXIT_PROBLEMS and report["slider_answers"] and report["loadcell_answers"]
    assert report["slider"]["alarm_code"] == 0x10
    assert report["problems"][0]["message"].startswith("the drive reports alarm 0x10: excessive position")
    assert {t["what"] for t in report["timing"]} == {"position read", "status read"}
