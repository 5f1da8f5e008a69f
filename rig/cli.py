"""The `rig` command: one small function per subcommand.

Every error a user can cause ends as one line on stderr and a non-zero exit status,
never a traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from rig import __version__
from rig.errors import RigError

EXIT_ERROR = 2  # bad input: file, argument, limits
EXIT_FAULT = 3  # the trial ran but ended on a fault
EXIT_INTERRUPTED = 130
EXIT_CURVES_FAILED = 64  # a batch: plus the number of curves it could not analyse (at most 61: 125)


def _positive_or_zero(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def _positive_float(text: str) -> float:
    value = _positive_or_zero(text)
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _specimen_size(r: argparse.ArgumentParser) -> None:
    r.add_argument("--thickness-mm", type=_positive_float, metavar="MM",
                   help="the specimen's thickness, kept in the log's header: the bottom effect's thickness in "
                        "rig analyze, the strain (indentation / thickness) in rig replay")
    r.add_argument("--area-mm2", type=_positive_float, metavar="MM2",
                   help="the specimen's contact area, kept in the log's header: the stress (force / area) in "
                        "rig replay")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text}")
    return value


def _draws(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number of draws, got {text}") from None
    if not 2 <= value <= 10000:
        raise argparse.ArgumentTypeError(f"must be between 2 and 10000 draws, got {text}")
    return value


def _seconds(text: str) -> float:
    value = _positive_or_zero(text)
    if not 0.2 <= value <= 60:
        raise argparse.ArgumentTypeError(f"must be between 0.2 and 60 s, got {text}")
    return value


# ------------------------------------------------------------------ commands

def cmd_run(args: argparse.Namespace) -> int:
    from rig.service.run import RunOptions, run_trial
    from rig.specs.config import load_config
    from rig.specs.protocol import load_protocol

    config = load_config(args.config)
    proto = load_protocol(args.protocol, config)  # refused here, before anything moves
    from rig.specs.specimen import dimensions

    opts = RunOptions(specimen=args.specimen, operator=args.operator, notes=args.notes,
                      out_dir=args.out, speed=args.speed, progress=not args.quiet, live_port=args.live,
                      model_path=args.model, spy_path=args.spy,
                      dimensions=dimensions(args.thickness_mm, args.area_mm2))
    result = run_trial(proto, config, opts)
    print(f"trial {result.outcome}: {result.samples} samples in {result.duration_s:.1f} s "
          f"({result.late_ticks} late, {result.missed_ticks} missed ticks)")
    if result.fault:
        print(f"fault: {result.fault}")
    for notice in result.notices:
        print(f"note: {notice}")
    print(f"log: {result.log_path}")
    if result.outcome == "fault":
        return EXIT_FAULT
    if result.outcome in ("aborted", "estopped", "stopped"):
        return EXIT_INTERRUPTED
    return 0


CHARACTERIZE_HELP = (
    "Characterise a specimen on the rig by itself: an exploratory trial (or --protocol), then after "
    "every trial a joint fit, the diagnosis, and the next trial: the protocol that best separates "
    "look-alike effects or, once the model is adequate, the one that most narrows the worst-determined "
    "parameter. Stops when the model is adequate and every parameter is within --target-rse, when no "
    "protocol within the rig's limits does better, or when the budget is spent. Every decision is "
    "journaled beside the logs; Ctrl-C stops the trial running (as for rig run) and the campaign with it.")


def cmd_characterize(args: argparse.Namespace) -> int:
    from rig.service.characterize import Request, characterize, format_campaign, plot_campaign
    from rig.specs.config import load_config

    config = load_config(args.config)
    if args.protocol:
        from rig.specs.protocol import load_protocol

        load_protocol(args.protocol, config)  # refused here, before anything moves
    # a name, never a path: the campaign's folder lies inside the log folder whatever it says
    from rig.recording.names import file_part

    stem = file_part(args.specimen, default="specimen")
    out = Path(args.out or config.recorder.out_dir) / f"characterize-{stem}"
    say = (lambda _: None) if args.json else print
    req = Request(args.specimen, config, out, model=args.model, indenter=args.indenter, first=args.protocol,
                  max_trials=args.max_trials, budget_min=args.budget_min, target_rse=args.target_rse,
                  rest_s=args.rest_s, speed=args.speed, say=say)
    camp = characterize(req)
    figure = plot_campaign(camp, out / "campaign.png") if any(t.model for t in camp.turns) else None
    if args.json:
        print(json.dumps({**camp.summary(), "figure": str(figure) if figure else None}, indent=2))
    else:
        print(format_campaign(camp))
        if figure:
            print(f"figure     {figure}")
    return EXIT_INTERRUPTED if camp.status == "stopped" else 0


def cmd_replay(args: argparse.Namespace) -> int:
    from rig.recording.logs import export_csv, read_log
    from rig.views.replay import format_summary, format_table, plot_compare, plot_log, summarize, table_row

    if len(args.log) > 1:
        if args.csv:
            raise RigError(f"--csv writes one log's samples: give one log, not {len(args.log)}")
        logs = [read_log(p) for p in args.log]
        rows = [table_row(summarize(log)) for log in logs]
        if args.plot:
            plot_compare(logs, args.plot)
        if args.json:
            print(json.dumps({"trials": rows, "plot": str(args.plot) if args.plot else None}, indent=2))
        else:
            print(format_table(rows))
            if args.plot:
                print(f"plot       {args.plot}")
        return 0
    log = read_log(args.log[0])
    summary = summarize(log)
    if args.csv:
        n = export_csv(log, args.csv)
        summary["csv"] = {"path": str(args.csv), "rows": n}
    if args.plot:
        plot_log(log, args.plot)
        summary["plot"] = str(args.plot)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(format_summary(summary))
        if args.csv:
            print(f"csv        {args.csv} ({summary['csv']['rows']} rows)")
        if args.plot:
            print(f"plot       {args.plot}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from rig.specs.config import load_config
    from rig.specs.protocol import FORCE_STEPS, load_protocol, plan

    config = load_config(args.config)
    proto = load_protocol(args.protocol, config)
    p = plan(proto, config)
    limits = proto.effective_limits(config.limits)
    resolution = 1.0 / config.sim.slider.steps_per_mm
    # from the plan's pieces, never its samples: a long protocol is not sampled to be checked
    order = p.excitation_order(resolution)
    info = {
        "protocol": proto.name,
        "file": proto.source_path,
        "valid": True,
        "steps": [s.kind for _, s in proto.run_steps()],
        "executed_steps": proto.executed_steps,
        "duration_s": round(p.duration_s, 2),
        "duration_is_upper_bound": p.upper_bound,
        "depths_mm": p.depths_mm,
        "depths_from": "first contact" if p.depths_from_contact else "start",
        "speeds_mm_s": p.speeds_mm_s,
        "max_position_mm": p.max_position_mm,
        "limits": {"max_force_N": limits.max_force_N, "max_speed_mm_s": limits.max_speed_mm_s,
                   "travel_mm": list(limits.travel_mm),
                   "max_protocol_steps": config.limits.max_protocol_steps},
        "excitation_order": order,
    }
    # a force step's clock starts at contact: out of contact it first seeks the surface, at most
    # to its max_mm, at the seek speed (each force step that does not follow another one)
    seek_mm_s = config.force.seek_speed_share * limits.max_speed_mm_s
    seek_s = 0.0
    after_force = False
    for _, step in proto.run_steps():
        is_force = isinstance(step, FORCE_STEPS)
        if is_force and not after_force:
            seek_s += step.max_mm / seek_mm_s
        after_force = is_force
    if seek_s:
        info["force_seek_up_to_s"] = round(seek_s, 1)
    from rig.control.calibration import calibration_warnings

    cal_warnings = calibration_warnings(config, limits.max_force_N) if config.loadcell.backend != "none" else []
    if config.calibration is not None:
        info["calibration"] = {"date": config.calibration.date, "range_N": list(config.calibration.range_N),
                               "warnings": cal_warnings}
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    bound = "up to " if p.upper_bound else ""
    repeats = ""
    if proto.repeat > 1:
        rest = f", {proto.rest_s:g} s rest between" if proto.rest_s > 0 else ""
        repeats = f"  (x{proto.repeat}{rest}: {proto.executed_steps} steps)"
    speeds = [s.speed_mm_s for s in proto.steps if hasattr(s, "speed_mm_s")]  # the same every repeat
    print(f"{proto.source_path}: OK  '{proto.name}'")
    if proto.description:
        print(f"  {proto.description}")
    print(f"  steps     {' -> '.join(s.kind for s in proto.steps)}{repeats}")
    print(f"  duration  {bound}{p.duration_s:.1f} s (including {config.loop.tare_s:g} s tare)")
    print(f"  depths    {_depths_text(p)}   speeds {', '.join(f'{v:g}' for v in speeds) or '-'} mm/s")
    if seek_s:
        print(f"  force     steps timed from contact: seeking the surface at {seek_mm_s:g} mm/s adds up to "
              f"{seek_s:.0f} s")
    print(f"  limits    force {limits.max_force_N:g} N, speed {limits.max_speed_mm_s:g} mm/s, "
          f"travel [{limits.travel_mm[0]:g}, {limits.travel_mm[1]:g}] mm")
    note = {0: "no motion: nothing is identifiable",
            1: "ramp-and-hold class: only f(t) = k x(t-1) is identifiable online"}.get(
        order, "rich enough for a model with more than one input lag")
    print(f"  excitation order {order} ({note})")
    for w in cal_warnings:
        print(f"  WARNING   {w}")
    return 0


def _depths_text(p) -> str:
    """The ramps' depths as the plan has them: one repeat's when every repeat goes as deep (from
    its own contact, or the start), else all of them, from the first contact: an approach that
    starts in contact re-zeroes there, and the next repeat goes deeper."""
    per_repeat = p.depths_by_repeat
    if not p.depths_mm:
        return "-"
    if all(d == per_repeat[0] for d in per_repeat):
        each = f" in each of {len(per_repeat)} repeats" if len(per_repeat) > 1 else ""
        return f"{', '.join(f'{d:g}' for d in per_repeat[0])} mm{each}"
    shown = [f"{d:g}" for d in p.depths_mm]
    if len(shown) > 12:  # the first and the last: the drift shows, not ten thousand numbers
        shown = [*shown[:6], "...", *shown[-3:]]
    where = "first contact" if p.depths_from_contact else "start"
    return (f"{', '.join(shown)} mm from the {where} (an approach that starts in contact re-zeroes "
            f"there: each repeat goes deeper)")


def cmd_position(args: argparse.Namespace) -> int:
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
    from rig.control.manual import move
    from rig.specs.config import load_config

    r = move(load_config(args.config), args.to_mm, args.speed_mm_s)
    print(f"moved from {r['from_mm']:.3f} mm to {r['position_mm']:.3f} mm")
    return 0


def cmd_reset_alarm(args: argparse.Namespace) -> int:
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
    from rig.control.manual import move
    from rig.specs.config import load_config

    r = move(load_config(args.config), 0.0, 0.0, home=True)
    print(f"homed: from {r['from_mm']:.3f} mm to {r['position_mm']:.3f} mm")
    return 0


# ------------------------------------------------------------------ daemon and its clients

def _socket(args: argparse.Namespace) -> Path:
    from rig.service.daemon import default_socket_path
    from rig.specs.config import load_config

    if args.socket:
        return Path(args.socket)
    return default_socket_path(load_config(args.config) if getattr(args, "config", None) else None)


def _reply(reply: dict) -> dict:
    if not reply.get("ok"):
        raise RigError(reply.get("error", "the daemon refused the request"))
    return reply


def cmd_daemon(args: argparse.Namespace) -> int:
    from rig.service.daemon import run_daemon
    from rig.specs.config import load_config

    config = load_config(args.config)
    return run_daemon(config, Path(args.socket) if args.socket else None, spy_path=args.spy)


def cmd_start(args: argparse.Namespace) -> int:
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
    from rig.service.client import request

    mode = "hold" if args.hold else "abort"
    reply = _reply(request(_socket(args), {"cmd": "stop", "mode": mode}))
    # what the daemon did (a trial stopped, a start cancelled, a campaign ended between trials)
    print(reply.get("message") or f"the daemon took the stop ({mode}) and said nothing more")
    return 0


def cmd_estop(args: argparse.Namespace) -> int:
    from rig.service.client import request

    reply = _reply(request(_socket(args), {"cmd": "estop"}))
    print(f"emergency stop: {reply.get('message', 'sent')}")
    return 0


def cmd_return(args: argparse.Namespace) -> int:
    from rig.service.client import request

    # a return moves the slider: the reply comes when it has arrived (or was stopped)
    reply = _reply(request(_socket(args), {"cmd": "return"}, 120.0))
    print(reply["message"])
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from rig.service.client import request
    from rig.views.watch import format_status

    reply = _reply(request(_socket(args), {"cmd": "status"}))
    print(json.dumps(reply, indent=2) if args.json else format_status(reply))
    return 0


def cmd_watch(args: argparse.Namespace) -> int:
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


def cmd_web(args: argparse.Namespace) -> int:
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


def cmd_logs(args: argparse.Namespace) -> int:
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


def cmd_sim(args: argparse.Namespace) -> int:
    from rig.sim.control import serve_sim
    from rig.specs.config import load_config

    config = load_config(args.config)
    return serve_sim(config.sim, loop_priority=config.loop.realtime_priority, json_out=args.json,
                     exit_with_parent=args.exit_with_parent, tcp_port=args.tcp_port)


def cmd_models(args: argparse.Namespace) -> int:
    from rig.models.catalogue import CATALOGUE, catalogue_json, format_catalogue
    from rig.models.plugins import load_plugin

    if args.action:
        if args.action[0] != "show" or len(args.action) != 2:
            raise RigError("usage: rig models [show MODEL.json]")
        from rig.models.saved import load

        saved = load(args.action[1])
        print(json.dumps(saved.as_dict(), indent=2) if args.json else saved.describe())
        return 0

    effects = dict(CATALOGUE)
    for p in args.plugin or []:
        effects.update({e.name: e for e in load_plugin(p)})
    print(json.dumps(catalogue_json(effects), indent=2) if args.json else format_catalogue(effects))
    return 0


def _progress(done: int, total: int) -> None:
    print(f"\rbootstrap: {done}/{total} draws", end="\n" if done == total else "", file=sys.stderr, flush=True)


def cmd_analyze(args: argparse.Namespace) -> int:
    from rig.analysis.batch.each import is_batch
    from rig.analysis.workflow.session import AnalyzeRequest, analyze
    from rig.records import ReadOptions

    options = ReadOptions(spring_constant_N_per_m=args.spring_constant, sensitivity_m_per_V=args.sensitivity)
    if is_batch(args.inputs, args.curve, args.each, options):
        return cmd_analyze_each(args)
    for flag in ("table", "resume", "workers", "scheduler", "min_quality"):
        if getattr(args, flag) not in (None, False):
            raise RigError(f"--{flag.replace('_', '-')} is for a batch (--each, a folder, a glob or a map file "
                           "alone): one record gives one analysis")
    if args.auto_steps is not None and not args.auto:
        raise RigError("--auto-steps N bounds --auto's search: give --auto with it")
    design_config = _design_args(args)  # refused before the long work, not after it
    done = analyze(AnalyzeRequest(
        inputs=args.inputs, model=args.model, add=args.add or [], holdout=args.holdout or [],
        plugins=args.plugin or [], block=args.block, compare=args.compare, explain=args.explain,
        auto=args.auto, auto_steps=args.auto_steps, design=args.design, design_config=design_config,
        save=args.save,
        report=args.report, indenter=args.indenter, poisson=args.poisson, segment=args.segment,
        form=args.form, curve=args.curve, spring_constant_N_per_m=args.spring_constant,
        sensitivity_m_per_V=args.sensitivity,
        bootstrap=args.bootstrap, profile=args.profile,
        progress=_progress if args.bootstrap and sys.stderr.isatty() else None))
    print(json.dumps(done.json, indent=2, default=float) if args.json else done.text)
    return 0


BATCH_REFUSED = ("compare", "auto", "auto_steps", "holdout", "design", "save", "bootstrap", "profile", "curve")


def cmd_analyze_each(args: argparse.Namespace) -> int:
    """Every curve on its own: a table (--table), a summary; the exit status is 0, or 64 plus the
    number of curves that could not be analysed (up to 125, clear of the other statuses)."""
    from rig.analysis.batch.each import format_rows, format_summary, run_each
    from rig.analysis.batch.engine import BatchRequest
    from rig.analysis.batch.table import jsonable

    given = [f for f in BATCH_REFUSED if getattr(args, f) not in (None, False)]
    if given:
        raise RigError(f"--{given[0].replace('_', '-')} is not for a batch: each curve is analysed on its own "
                       "(give one record, or --curve N of a map, to use it)")
    if args.resume and not args.table:
        raise RigError("--resume continues the table of an earlier batch: give it with --table")
    if args.min_quality is not None and not 0 <= args.min_quality <= 10:
        raise RigError(f"--min-quality {args.min_quality:g}: a quality is rated from 0 to 10")
    if args.workers is not None and args.scheduler:
        raise RigError("--workers sets local processes; with --scheduler the cluster's workers do the work")
    req = BatchRequest(model=args.model, add=tuple(args.add or ()), plugins=tuple(args.plugin or ()),
                       explain=args.explain, indenter=args.indenter, poisson=args.poisson, segment=args.segment,
                       spring_constant_N_per_m=args.spring_constant, sensitivity_m_per_V=args.sensitivity,
                       block=args.block)
    res = run_each(args.inputs, req, table=args.table, resume=args.resume, workers=args.workers,
                   scheduler=args.scheduler, progress=not args.json or sys.stderr.isatty())
    summary = format_summary(res, req, args.min_quality)
    if args.report:
        from rig.analysis.batch.each import parameters, passes
        from rig.analysis.batch.map_report import write_map_report

        kept = [r for r in res.rows if passes(r, args.min_quality)]
        summary += f"\nreport: {write_map_report(kept, args.report, parameters(kept), summary)}"
    if args.json:
        for r in res.rows:
            print(json.dumps(jsonable(r)))
    else:
        if not args.table:
            print(format_rows(res.rows))
        print(summary)
    return EXIT_CURVES_FAILED + min(len(res.failed), 61) if res.failed else 0


def _design_args(args: argparse.Namespace):
    """The rig config a designed protocol is checked against, after checking the arguments."""
    if args.config and not args.design:
        raise RigError("--config is the rig whose limits a --design protocol must respect; it needs --design")
    if not args.design:
        return None
    if not args.explain:
        raise RigError("--design needs --explain: the tie it settles comes from the diagnosis")
    target = Path(args.design)
    if target.is_dir() or not target.parent.is_dir():
        raise RigError(f"--design {args.design}: not a file in an existing directory")
    from rig.specs.config import load_config

    return load_config(args.config)


def cmd_import(args: argparse.Namespace) -> int:
    from rig.analysis.trials.data import load_trial
    from rig.records.csvfile import write_trial_csv

    trial = load_trial(args.file, args.block)
    n = write_trial_csv(trial, args.csv)
    k, u = trial.force_unit
    kl, ul = trial.length_unit
    print(f"{args.file}: {trial.source}, {n} samples at {1 / trial.motion.dt_s:.4g} Hz, peak force "
          f"{trial.scales.force_N / k:.4g} {u}, travel {trial.scales.length_m / kl:.4g} {ul}")
    for note in trial.notes:
        print(f"  {note}")
    print(f"wrote {args.csv} (" + ("t_s,position_mm,force_N: travel from the first sample, force as recorded; "
                                   "every fit places the contact point and the zero" if trial.contact_estimated
                                   else "t_s,indentation_mm,force_N: indentation from contact, force above the "
                                   "preload") + ")")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from rig.diagnostics.bench import format_bench, run_bench

    result = run_bench(duration_s=args.duration, rate_Hz=args.rate, progress=not args.json,
                       wire=args.wire, find_max_rate=args.max_rate, load=args.load,
                       realtime="off" if args.no_realtime else "auto")
    print(json.dumps(result, indent=2) if args.json else format_bench(result))
    return 0


# ------------------------------------------------------------------ setting up a real rig

def cmd_ports(args: argparse.Namespace) -> int:
    from rig.diagnostics.ports import format_ports, list_ports

    ports = list_ports()
    if args.json:
        print(json.dumps([p.as_dict() for p in ports], indent=2))
    else:
        print(format_ports(ports))
    return 0


def cmd_probe(args: argparse.Namespace) -> int:
    from rig.diagnostics.probe import probe
    from rig.specs.config import load_config

    report = probe(load_config(args.config), seconds=args.seconds, spy_path=args.spy)
    print(json.dumps(report.as_dict(), indent=2) if args.json else report.format())
    return report.exit_status()


def cmd_spy(args: argparse.Namespace) -> int:
    from rig.views.spyview import format_spy, read_spy

    print(format_spy(read_spy(args.file), show_hex=args.hex, channel=args.channel))
    return 0


def cmd_config_init(args: argparse.Namespace) -> int:
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


# ------------------------------------------------------------------ parser

def _rig_config(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="rig config (YAML); default: the built-in simulated rig")


def _campaign_options(p) -> None:
    """The options a campaign takes, for `rig characterize` and `rig start --characterize`."""
    p.add_argument("--indenter", help="the probe's geometry, for a modulus in Pa (e.g. sphere:R=2mm)")
    p.add_argument("--max-trials", type=int, default=6, help="at most this many trials (default 6)")
    p.add_argument("--budget-min", type=float, default=30.0,
                   help="specimen time for trials and rests, minutes (default 30); a trial chosen to "
                        "narrow a parameter may be slowed to take its share of what is left")
    p.add_argument("--target-rse", type=float, default=0.05,
                   help="every parameter's relative standard error at most this (default 0.05)")
    p.add_argument("--rest-s", type=float, default=60.0,
                   help="rest between trials for the specimen to recover, s (default 60)")


def build_parser() -> argparse.ArgumentParser:
    from rig.sim.afm_map import add_map_parser

    p = argparse.ArgumentParser(
        prog="rig", description="Soft-tissue indentation rig: run and control trials, replay logs, fit and "
                                    "diagnose force models.",
        epilog="Start with: rig run protocols/demo.yaml   (runs on the built-in simulated rig)")
    p.add_argument("--version", action="version", version=f"rig {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    r = sub.add_parser("run", help="run a protocol and log it to MCAP",
                       description="Run a protocol file on the rig named by --config (default: the "
                                   "built-in simulated rig) and write one MCAP log.")
    r.add_argument("protocol", help="protocol file (YAML), e.g. protocols/demo.yaml")
    _rig_config(r)
    r.add_argument("--specimen", default="specimen", help="specimen ID recorded in the log")
    r.add_argument("--operator", default="", help="operator name recorded in the log")
    r.add_argument("--notes", default="", help="free text recorded in the log")
    _specimen_size(r)
    r.add_argument("--out", help="directory for the log (default: the config's recorder.out_dir)")
    r.add_argument("--speed", type=_positive_or_zero, default=1.0,
                   help="simulated rig only: 0 = as fast as possible, N = N times real time "
                        "(default 1: real time)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--model", metavar="MODEL.json",
                   help="run this saved model (rig analyze --save) in the loop: force_model_N, model_error_N")
    r.add_argument("--live", type=int, nargs="?", const=8765, metavar="PORT",
                   help="publish the trial live for Foxglove (WebSocket on 127.0.0.1:PORT, default 8765; "
                        "needs the extra rig[live])")
    r.add_argument("--spy", metavar="FILE", help="write every Modbus frame and load-cell line to FILE "
                                                  "(read it with `rig spy FILE`)")
    r.set_defaults(func=cmd_run)

    r = sub.add_parser("characterize", help="run, fit, diagnose and design trials until the model is right",
                       description=CHARACTERIZE_HELP)
    _rig_config(r)
    r.add_argument("--specimen", required=True, help="specimen ID (the logs and the journal carry it)")
    r.add_argument("--model", default="proposed", help="the model to start from (default: proposed)")
    r.add_argument("--protocol", help="the first trial (default: an exploratory ramp-hold inside the limits)")
    _campaign_options(r)
    r.add_argument("--out", help="directory for the logs, the journal and the figure (default: the config's "
                                 "recorder.out_dir / characterize-SPECIMEN)")
    r.add_argument("--speed", type=_positive_or_zero, default=1.0,
                   help="simulated rig only: 0 = as fast as possible (default 1: real time)")
    r.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    r.set_defaults(func=cmd_characterize)

    r = sub.add_parser("replay", help="summarise a log (or compare several); export CSV; plot",
                       description="Summarise a trial log (also one cut short by a crash), re-run "
                                   "the estimator on it, and optionally export CSV or plot. Given several "
                                   "logs: a table of them (specimen, outcome, peak force, stiffness at the "
                                   "hold's end, estimator error, duration) and one plot comparing them.")
    r.add_argument("log", nargs="+", help="MCAP log file(s)")
    r.add_argument("--csv", type=Path, help="write samples as CSV (t_s,position_mm,force_N,...); one log only")
    r.add_argument("--plot", type=Path, help="write a PNG of force, position and stiffness (several logs: "
                                             "their force against time and against indentation)")
    r.add_argument("--json", action="store_true", help="print the summary as JSON")
    r.set_defaults(func=cmd_replay)

    r = sub.add_parser("check", help="validate a protocol and show its plan",
                       description="Validate a protocol against the rig's limits and show the plan: "
                                   "duration, depths, speeds and the excitation order of the motion.")
    r.add_argument("protocol")
    _rig_config(r)
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_check)

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

    def client(name: str, help_text: str, func) -> argparse.ArgumentParser:
        c = sub.add_parser(name, help=help_text, description=help_text)
        c.add_argument("--socket", help="the daemon's control socket")
        c.add_argument("--config", help="rig config naming the socket (daemon.socket)")
        c.set_defaults(func=func)
        return c

    r = client("start", "start a protocol on the daemon (or, with --characterize, a campaign)", cmd_start)
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
    r = client("stop", "stop the running trial, then return to the start position", cmd_stop)
    r.add_argument("--hold", action="store_true", help="stop and stay where it is")
    client("estop", "emergency stop: stop the motor now, nothing else", cmd_estop)
    client("return", "move the probe back out of the specimen after an estop or a fault left it in contact "
           "(to where that trial started)", cmd_return)
    r = client("status", "what the daemon is doing", cmd_status)
    r.add_argument("--json", action="store_true")
    r = client("watch", "live view of the running trial until it ends", cmd_watch)
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

    r = sub.add_parser("sim", help="start the simulated slider and load cell on real wires",
                       description="Serve the simulated drive over Modbus TCP (loopback) and Modbus RTU "
                                   "(a pseudo-terminal), and the simulated load cell on a pseudo-terminal, "
                                   "until Ctrl-C. Prints the ports to put in a rig config. Faults can be "
                                   'switched on stdin with JSON lines, e.g. {"faults": {"drop_replies": 1}}.')
    r.add_argument("--config", help="rig config whose sim: section describes the rig (default: built-in)")
    r.add_argument("--tcp-port", type=int, default=0, help="Modbus TCP port on 127.0.0.1 (default: a free one)")
    r.add_argument("--json", action="store_true", help="print the endpoints as one JSON line")
    r.add_argument("--exit-with-parent", action="store_true", help="exit when stdin closes")
    r.set_defaults(func=cmd_sim)
    add_map_parser(sub)  # rig sim-map: a simulated AFM force map with its truth

    r = sub.add_parser("models", help="list the effects catalogue and the named models",
                       description="The effects a force model is built from, with equations, parameters "
                                   "and where each one's absence shows in a trial; and the named models.")
    r.add_argument("action", nargs="*", metavar="show MODEL.json",
                   help="print a saved model (rig analyze --save) instead")
    r.add_argument("--plugin", action="append", help="also list the effects in this Python file")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_models)

    r = sub.add_parser("analyze", help="fit force models to trials; compare; report",
                       description="Fit a force model to one or more records jointly, show the error overall "
                                   "and by phase, compare all named models, test on held-out records, find "
                                   "the missing effect. Reads, by content: the rig's MCAP logs; CSV with "
                                   "t_s,position_mm,force_N or other units in the column names (t_ms, "
                                   "position_um, indentation_nm, force_nN, load_mN, force_gf, strain); AFM "
                                   "force curves and maps that afmformats reads (JPK, Asylum, NT-MDT, AFM "
                                   "Workshop, Optics11 Chiaro) and JPK text exports; Mach-1 .txt; Instron "
                                   "Bluehill CSV. "
                                   "Contact, phases and every scale come from the record itself.")
    r.add_argument("inputs", nargs="+",
                   help="records: the rig's MCAP logs, CSV, AFM force curves and maps (JPK, Asylum, NT-MDT, "
                        "AFM Workshop, Optics11), Mach-1 or Instron files")
    r.add_argument("--block", type=int, metavar="N",
                   help="Mach-1 files: analyse data block N (default: the longest)")
    r.add_argument("--curve", type=int, metavar="N",
                   help="AFM maps and QI files: analyse curve N, numbered as the instrument numbers it "
                        "(default: the first)")
    r.add_argument("--spring-constant", type=_positive_float, metavar="N_PER_M",
                   help="AFM files: the cantilever's spring constant (N/m), where the file lacks it or to "
                        "override it")
    r.add_argument("--sensitivity", type=_positive_float, metavar="M_PER_V",
                   help="AFM files: the deflection sensitivity in the unit of the file's deflection signal "
                        "(m/V; nm/nA for NT-MDT text exports), where the file lacks it")
    r.add_argument("--model", default="proposed",
                   help="named model or effect (default: proposed; hertz: E in Pa for the indenter)")
    r.add_argument("--indenter", metavar="SPEC",
                   help="the indenter's geometry, e.g. paraboloid:R=10um, sphere:R=2.5um, "
                        "cone:half_angle=35deg, pyramid:half_angle=35deg,sides=4, cylinder:R=1mm "
                        "(default: what the file's header says)")
    r.add_argument("--poisson", type=float, default=0.5, metavar="NU",
                   help="Poisson's ratio for the contact law (default 0.5: incompressible)")
    r.add_argument("--segment", choices=["auto", "all", "approach"], default="auto",
                   help="auto (default): the approach alone for an elastic contact (hertz and the other "
                        "contact laws) on a curve whose file names its segments, as AFM tools fit it, "
                        "else the whole record; all: the whole record (the retract too); approach: the "
                        "approach alone")
    r.add_argument("--form", choices=["auto", "creep", "force"], default="auto",
                   help="auto (default): where a controller held the force (ramp_force, hold_force, an AFM "
                        "creep-compliance pause) the model predicts the indentation from the force (creep "
                        "form), elsewhere the force from the indentation; creep: the same, refused on a "
                        "record that holds no force; force: force form throughout")
    r.add_argument("--add", action="append", metavar="EFFECT", help="add an effect to the model")
    r.add_argument("--plugin", action="append", metavar="FILE", help="load user effects from a Python file")
    r.add_argument("--holdout", action="append", metavar="FILE",
                   help="report the fitted model's error on this trial (not used in the fit)")
    r.add_argument("--compare", action="store_true", help="fit every named model and tabulate")
    r.add_argument("--explain", action="store_true",
                   help="rank the effects the model lacks by how much each would reduce the error")
    r.add_argument("--auto", action="store_true",
                   help="add effects one by one while the error falls; print the steps")
    r.add_argument("--auto-steps", type=_positive_int, metavar="N",
                   help="with --auto: stop after N steps (default 5); each step refits the model from "
                        "several starts, minutes on a long record")
    r.add_argument("--design", metavar="FILE",
                   help="with --explain: when two effects cannot be told apart, write the protocol (YAML) "
                        "that would separate them")
    r.add_argument("--config", help="with --design: the rig whose limits the protocol must respect "
                                    "(default: the built-in simulated rig)")
    r.add_argument("--bootstrap", type=_draws, metavar="N",
                   help="redraw the record N times from the fitted model and the measured noise and "
                        "analyse each as this one: each parameter's bias, scatter against its standard "
                        "error, how often +/-1.96 SE held it, how often the verdict stays (100 is a start)")
    r.add_argument("--profile", nargs="*", metavar="PARAM",
                   help="profile-likelihood 95 %% intervals: of the parameters named (any of the model's, "
                        "e.g. --profile E_Pa), or with no name of those that trade off (|correlation| >= 0.9 "
                        "with another); each end where the cost has risen, the others refitted")
    r.add_argument("--report", metavar="DIR", help="write figures and report.md here")
    r.add_argument("--save", metavar="MODEL.json",
                   help="save the fitted model (effects, parameters, what it was fitted on) to run it "
                        "in the loop (rig run --model)")
    r.add_argument("--json", action="store_true",
                   help="one JSON object on stdout (a batch: one line per curve)")
    b = r.add_argument_group("batches", "every curve of a map, every file of a folder or a glob, each analysed "
                                        "on its own (a folder, a glob, or a map file given alone without "
                                        "--curve, are analysed so without --each). Exit status: 0 when every "
                                        "curve was analysed, else 64 plus how many could not be (up to 125)")
    b.add_argument("--each", action="store_true",
                   help="analyse every curve of every input on its own (several files without --each are "
                        "fitted jointly)")
    b.add_argument("--table", metavar="OUT",
                   help="write one row per curve to OUT (.csv, .jsonl, or .parquet with the table extra): "
                        "position, parameters with standard errors, contact, RMSE over noise, verdict, why a "
                        "curve failed")
    b.add_argument("--min-quality", type=float, metavar="Q",
                   help="leave curves rated below Q (0-10: contact, fit over noise, baseline, artefacts; the "
                        "table's quality column) out of the summary's statistics and the report's maps; the "
                        "table keeps them all")
    b.add_argument("--resume", action="store_true",
                   help="keep the rows of an interrupted (or finished) batch in --table and do only the rest")
    b.add_argument("--workers", type=_positive_int, metavar="N",
                   help="local processes (default: every core)")
    b.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="send the curves to this Dask distributed scheduler (the cluster extra)")
    r.set_defaults(func=cmd_analyze)

    r = sub.add_parser("import", help="read an instrument's file and write the canonical CSV",
                       description="Read a record (JPK .jpk-force or text export, Mach-1 .txt, Instron CSV, "
                                   "CSV with units in the column names, MCAP log), find contact, the direction "
                                   "of loading and the baseline, and write t_s,indentation_mm,force_N.")
    r.add_argument("file", help="the instrument's file")
    r.add_argument("--csv", type=Path, required=True, metavar="OUT", help="canonical CSV to write")
    r.add_argument("--block", type=int, metavar="N", help="Mach-1 files: data block N (default: the longest)")
    r.set_defaults(func=cmd_import)

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
    return p


def main(argv: list[str] | None = None) -> int:
    # The fits' matrices are tall and a few columns wide: a second BLAS thread gains nothing on
    # them, and on a busy machine a product waits tens of ms for a descheduled thread. Set
    # before numpy is first imported (every subcommand imports it lazily); a user's own
    # setting wins.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except RigError as exc:
        print(f"rig {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f"rig {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
