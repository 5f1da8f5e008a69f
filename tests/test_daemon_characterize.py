"""`rig start --characterize`: a campaign on the daemon's devices, over real wires. Status and
watch show where it is, a second start is refused while it runs, `rig stop` ends it in a trial
or between two, and the journal ends complete either way."""

from __future__ import annotations

import json
import time
from pathlib import Path

from rig.sim.params import SimParams
from rig.sim.server import WireSim

from rig.recording.logs import read_log
from rig.service.client import stream
from tests.test_daemon import DaemonProc

FIRST = ("name: first look\nsteps:\n  - ramp: {to_mm: 6, speed_mm_s: 3}\n  - hold: {duration_s: 3}\n"
         "  - return: {to_mm: 0, speed_mm_s: 5}\n")


def _start(d: DaemonProc, **opts) -> dict:
    return d.req({"cmd": "start", "specimen": "liver-9", "protocol_text": FIRST, "protocol_path": "first.yaml",
                  "characterize": opts})


def _until(d: DaemonProc, ok, timeout_s: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st = d.req({"cmd": "status"})
        if ok(st):
            return st
        time.sleep(0.05)
    raise AssertionError(f"not reached; last status {st}")


def _journal(path: str) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines()]


def test_a_campaign_on_the_daemon_runs_its_trials_and_is_watched(tmp_path):
    with WireSim(SimParams(), rtu=False) as sim:
        d = DaemonProc(tmp_path, sim)
        try:
            # 24 s: the second trial takes what the first (7 s) and the rest leave, less a margin
            r = _start(d, max_trials=2, budget_min=0.4, rest_s=1.0)
            assert r["ok"], r
            refused = d.start_trial(FIRST)
            assert not refused["ok"] and "busy: characterizing specimen liver-9" in refused["error"]
            watched = []
            for msg in stream(d.sock, {"cmd": "watch", "rate_Hz": 20}, timeout_s=30.0):
                watched.append(msg)
                if msg.get("end") or len(watched) > 1200:  # 60 s at 20 Hz: the campaign is over long before
                    break
            phases = {m["campaign"]["phase"].split(":")[0] for m in watched if m.get("campaign")}
            assert {"trial 1", "trial 2"} <= phases, phases
            assert watched[-1].get("end")
            st = _until(d, lambda s: s["state"] == "idle")
            camp = st["campaign"]
            assert camp["status"] == "budget" and camp["trials"] == 2
            events = _journal(camp["journal"])
            assert events[0]["event"] == "start" and events[-1]["event"] == "end"
            assert [e["n"] for e in events if e["event"] == "ran"] == [1, 2]
            assert all(e["outcome"] == "completed" for e in events if e["event"] == "ran")
            second = next(e for e in events if e["event"] == "trial" and e["n"] == 2)
            assert second["why"] and second["duration_s"] <= 0.4 * 60
            logs = [e["log"] for e in events if e["event"] == "ran"]
            for log in logs:
                trial = read_log(log).trial
                assert trial["specimen"] == "liver-9" and trial["daemon"] == "rigd"
            assert "campaign budget" in d.log_text()
        finally:
            d.stop()


def test_a_stop_between_trials_ends_the_campaign_before_the_next(tmp_path):
    with WireSim(SimParams(), rtu=False) as sim:
        d = DaemonProc(tmp_path, sim)
        try:
            assert _start(d, max_trials=3, budget_min=5.0, rest_s=30.0)["ok"]
            # the first trial ran and was fitted; the campaign rests before the second
            _until(d, lambda s: s["state"] == "characterizing" and s["campaign"]["phase"].startswith("decided"))
            moves = sim.drive.moves
            stop = d.req({"cmd": "stop"})
            assert stop["ok"] and "ends before its next trial" in stop["message"]
            st = _until(d, lambda s: s["state"] == "idle", timeout_s=10.0)
            camp = st["campaign"]
            assert camp["status"] == "stopped" and camp["trials"] == 1
            assert sim.drive.moves == moves  # nothing moved after the stop
            events = _journal(camp["journal"])
            assert events[-1]["event"] == "end" and events[-1]["status"] == "stopped"
            assert events[-2]["event"] == "decision" and events[-2]["kind"] == "stopped"
            # the daemon takes the next start
            r = d.start_trial(FIRST, specimen="after")
            assert r["ok"], r
            assert d.wait_idle()["last"]["outcome"] == "completed"
        finally:
            d.stop()
