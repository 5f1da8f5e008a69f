"""`rig run`, `rig characterize`, `rig replay`, `rig check`: a protocol run in the foreground, its
log read back, its plan checked."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rig.cli.args import (
    EXIT_FAULT,
    EXIT_INTERRUPTED,
    _campaign_options,
    _positive_or_zero,
    _rig_config,
    _specimen_size,
)
from rig.errors import RigError


def cmd_run(args: argparse.Namespace) -> int:
    """`rig run`: run a protocol and log it to MCAP."""
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
    """`rig characterize`: run, fit, diagnose and design trials until the model is right."""
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
    """`rig replay`: summarise a log (or compare several); export CSV; plot."""
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
    """`rig check`: validate a protocol and show its plan."""
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


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register `rig run`, `rig characterize`, `rig replay`, `rig check` with their handlers."""
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
