"""`rig models`, `rig analyze` (one fit, or every curve with --each) and `rig import`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rig.cli.args import EXIT_CURVES_FAILED, _draws, _positive_float, _positive_int
from rig.errors import RigError


def cmd_models(args: argparse.Namespace) -> int:
    """`rig models`: list the effects catalogue and the named models."""
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
    """`rig analyze`: fit force models to trials; compare; report."""
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
    """`rig import`: read an instrument's file and write the canonical CSV."""
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


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register `rig models`, `rig analyze`, `rig import` with their handlers."""
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
