"""The `rig` command: its parser built from one module per group of subcommands, each holding
its commands' parsers beside their handlers (`add_parsers`), and `main`.

    trials       run, characterize, replay, check
    manual       position, move, reset-alarm, tare, calibrate, home
    service      daemon, start, stop, estop, return, status, watch, logs, web
    sim          sim, sim-map
    analysis     models, analyze, import
    diagnostics  bench, ports, probe, spy, config init
    args         the argument types, shared options and exit statuses

Every error a user can cause ends as one line on stderr and a non-zero exit status,
never a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys

from rig import __version__
from rig.cli import analysis, diagnostics, manual, service, sim, trials
from rig.cli.args import EXIT_CURVES_FAILED, EXIT_ERROR, EXIT_FAULT, EXIT_INTERRUPTED
from rig.errors import RigError

__all__ = ["EXIT_CURVES_FAILED", "EXIT_ERROR", "EXIT_FAULT", "EXIT_INTERRUPTED", "build_parser", "main"]

# in the order `rig --help` lists them
GROUPS = (trials, manual, service, sim, analysis, diagnostics)


def build_parser() -> argparse.ArgumentParser:

    p = argparse.ArgumentParser(
        prog="rig", description="Soft-tissue indentation rig: run and control trials, replay logs, fit and "
                                    "diagnose force models.",
        epilog="Start with: rig run protocols/demo.yaml   (runs on the built-in simulated rig)")
    p.add_argument("--version", action="version", version=f"rig {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    for group in GROUPS:
        group.add_parsers(sub)
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
