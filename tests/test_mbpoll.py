"""mbpoll (libmodbus) talks to the simulated drive: an independent Modbus master agrees with ours."""

from __future__ import annotations

import os
import shutil
import subprocess
import time

import pytest
from rig.sim.params import SimParams
from rig.sim.server import WireSim

MBPOLL = shutil.which("mbpoll")
if MBPOLL is None and os.environ.get("CI"):
    raise RuntimeError("mbpoll is missing on CI: .ci/run must install it")
pytestmark = pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed (apt-get install mbpoll)")


@pytest.fixture(scope="module")
def sim():
    params = SimParams()
    params.slider.start_mm = -123.45  # feedback -12345 steps: a signed 32-bit value to read
    s = WireSim(params, loadcell=False)
    s.start()
    yield s
    s.stop()


def mbpoll(sim: WireSim, transport: str, *options: str, values: list[int] | None = None) -> str:
    """One mbpoll run: options, the device or host, then any values to write."""
    if transport == "tcp":
        host, port = sim.endpoints.modbus_tcp.split(":")
        link, device = ["-m", "tcp", "-p", port], host
    else:
        link, device = ["-m", "rtu", "-b", "115200", "-P", "none"], sim.endpoints.modbus_rtu
    cmd = [MBPOLL, "-a", "1", "-0", "-1", "-o", "1", *link, *options, device]
    if values:
        cmd += ["--", *map(str, values)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=20)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


def wait_still(sim: WireSim, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with sim.rig.lock:
            sim.drive.sync()
            if not sim.rig.slider.moving:
                return
        time.sleep(0.02)
    raise AssertionError("the slider kept moving")


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_mbpoll_reads_position_and_status(sim, transport):
    wait_still(sim)
    out = mbpoll(sim, transport, "-t", "4:int", "-B", "-r", "204", "-c", "1")
    steps = round(sim.rig.feedback_position_mm() * 100)
    assert f"[204]: \t{steps}" in out or f"[204]: {steps}" in out, out
    out = mbpoll(sim, transport, "-t", "4:hex", "-r", "126", "-c", "2")
    # output status lower word: READY (bit 5) and IN-POS (bit 14) while still
    assert "[127]: \t0x4020" in out or "[127]: 0x4020" in out, out


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_mbpoll_starts_a_move_with_direct_data(sim, transport):
    wait_still(sim)
    start = sim.rig.feedback_position_mm()
    target_steps = round(start * 100) + 250  # 2.5 mm further
    # data No. 0, type 1 (absolute), position, 2000 Hz, rate 20000, 20000, current 100 %, trigger 1
    values = [0, 1, target_steps, 2000, 20000, 20000, 1000, 1]
    mbpoll(sim, transport, "-t", "4:int", "-B", "-r", "88", values=values)
    assert sim.drive.moves >= 1
    wait_still(sim)
    assert sim.rig.feedback_position_mm() == pytest.approx(start + 2.5)
