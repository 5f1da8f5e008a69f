"""`rig position`, `rig move`, `rig reset-alarm`, `rig tare`, `rig calibrate`, `rig home`: the rig
by hand, between trials."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rig.cli.args import _positive_float, _reply, _rig_config
from rig.errors import RigError


def cmd_position(args: argparse.Namespace) -> int:
    """`rig position`: read the slider position, status and force."""
    if args.socket:
        return _position_from_daemon(args)
    from rig.control.manual import position
    from rig.specs.config import load_config

    info = position(load_config(args.config))
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        force = "-" if info["force_N"] is None else f"{info['force_N']:.3f} N (untared)"
        state = "moving" if info["moving"] else "ready" if info["ready"] else "not ready"
        alarm = f", ALARM 0x{info['alarm_code']:02X}" if info["alarm_code"] else ""
        print(f"position {info['position_mm']:.3f} mm, {state}{alarm}; force {force}\n"
              f"devices  {info['devices']}")
    return 0


def _position_from_daemon(args: argparse.Namespace) -> int:
    """The daemon owns the devices: its status carries the position (read now while idle,
    the loop's latest during a trial)."""
    from rig.service.client import request

    st = _reply(request(Path(args.socket), {"cmd": "status"}))
    snap = st.get("snapshot") or {}
    if "error" in snap or "position_mm" not in snap:
        raise RigError(f"the daemon could not read the position: {snap.get('error', 'devices busy')}")
    info = {"position_mm": snap["position_mm"], "force_N": snap.get("force_N"), "state": st["state"],
            "alarm_code": snap.get("alarm_code", 0)}
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    force = "-" if info["force_N"] is None else f"{info['force_N']:.3f} N"
    alarm = f", ALARM 0x{info['alarm_code']:02X}" if info["alarm_code"] else ""
    print(f"position {info['position_mm']:.3f} mm, daemon {st['state']}{alarm}; force {force}")
    return 0


def cmd_move(args: argparse.Namespace) -> int:
    """`rig move`: move the probe to a position (under the rig's limits)."""
    from rig.control.manual import move
    from rig.specs.config import load_config

    r = move(load_config(args.config), args.to_mm, args.speed_mm_s)
    print(f"moved from {r['from_mm']:.3f} mm to {r['position_mm']:.3f} mm")
    return 0


def cmd_reset_alarm(args: argparse.Namespace) -> int:
    """`rig reset-alarm`: clear the drive's alarm once its cause is gone."""
    if args.socket:
        from rig.service.client import request

        r = _reply(request(Path(args.socket), {"cmd": "reset_alarm"}))
    else:
        from rig.control.manual import reset_alarm
        from rig.specs.config import load_config

        r = reset_alarm(load_config(args.config))
    before = f"alarm 0x{r['alarm_before']:02X}" if r["alarm_before"] else "no alarm"
    print(f"alarm reset: {before} before, none now")
    return 0


def cmd_tare(args: argparse.Namespace) -> int:
    """`rig tare`: measure the load cell's free-air zero (probe out of contact) and save it."""
    from rig.control.zero import tare
    from rig.specs.config import load_config

    r = tare(load_config(args.config), args.seconds)
    was = "" if r["previous_N"] is None else f"; it was {r['previous_N']:+.4f} N"
    print(f"load cell {r['cell']}: zero {r['zero_N']:+.4f} N (std {r['std_N']:.4f} N, {r['readings']} "
          f"readings) saved in {r['path']}{was}")
    if r["config_zero_N"] is not None:
        print(f"note: the config's loadcell.zero_N ({r['config_zero_N']:g} N) takes precedence over it")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    """`rig calibrate`: calibrate the load cell with known masses and save it in the config."""
    from rig.control.calibration import (
        calibration,
        fit_calibration,
        format_calibration,
        measure,
        read_readings_file,
        save_calibration,
    )
    from rig.specs.config import load_config

    if not args.config:
        raise RigError("rig calibrate: give --config FILE: the calibration is saved into it (created if "
                       "absent, the built-in simulated rig's defaults otherwise)")
    path = Path(args.config)
    config = load_config(path if path.exists() else None)
    if args.readings:
        lines = read_readings_file(args.readings)
        given = [x for x in lines if x[1] is not None]
        if given and len(given) != len(lines):
            raise RigError(f"--readings {args.readings}: give a reading for every mass, or for none")
        if given:
            points = [(m, r, s or 0.0, n or 1) for m, r, s, n in lines]
        else:
            points = measure(config, [m for m, *_ in lines], args.seconds, lambda m: None, print)
    else:
        if not args.masses:
            raise RigError("rig calibrate: give the masses in g (e.g. rig calibrate 200 500 1000 --config "
                           "rig.yaml), or --readings FILE")
        masses = [0.0, *args.masses]

        def confirm(m: float) -> None:
            what = ("take every mass off the probe (nothing touching it)" if m == 0
                    else f"place {m:g} g on the probe")
            try:
                input(f"{what}, then press Enter: ")
            except EOFError:
                raise RigError("rig calibrate: cancelled (no confirmation)") from None

        points = measure(config, masses, args.seconds, confirm, print)
    cal = calibration(config, points, config.calibration)
    fit = fit_calibration(cal.masses_g, cal.readings_N, [p[2] for p in points], [p[3] for p in points])
    saved = save_calibration(path, cal)
    if args.json:
        from dataclasses import asdict

        print(json.dumps({**asdict(cal), "deviations_N": fit["deviations_N"], "config": str(saved)}, indent=2))
    else:
        print(format_calibration(cal, fit, saved))
    return 0


def cmd_home(args: argparse.Namespace) -> int:
    """`rig home`: run the drive's return-to-home operation."""
    from rig.control.manual import move
    from rig.specs.config import load_config

    r = move(load_config(args.config), 0.0, 0.0, home=True)
    print(f"homed: from {r['from_mm']:.3f} mm to {r['position_mm']:.3f} mm")
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register position, move, reset-alarm, tare, calibrate and home with their handlers."""
    r = sub.add_parser("position", help="read the slider position, status and force",
                       description="Read the slider's position, status and force. With --socket, asks "
                                   "the daemon (which owns the devices).")
    _rig_config(r)
    r.add_argument("--json", action="store_true")
    r.add_argument("--socket", help="ask the daemon on this control socket instead")
    r.set_defaults(func=cmd_position)

    r = sub.add_parser("move", help="move the probe to a position (under the rig's limits)",
                       description="Move the slider to an absolute position, watching force, travel, "
                                   "speed and drive alarms as a trial does. Ctrl-C stops.")
    r.add_argument("--to-mm", type=float, required=True, help="target position, mm (slider coordinates)")
    r.add_argument("--speed-mm-s", type=float, default=2.0, help="speed, mm/s (default 2)")
    _rig_config(r)
    r.set_defaults(func=cmd_move)

    r = sub.add_parser("reset-alarm", help="clear the drive's alarm once its cause is gone",
                       description="Reset the drive's alarm (the alarm-reset command of its register "
                                   "map) and read the status back: fails if the drive still reports an "
                                   "alarm. With --socket, asks the daemon (which owns the devices).")
    _rig_config(r)
    r.add_argument("--socket", help="ask the daemon on this control socket instead")
    r.set_defaults(func=cmd_reset_alarm)

    r = sub.add_parser("tare", help="measure the load cell's free-air zero (probe out of contact) and save it",
                       description="Average the load cell with nothing touching the probe and save it as "
                                   "its free-air zero (in recorder.out_dir, keyed by the load cell). Every "
                                   "later trial, `rig run` or the daemon's, counts the force the tissue "
                                   "carries from it: a trial started in contact knows its preload, and a "
                                   "preload beyond limits.max_preload_share of the force limit is refused.")
    _rig_config(r)
    r.add_argument("--seconds", type=float, default=1.0, help="how long to average (default 1 s)")
    r.set_defaults(func=cmd_tare)

    r = sub.add_parser("calibrate", help="calibrate the load cell with known masses and save it in the config",
                       description="Read the load cell empty and with each mass on the probe (you place each "
                                   "and press Enter; the simulated rig places them itself), fit the line: "
                                   "sensitivity, offset and linearity with their uncertainties, saved with the "
                                   "date into the config's calibration: section. Every log's header carries "
                                   "it; rig check and the log warn when it is older than "
                                   "calibration.max_age_days or a force may go beyond the calibrated range.")
    r.add_argument("masses", nargs="*", type=_positive_float, metavar="GRAMS",
                   help="the masses, in g, placed one at a time (the empty probe is read first)")
    r.add_argument("--config", help="the rig config to save the calibration into (created if absent)")
    r.add_argument("--readings", metavar="FILE",
                   help="a scripted run: one mass (g) a line, read without asking; or each mass with its "
                        "reading (N, and optionally its std and count), fitted without the cell")
    r.add_argument("--seconds", type=_positive_float, default=1.0,
                   help="how long to read each mass (default 1 s)")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_calibrate)

    r = sub.add_parser("home", help="run the drive's return-to-home operation")
    _rig_config(r)
    r.set_defaults(func=cmd_home)
