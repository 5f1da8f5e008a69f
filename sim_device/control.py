"""`rig sim`: serve the simulated devices on the wire until told to stop.

Commands arrive on stdin as JSON lines: {"faults": {"drop_replies": 2}} switches faults
(any field of `FaultParams`), {"loadcell": {"mass_g": 500}} puts a calibration mass on the
load cell (and 0 takes it off), {"status": true} prints the drive's state as a JSON line.
"""

from __future__ import annotations

import gc
import json
import signal
import sys
import threading
from dataclasses import fields

from rig.sim.params import SimParams
from rig.sim.server import WireSim, wire_note

from rig.realtime import Realtime

# what a command may change of the load cell while it serves: the mass resting on it
LOADCELL_AT_RUN_TIME = ["mass_g"]


def serve_sim(params: SimParams, *, loop_priority: int = 0, json_out: bool = False,
              exit_with_parent: bool = False, tcp_port: int = 0) -> int:
    """Serve until stdin closes; `loop_priority`: the controller's real-time priority (the
    simulator runs one below it)."""
    # Like the controller: no thread may hold the interpreter for the default 5 ms while
    # a Modbus reply is due.
    sys.setswitchinterval(0.0005)
    # Before any thread starts: they inherit the policy.
    Realtime(params.realtime, max(loop_priority - 1, 1)).enter()
    sim = WireSim(params, tcp_port=tcp_port)
    ep = sim.start()
    gc.collect()
    gc.freeze()  # keep full collections short while serving (see rig.loop)
    done = threading.Event()
    out_lock = threading.Lock()

    def say(obj: dict) -> None:
        with out_lock:
            print(json.dumps(obj), flush=True)

    if json_out:
        say(ep.as_dict())
    else:
        host, port = ep.modbus_tcp.rsplit(":", 1)
        print(f"simulated drive   Modbus TCP {ep.modbus_tcp}  |  Modbus RTU {ep.modbus_rtu} "
              f"({wire_note(params)}, unit {params.drive.device_id})\n"
              f"simulated load cell  {ep.loadcell}  ({params.loadcell.mode}, "
              f"{params.loadcell.rate_Hz:g} lines/s)\n\n"
              "For a rig config (RTU):\n"
              f"  slider:   {{backend: modbus-rtu, port: {ep.modbus_rtu}, profile: oriental_az_sim}}\n"
              f"  loadcell: {{backend: serial, port: {ep.loadcell}}}\n"
              "or TCP:\n"
              f"  slider:   {{backend: modbus-tcp, host: {host}, tcp_port: {port}, profile: oriental_az_sim}}\n"
              "Ctrl-C stops.", flush=True)

    fault_names = {f.name: f.type for f in fields(params.faults)}

    def handle(line: str) -> None:
        try:
            cmd = json.loads(line)
        except json.JSONDecodeError:
            say({"error": "not JSON"})
            return
        if not isinstance(cmd, dict):
            say({"error": "expected a JSON object"})
            return
        for name, value in (cmd.get("faults") or {}).items():
            if name not in fault_names:
                say({"error": f"unknown fault '{name}'", "known": sorted(fault_names)})
                continue
            setattr(params.faults, name, value)
        for name, value in (cmd.get("loadcell") or {}).items():
            if name not in LOADCELL_AT_RUN_TIME:
                say({"error": f"loadcell.{name} cannot be changed at run time", "known": LOADCELL_AT_RUN_TIME})
                continue
            setattr(params.loadcell, name, float(value))
        if cmd.get("status"):
            with sim.rig.lock:
                sim.drive.sync()
                m = sim.rig.slider
                say({"position_mm": m.position_mm, "moving": m.moving,
                     "alarm_code": params.faults.alarm_code, "requests": sim.drive.requests,
                     "moves": sim.drive.moves, "stops": sim.drive.stops,
                     "stop_held": sim.drive.stop_held, "ignored_moves": sim.drive.ignored_moves,
                     "comm_timeout_s": sim.drive.comm_timeout_s})

    def read_stdin() -> None:
        for line in sys.stdin:
            if line.strip():
                handle(line)
        if exit_with_parent:
            done.set()

    threading.Thread(target=read_stdin, name="sim-stdin", daemon=True).start()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    try:
        done.wait()
    finally:
        sim.stop()
    return 0
