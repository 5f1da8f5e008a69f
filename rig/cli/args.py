"""What the commands share: argument types that say what is wrong, the options several take, the
daemon's clients, and the exit statuses."""

from __future__ import annotations

import argparse
from pathlib import Path

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


def client(sub: argparse._SubParsersAction, name: str, help_text: str, func) -> argparse.ArgumentParser:
    """A subcommand that asks the daemon: its socket, or the config that names it."""
    c = sub.add_parser(name, help=help_text, description=help_text)
    c.add_argument("--socket", help="the daemon's control socket")
    c.add_argument("--config", help="rig config naming the socket (daemon.socket)")
    c.set_defaults(func=func)
    return c
