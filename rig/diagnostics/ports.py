"""`rig ports`: the serial ports of this machine, with their USB identity and latency timer.

The port list comes from pyserial's `serial.tools.list_ports`, the latency timer of a
USB-serial adapter from sysfs; both are injectable so tests can build them. An FTDI
adapter holds received bytes for its latency timer (16 ms by default) before passing
them on: a Modbus reply then arrives a tick late, so anything above 1 ms is flagged.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

LATENCY_OK_MS = 1


@dataclass(frozen=True)
class PortInfo:
    device: str
    description: str
    hwid: str
    vid: int | None = None
    pid: int | None = None
    serial_number: str | None = None
    manufacturer: str | None = None
    product: str | None = None
    location: str | None = None
    latency_timer_ms: int | None = None  # USB-serial adapters on Linux only
    console: bool = False  # the kernel's console: taken, not for a device

    @property
    def usb(self) -> bool:
        return self.vid is not None

    def warnings(self, period_ms: float = 10.0) -> list[str]:
        out = []
        if self.latency_timer_ms is not None and self.latency_timer_ms > LATENCY_OK_MS:
            name = Path(self.device).name
            out.append(f"latency timer {self.latency_timer_ms} ms (above {LATENCY_OK_MS} ms): every reply can "
                       f"wait that long in the adapter, against a {period_ms:g} ms loop period. Set it to 1: "
                       f"echo 1 | sudo tee /sys/bus/usb-serial/devices/{name}/latency_timer  (lasts until "
                       "unplugged; a udev rule makes it stick: docs/how-to/new-drive.md)")
        return out

    def as_dict(self) -> dict:
        return {**asdict(self), "usb": self.usb, "warnings": self.warnings()}


def _system_comports() -> Iterable:
    from serial.tools import list_ports

    return list_ports.comports()


def read_latency_timer_ms(device: str, sysfs_root: Path) -> int | None:
    path = sysfs_root / "bus" / "usb-serial" / "devices" / Path(device).name / "latency_timer"
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return None


def _is_console(device: str, sysfs_root: Path) -> bool:
    try:
        return (sysfs_root / "class" / "tty" / Path(device).name / "console").read_text().strip() == "Y"
    except OSError:
        return False


def _text(value) -> str | None:
    return None if value in (None, "", "n/a") else str(value)


def list_ports(comports: Callable[[], Iterable] = _system_comports,
               sysfs_root: Path = Path("/sys")) -> list[PortInfo]:
    """Every port pyserial finds (objects with pyserial's ListPortInfo fields), sorted by device."""
    ports = []
    for p in comports():
        ports.append(PortInfo(
            device=p.device, description=_text(p.description) or "", hwid=_text(p.hwid) or "",
            vid=p.vid, pid=p.pid, serial_number=_text(p.serial_number),
            manufacturer=_text(p.manufacturer), product=_text(p.product), location=_text(p.location),
            latency_timer_ms=read_latency_timer_ms(p.device, sysfs_root) if p.vid is not None else None,
            console=_is_console(p.device, sysfs_root)))
    return sorted(ports, key=lambda p: p.device)


def format_ports(ports: list[PortInfo]) -> str:
    free = [p for p in ports if not p.console]
    lines: list[str] = []
    if not free:
        lines.append("no serial ports for a device on this machine.")
    for p in ports:
        if p.console:
            lines.append(f"{p.device}  the kernel console: not free for a device")
            continue
        lines.append(f"{p.device}  {p.description or '(no description)'}")
        if p.usb:
            ident = f"USB {p.vid:04X}:{p.pid or 0:04X}"
            if p.serial_number:
                ident += f"  serial {p.serial_number}"
            maker = " ".join(x for x in (p.manufacturer, p.product) if x)
            if maker:
                ident += f"  ({maker})"
            lines.append(f"    {ident}")
            if p.location:
                lines.append(f"    location {p.location}")
            if p.latency_timer_ms is not None:
                lines.append(f"    latency timer {p.latency_timer_ms} ms")
        elif p.hwid:
            lines.append(f"    {p.hwid}")
        lines.extend(f"    WARNING: {w}" for w in p.warnings())
    if not free:
        lines.append("Plug in the USB-serial adapter of the slider or the load cell and run `rig ports` "
                     "again. The simulated rig needs no port: `rig probe` and `rig run` start it.")
    else:
        lines.append("Next: `rig config init --slider PORT --loadcell PORT` writes a config and probes it.")
    return "\n".join(lines)
