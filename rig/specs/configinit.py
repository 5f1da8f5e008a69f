"""`rig config init`: a commented config for a real rig, naming only what differs from the defaults."""

from __future__ import annotations

import re
from pathlib import Path

from rig.errors import RigError
from rig.specs.config import LoadCellConfig, SliderConfig, parse_config

_HOST_PORT = re.compile(r"^(?P<host>[\w.-]+):(?P<port>\d{1,5})$")


def _yaml_str(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def config_text(*, slider_port: str, loadcell_port: str, baudrate: int = 115200, parity: str = "E",
                device_id: int = 1, loadcell_baudrate: int = 115200, loadcell_mode: str = "stream") -> str:
    """A commented config for a real rig with only what differs from the defaults: its ports, serial
    settings, drive unit and the load cell's mode."""
    sd, ld = SliderConfig(), LoadCellConfig()
    out = ["# A real rig: only what differs from the built-in defaults (config/sim-rig.yaml spells",
           "# every field out). Check it with `rig probe --config THIS_FILE`.",
           "name: lab rig", "", "slider:"]
    tcp = _HOST_PORT.match(slider_port)
    if tcp:
        out += ["  backend: modbus-tcp",
                f"  host: {_yaml_str(tcp['host'])}",
                f"  tcp_port: {int(tcp['port'])}"]
    else:
        out += ["  backend: modbus-rtu            # modbus-tcp (host:, tcp_port:) for a drive on Ethernet",
                f"  port: {_yaml_str(slider_port):<24}  # `rig ports` lists the serial ports"]
        if baudrate != sd.baudrate:
            out.append(f"  baudrate: {baudrate:<20}  # the drive's BAUD switch")
        if parity != sd.parity:
            out.append(f"  parity: {parity:<22}  # Oriental AZ drives ship 8E1")
    if device_id != sd.device_id:
        out.append(f"  device_id: {device_id:<19}  # the drive's ID switch")
    out += ["  # steps_per_mm: 100               # from the slider's lead and the drive's resolution: check it",
            "  # registers:",
            "  #   comm_timeout_ms: 0x....       # the drive's communication-timeout parameter (drive manual);",
            "  #                                 # until it is named, `rig run` refuses to start, unless",
            "  # allow_no_comm_timeout: true     # says the rig runs without that backstop",
            "", "loadcell:", "  backend: serial",
            f"  port: {_yaml_str(loadcell_port):<24}  # `rig ports` lists the serial ports"]
    if loadcell_baudrate != ld.baudrate:
        out.append(f"  baudrate: {loadcell_baudrate}")
    if loadcell_mode != ld.mode:
        out.append(f"  mode: {loadcell_mode:<24}  # the cell answers a request each tick")
        out.append('  # request: "?\\r\\n"              # Mark-10 style; Loadstar DI: "w\\r"')
    else:
        out.append("  # mode: poll                      # if the cell answers requests instead of streaming")
    out += ["  # pattern: ...                    # a regular expression with a group 'value' when lines are",
            "  #                                 # not '<number> <unit>'; unit: N when they carry none", ""]
    return "\n".join(out)


def write_config(path: str | Path, *, force: bool = False, **fields) -> Path:
    """Write the config (checked by parsing it back); refuses to overwrite unless `force`."""
    p = Path(path)
    if p.exists() and not force:
        raise RigError(f"{p} exists: pick another --out, or --force to overwrite it")
    text = config_text(**fields)
    parse_config(text, str(p))  # what we write must load
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    except OSError as exc:
        raise RigError(f"cannot write {p}: {exc.strerror or exc}") from None
    return p
