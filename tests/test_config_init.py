"""`rig config init`: a config for a real rig with only what differs from the defaults, then a probe."""

from __future__ import annotations

import subprocess
import sys

import yaml
from rig.sim.params import SimParams
from rig.sim.server import WireSim

from rig.specs.config import RigConfig, load_config, parse_config
from rig.specs.configinit import config_text
from tests.conftest import ROOT


def rig(*args):
    return subprocess.run([sys.executable, "-m", "rig", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)


def test_init_writes_the_differences_and_probes_them(tmp_path):
    out = tmp_path / "lab.yaml"
    with WireSim(SimParams(), tcp=False) as sim:
        rtu, cell = sim.endpoints.modbus_rtu, sim.endpoints.loadcell
        # parity N: this machine's pseudo-terminals refuse even parity
        proc = rig("config", "init", "--slider", rtu, "--loadcell", cell, "--parity", "N",
                   "--out", str(out), "--seconds", "1")
        again = rig("config", "init", "--slider", rtu, "--loadcell", cell, "--out", str(out))
    # the drive and cell answer; the real-drive profile has no comm-timeout register: a problem, not a refusal
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert proc.stdout.startswith(f"wrote {out}; probing it")
    assert "answers       yes: unit 1" in proc.stdout and "lines/s" in proc.stdout
    assert "config: slider.registers.comm_timeout_ms, slider.allow_no_comm_timeout" in proc.stdout
    assert yaml.safe_load(out.read_text()) == {
        "name": "lab rig",
        "slider": {"backend": "modbus-rtu", "port": rtu},
        "loadcell": {"backend": "serial", "port": cell}}
    cfg, default = load_config(out), RigConfig()
    assert cfg.limits == default.limits and cfg.slider.steps_per_mm == default.slider.steps_per_mm
    assert "# `rig ports` lists the serial ports" in out.read_text()
    assert again.returncode == 2 and "exists: pick another --out, or --force" in again.stderr


def test_non_default_fields_are_written_and_load():
    text = config_text(slider_port="/dev/ttyUSB0", loadcell_port="/dev/ttyUSB1", baudrate=230400,
                       parity="E", device_id=3, loadcell_baudrate=9600, loadcell_mode="poll")
    cfg = parse_config(text)
    s, lc = cfg.slider, cfg.loadcell
    assert (s.backend, s.port, s.baudrate, s.parity, s.device_id) == ("modbus-rtu", "/dev/ttyUSB0", 230400,
                                                                      "E", 3)
    assert (lc.port, lc.baudrate, lc.mode) == ("/dev/ttyUSB1", 9600, "poll")
    assert set(yaml.safe_load(text)["slider"]) == {"backend", "port", "baudrate", "parity", "device_id"}


def test_host_and_port_make_a_tcp_slider():
    cfg = parse_config(config_text(slider_port="192.168.0.7:502", loadcell_port="/dev/ttyUSB0"))
    assert (cfg.slider.backend, cfg.slider.host, cfg.slider.tcp_port) == ("modbus-tcp", "192.168.0.7", 502)
