"""`rig bench`, `rig ports`, `rig probe`, `rig spy` and `rig config init`."""

from __future__ import annotations

import argparse
import json

from rig.cli.args import _seconds


def cmd_bench(args: argparse.Namespace) -> int:
    """`rig bench`: measure loop timing, estimator and logging costs."""
    from rig.diagnostics.bench import format_bench, run_bench

    result = run_bench(duration_s=args.duration, rate_Hz=args.rate, progress=not args.json,
                       wire=args.wire, find_max_rate=args.max_rate, load=args.load,
                       realtime="off" if args.no_realtime else "auto")
    print(json.dumps(result, indent=2) if args.json else format_bench(result))
    return 0


def cmd_ports(args: argparse.Namespace) -> int:
    """`rig ports`: list the serial ports, with USB identity and latency timer."""
    from rig.diagnostics.ports import format_ports, list_ports

    ports = list_ports()
    if args.json:
        print(json.dumps([p.as_dict() for p in ports], indent=2))
    else:
        print(format_ports(ports))
    return 0


def cmd_probe(args: argparse.Namespace) -> int:
    """`rig probe`: check that the slider and load cell answer, without moving."""
    from rig.diagnostics.probe import probe
    from rig.specs.config import load_config

    report = probe(load_config(args.config), seconds=args.seconds, spy_path=args.spy)
    print(json.dumps(report.as_dict(), indent=2) if args.json else report.format())
    return report.exit_status()


def cmd_spy(args: argparse.Namespace) -> int:
    """`rig spy`: decode a wire-spy file (--spy of run, probe, daemon)."""
    from rig.views.spyview import format_spy, read_spy

    print(format_spy(read_spy(args.file), show_hex=args.hex, channel=args.channel))
    return 0


def cmd_config_init(args: argparse.Namespace) -> int:
    """`rig config init`: write a commented config for a real rig and probe it."""
    from rig.diagnostics.probe import probe
    from rig.specs.config import load_config
    from rig.specs.configinit import write_config

    path = write_config(args.out, slider_port=args.slider, loadcell_port=args.loadcell,
                        baudrate=args.baudrate, parity=args.parity, device_id=args.device_id,
                        loadcell_baudrate=args.loadcell_baudrate, loadcell_mode=args.loadcell_mode,
                        force=args.force)
    print(f"wrote {path}; probing it (rig probe --config {path})\n")
    report = probe(load_config(path), seconds=args.seconds)
    print(report.format())
    return report.exit_status()


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register `rig bench`, `rig ports`, `rig probe`, `rig spy`, `rig config` with their handlers."""
    r = sub.add_parser("bench", help="measure loop timing, estimator and logging costs",
                       description="Loop period jitter and late ticks at the loop rate on the real "
                                   "clock with in-process simulated devices; RLS update time; "
                                   "per-sample recording cost; replay speed.")
    r.add_argument("--duration", type=float, default=60.0, help="real-clock run length, s (default 60)")
    r.add_argument("--rate", type=float, default=100.0, help="loop rate, Hz (default 100)")
    r.add_argument("--wire", choices=["none", "rtu", "tcp"], default="none",
                   help="devices: in-process (none, default) or the simulated devices over Modbus "
                        "RTU on a pseudo-terminal / Modbus TCP on loopback")
    r.add_argument("--load", type=int, default=0, metavar="N",
                   help="run N CPU-bound processes beside the loop (a busy machine)")
    r.add_argument("--no-realtime", action="store_true",
                   help="run the loop at normal priority (default: SCHED_FIFO where allowed)")
    r.add_argument("--max-rate", action="store_true",
                   help="also find the highest loop rate without late ticks (5 s runs)")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_bench)

    r = sub.add_parser("ports", help="list the serial ports, with USB identity and latency timer",
                       description="The serial ports of this machine (pyserial's list_ports) with their "
                                   "description, USB vendor:product and serial number, and for USB-serial "
                                   "adapters on Linux the latency timer, flagged above 1 ms.")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_ports)

    r = sub.add_parser("probe", help="check that the slider and load cell answer, without moving",
                       description="Open the slider and load cell the config names, move nothing, and "
                                   "report: the drive's status, alarm and position, whether its "
                                   "communication timeout could be set; the load cell's lines as received "
                                   "and parsed; the time each bus transaction takes against the loop "
                                   "period. Every problem names the config field to change. Exit status: "
                                   "0 all well, 1 problems found, 3 a device does not answer.")
    r.add_argument("--config", help="rig config (YAML); default: the built-in simulated rig on the wire")
    r.add_argument("--seconds", type=_seconds, default=2.0,
                   help="how long to time bus transactions and count lines (default 2)")
    r.add_argument("--spy", metavar="FILE", help="also write every frame and line to FILE")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_probe)

    r = sub.add_parser("spy", help="decode a wire-spy file (--spy of run, probe, daemon)",
                       description="Print a spy file decoded: each Modbus frame's function code, "
                                   "addresses and values, CRC good or bad, round-trip time; each "
                                   "load-cell line as sent and received; then a summary.")
    r.add_argument("file", help="spy file written with --spy")
    r.add_argument("--hex", action="store_true", help="also print each frame's bytes")
    r.add_argument("--channel", choices=["rtu", "tcp", "cell"], help="only this channel")
    r.set_defaults(func=cmd_spy)

    r = sub.add_parser("config", help="write a rig config for a real rig",
                       description="Configs for a real rig.")
    csub = r.add_subparsers(dest="config_command", metavar="ACTION")
    csub.required = True
    c = csub.add_parser("init", help="write a commented config for a real rig and probe it",
                        description="Write a config naming the slider's and the load cell's ports (only "
                                    "what differs from the defaults, each field commented), then run "
                                    "`rig probe` on it.")
    c.add_argument("--slider", required=True, metavar="PORT",
                   help="the drive's serial port (e.g. /dev/ttyUSB0), or HOST:PORT for Modbus TCP")
    c.add_argument("--loadcell", required=True, metavar="PORT", help="the load cell's serial port")
    c.add_argument("--out", default="config/lab-rig.yaml", help="file to write (default config/lab-rig.yaml)")
    c.add_argument("--baudrate", type=int, default=115200, help="drive baud rate (default 115200)")
    c.add_argument("--parity", choices=["N", "E", "O"], default="E",
                   help="drive parity (default E: Oriental AZ drives ship 8E1)")
    c.add_argument("--device-id", type=int, default=1, help="drive unit id (default 1)")
    c.add_argument("--loadcell-baudrate", type=int, default=115200)
    c.add_argument("--loadcell-mode", choices=["stream", "poll"], default="stream")
    c.add_argument("--seconds", type=_seconds, default=2.0, help="probe duration (default 2)")
    c.add_argument("--force", action="store_true", help="overwrite the file if it exists")
    c.set_defaults(func=cmd_config_init)
