"""`rig daemon` and its clients (`rig start`, `stop`, `estop`, `return`, `status`, `watch`),
`rig logs` and `rig web`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rig.cli.args import _campaign_options, _reply, _rig_config, _socket, _specimen_size, client
from rig.errors import RigError


def cmd_daemon(args: argparse.Namespace) -> int:
    """`rig daemon`: run the control service (owns the devices; one trial at a time)."""
    from rig.service.daemon import run_daemon
    from rig.specs.config import load_config

    config = load_config(args.config)
    return run_daemon(config, Path(args.socket) if args.socket else None, spy_path=args.spy)


def cmd_start(args: argparse.Namespace) -> int:
    """`rig start`: start a protocol on the daemon (or, with --characterize, a campaign)."""
    from rig.service.client import request
    from rig.specs.yamlspec import read_text

    if args.characterize:
        req = {"cmd": "start", "specimen": args.specimen, "operator": args.operator,
               "characterize": {"model": args.fit_model, "indenter": args.indenter,
                                "max_trials": args.max_trials, "budget_min": args.budget_min,
                                "target_rse": args.target_rse, "rest_s": args.rest_s},
               "from_contact": args.from_contact}
        if args.protocol:
            path = Path(args.protocol).resolve()
            req.update(protocol_text=read_text(path, "protocol file"), protocol_path=str(path))
        reply = _reply(request(_socket(args), req))
        for w in reply.get("warnings") or []:
            print(w, file=sys.stderr)
        print(f"characterizing specimen {reply['characterize']}; logs and journal in {reply['out']} "
              "(rig watch follows it, rig stop ends it)")
        return 0
    if not args.protocol:
        raise RigError("rig start: give a protocol file (or --characterize for a campaign)")
    path = Path(args.protocol).resolve()
    text = read_text(path, "protocol file")
    from rig.specs.specimen import dimensions

    req = {"cmd": "start", "protocol_text": text, "protocol_path": str(path), "specimen": args.specimen,
           "operator": args.operator, "notes": args.notes, "from_contact": args.from_contact,
           **{k: float(v) for k, v in dimensions(args.thickness_mm, args.area_mm2).items()}}
    if args.model:
        req.update(model_text=read_text(Path(args.model).resolve(), "model file"), model_path=args.model)
    reply = _reply(request(_socket(args), req))
    for w in reply.get("warnings") or []:
        print(w, file=sys.stderr)
    print(f"started '{reply['protocol']}'; log {reply['log']}")
    return 0


def cmd_stop(args: argparse.Namespace) -> int:
    """`rig stop`: stop the running trial, then return to the start position."""
    from rig.service.client import request

    mode = "hold" if args.hold else "abort"
    reply = _reply(request(_socket(args), {"cmd": "stop", "mode": mode}))
    # what the daemon did (a trial stopped, a start cancelled, a campaign ended between trials)
    print(reply.get("message") or f"the daemon took the stop ({mode}) and said nothing more")
    return 0


def cmd_estop(args: argparse.Namespace) -> int:
    """`rig estop`: emergency stop: stop the motor now, nothing else."""
    from rig.service.client import request

    reply = _reply(request(_socket(args), {"cmd": "estop"}))
    print(f"emergency stop: {reply.get('message', 'sent')}")
    return 0


def cmd_return(args: argparse.Namespace) -> int:
    """`rig return`: move the probe back out of the specimen after an estop or a fault left it in
    contact (to where that trial started)."""
    from rig.service.client import request

    # a return moves the slider: the reply comes when it has arrived (or was stopped)
    reply = _reply(request(_socket(args), {"cmd": "return"}, 120.0))
    print(reply["message"])
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    """`rig status`: what the daemon is doing."""
    from rig.service.client import request
    from rig.views.watch import format_status

    reply = _reply(request(_socket(args), {"cmd": "status"}))
    print(json.dumps(reply, indent=2) if args.json else format_status(reply))
    return 0


def cmd_watch(args: argparse.Namespace) -> int:
    """`rig watch`: live view of the running trial until it ends."""
    from rig.service.client import stream
    from rig.views.watch import Watcher

    watcher = Watcher(sys.stdout)
    for msg in stream(_socket(args), {"cmd": "watch", "rate_Hz": args.rate}, timeout_s=30.0):
        _reply(msg)
        if msg.get("end"):
            watcher.finish(msg.get("last"))
            return 0
        watcher.update(msg.get("snapshot"), msg.get("trial", {}), msg.get("campaign"))
    return 0


def cmd_logs(args: argparse.Namespace) -> int:
    """`rig logs`: the trials recorded, newest first."""
    from rig.recording.recovery import list_trials
    from rig.specs.config import load_config
    from rig.views.watch import format_logs, trial_figures

    out_dir = Path(args.dir) if args.dir else Path(load_config(args.config).recorder.out_dir)
    entries = list_trials(out_dir)
    figures = trial_figures(entries)
    if args.table:
        from rig.views.logtable import table_rows, write_logs_table

        path = write_logs_table(table_rows(entries, figures, out_dir), args.table)
        print(f"table      {path} ({len(entries)} trials)")
        return 0
    if args.json:
        print(json.dumps([{**e.as_dict(), **f} for e, f in zip(entries, figures, strict=True)], indent=2))
    else:
        print(format_logs(entries, out_dir, figures))
    return 0


def cmd_web(args: argparse.Namespace) -> int:
    """`rig web`: the lab in a browser: live console, trial history, maps."""
    try:
        from rig.web.app import WebOptions
        from rig.web.server import serve
    except ImportError as exc:
        raise RigError(f"rig web needs the web extra ({exc.name} is missing): "
                       "python3 -m pip install 'indentation-rig[web]'") from None
    from rig.service.daemon import default_socket_path
    from rig.specs.config import load_config

    config = load_config(args.config)
    sock = Path(args.socket) if args.socket else default_socket_path(config)
    opts = WebOptions(socket_path=sock, logs=Path(args.logs or config.recorder.out_dir),
                      protocols=Path(args.protocols), tables=Path(args.tables), config=config,
                      host=args.host, port=args.port, exposed=args.expose)
    return serve(opts)


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register daemon, start, stop, estop, return, status, watch, logs and web with their handlers."""
    r = sub.add_parser("daemon", help="run the control service (owns the devices; one trial at a time)",
                       description="Own the slider and load cell and serve trial requests on a Unix socket "
                                   "(mode 0660: owner and the config's daemon.group). Recovers logs left "
                                   "unfinished by a crash at start. Speaks sd_notify when NOTIFY_SOCKET "
                                   "is set.")
    _rig_config(r)
    r.add_argument("--socket", help="control socket path (default: daemon.socket, $RIG_SOCKET, "
                                    "/run/rig/rigd.sock as root, else $XDG_RUNTIME_DIR/rig/rigd.sock)")
    r.add_argument("--spy", metavar="FILE", help="write every Modbus frame and load-cell line to FILE "
                                                  "while the daemon runs (read it with `rig spy FILE`)")
    r.set_defaults(func=cmd_daemon)

    r = client(sub, "start", "start a protocol on the daemon (or, with --characterize, a campaign)", cmd_start)
    r.add_argument("protocol", nargs="?",
                   help="protocol file (YAML); with --characterize, the campaign's first trial (default: "
                        "an exploratory ramp-hold inside the limits)")
    r.add_argument("--specimen", default="specimen")
    r.add_argument("--operator", default="", help="default: your user name")
    r.add_argument("--notes", default="")
    _specimen_size(r)
    r.add_argument("--model", metavar="MODEL.json", help="run this saved model in the loop")
    r.add_argument("--from-contact", action="store_true",
                   help="start although a trial cut short (an estop, a fault) left the probe in the specimen: "
                        "run from there, its preload counted (without it such a start is refused; "
                        "`rig return` raises the probe instead)")
    g = r.add_argument_group("campaign (rig characterize on the daemon; rig watch shows it, rig stop ends it)")
    g.add_argument("--characterize", action="store_true",
                   help="run, fit, diagnose and design trials until the model is right")
    g.add_argument("--fit-model", default="proposed",
                   help="the model the campaign starts from (default: proposed)")
    _campaign_options(g)

    r = client(sub, "stop", "stop the running trial, then return to the start position", cmd_stop)
    r.add_argument("--hold", action="store_true", help="stop and stay where it is")

    client(sub, "estop", "emergency stop: stop the motor now, nothing else", cmd_estop)

    client(sub, "return", "move the probe back out of the specimen after an estop or a fault left it in "
           "contact (to where that trial started)", cmd_return)

    r = client(sub, "status", "what the daemon is doing", cmd_status)
    r.add_argument("--json", action="store_true")

    r = client(sub, "watch", "live view of the running trial until it ends", cmd_watch)
    r.add_argument("--rate", type=float, default=10.0, help="updates per second (default 10)")

    r = sub.add_parser("logs", help="the trials recorded, newest first",
                       description="List the trial logs in the recorder directory, newest first.")
    r.add_argument("--dir", help="directory of logs (default: the config's recorder.out_dir)")
    r.add_argument("--config")
    r.add_argument("--json", action="store_true")
    r.add_argument("--table", metavar="FILE", help="write the trials as a table, one row per trial (specimen, "
                   "protocol, outcome, peak force, stiffness at the hold's end, estimator error, duration, "
                   "calibration date): CSV, or Parquet for a .parquet name")
    r.set_defaults(func=cmd_logs)

    r = sub.add_parser("web", help="the lab in a browser: live console, trial history, maps",
                       description="Serve the web application: the console (the live trial, a start from "
                                   "the protocol library after its check, STOP / HOLD / ESTOP), the history "
                                   "of the trials in the log folder, and batch tables (rig analyze --each "
                                   "--table) as maps. A client of the daemon: it never opens a device. "
                                   "Prints its URL with a token (also written to a file only you can read); "
                                   "every page needs it.")
    r.add_argument("--port", type=int, default=8750, help="TCP port (default 8750; 0: a free one)")
    r.add_argument("--logs", metavar="DIR", help="the log folder (default: the config's recorder.out_dir)")
    r.add_argument("--protocols", metavar="DIR", default="protocols",
                   help="the protocol library the console starts from (default: ./protocols)")
    r.add_argument("--tables", metavar="DIR", default=".",
                   help="where the maps page finds batch tables (default: the current directory)")
    r.add_argument("--host", default="127.0.0.1",
                   help="address to serve on (default 127.0.0.1: this machine only); another needs --expose")
    r.add_argument("--expose", action="store_true",
                   help="allow --host beyond loopback: anyone reaching it with the token can watch, read the "
                        "logs, start trials and stop the rig (plain HTTP)")
    r.add_argument("--socket", help="the daemon's control socket (default: daemon.socket, $RIG_SOCKET, ...)")
    r.add_argument("--config", help="rig config (the socket, the log folder, the limits drawn)")
    r.set_defaults(func=cmd_web)
