"""`rig ports`: a port list and a sysfs tree made for the test (the only fakes: no USB adapter here)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from serial.tools.list_ports_common import ListPortInfo

from rig.diagnostics.ports import format_ports, list_ports
from tests.conftest import ROOT


def usb_port(device: str, vid: int, pid: int, serial: str, manufacturer: str, product: str) -> ListPortInfo:
    p = ListPortInfo(device, skip_link_detection=True)
    p.vid, p.pid, p.serial_number = vid, pid, serial
    p.manufacturer, p.product, p.location = manufacturer, product, "1-1.2:1.0"
    p.description = f"{product} - {product}"
    p.hwid = f"USB VID:PID={vid:04X}:{pid:04X} SER={serial} LOCATION=1-1.2:1.0"
    return p


def sysfs(tmp_path: Path, latency: dict[str, str], console: tuple[str, ...] = ()) -> Path:
    for name, value in latency.items():
        d = tmp_path / "bus" / "usb-serial" / "devices" / name
        d.mkdir(parents=True)
        (d / "latency_timer").write_text(value)
    for name in console:
        d = tmp_path / "class" / "tty" / name
        d.mkdir(parents=True)
        (d / "console").write_text("Y\n")
    return tmp_path


def test_usb_details_and_the_16_ms_warning(tmp_path):
    ports = [usb_port("/dev/ttyUSB1", 0x067B, 0x2303, "PL01", "Prolific", "USB-Serial Controller"),
             usb_port("/dev/ttyUSB0", 0x0403, 0x6001, "A10KZP3Q", "FTDI", "FT232R USB UART")]
    root = sysfs(tmp_path, {"ttyUSB0": "16\n", "ttyUSB1": "1\n"})
    found = list_ports(lambda: ports, root)
    assert [p.device for p in found] == ["/dev/ttyUSB0", "/dev/ttyUSB1"]
    assert found[0].latency_timer_ms == 16 and found[1].latency_timer_ms == 1
    text = format_ports(found)
    lines = text.splitlines()
    assert lines[0] == "/dev/ttyUSB0  FT232R USB UART - FT232R USB UART"
    assert lines[1] == "    USB 0403:6001  serial A10KZP3Q  (FTDI FT232R USB UART)"
    assert "    latency timer 16 ms" in lines
    warning = next(line for line in lines if "WARNING" in line)
    assert "latency timer 16 ms (above 1 ms)" in warning and "10 ms loop period" in warning
    assert "echo 1 | sudo tee /sys/bus/usb-serial/devices/ttyUSB0/latency_timer" in warning
    assert text.count("WARNING") == 1  # the 1 ms adapter is fine
    assert "USB 067B:2303  serial PL01" in text
    assert "rig config init --slider PORT --loadcell PORT" in text


def test_no_ports_says_so_plainly(tmp_path):
    text = format_ports(list_ports(lambda: [], sysfs(tmp_path, {})))
    assert text.splitlines()[0] == "no serial ports for a device on this machine."
    assert "Plug in the USB-serial adapter" in text


def test_the_kernel_console_is_not_offered_for_a_device(tmp_path):
    uart = ListPortInfo("/dev/ttyS0", skip_link_detection=True)
    text = format_ports(list_ports(lambda: [uart], sysfs(tmp_path, {}, console=("ttyS0",))))
    assert text.splitlines()[0] == "no serial ports for a device on this machine."
    assert "/dev/ttyS0  the kernel console: not free for a device" in text


def test_a_port_without_latency_file_has_no_timer(tmp_path):
    ports = [usb_port("/dev/ttyACM0", 0x2341, 0x0043, "X1", "Arduino", "Uno")]
    (found,) = list_ports(lambda: ports, sysfs(tmp_path, {}))
    assert found.latency_timer_ms is None and found.warnings() == []
    assert "latency" not in format_ports([found])


def test_rig_ports_on_this_machine():
    proc = subprocess.run([sys.executable, "-m", "rig", "ports"], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr
    assert proc.stdout.strip()
    proc = subprocess.run([sys.executable, "-m", "rig", "ports", "--json"], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0
    for port in json.loads(proc.stdout):
        assert port["device"].startswith("/dev/") and "warnings" in port
