"""`rig sim` (the simulated slider and load cell on real wires) and `rig sim-map` (a simulated AFM
force map with its truth)."""

from __future__ import annotations

import argparse


def cmd_sim(args: argparse.Namespace) -> int:
    """`rig sim`: start the simulated slider and load cell on real wires."""
    from rig.sim.control import serve_sim
    from rig.specs.config import load_config

    config = load_config(args.config)
    return serve_sim(config.sim, loop_priority=config.loop.realtime_priority, json_out=args.json,
                     exit_with_parent=args.exit_with_parent, tcp_port=args.tcp_port)


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register `rig sim` with their handlers."""
    from rig.sim.afm_map import add_map_parser

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
