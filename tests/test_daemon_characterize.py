"""`rig start --characterize`: a campaign on the daemon's devices, over real wires. Status and
watch show where it is, a second start is refused while it runs, `rig stop` ends it in a trial
or between two, and the journal ends complete either way; a campaign cut short by a killed
daemon is recovered, listed and ended in its journal at the next start."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from rig.sim.params import SimParams
from rig.sim.server import WireSim

from rig.recording.logs import read_log
from rig.recording.recovery import end_journal, find_open_journals
from rig.service.client import stream
from rig.specs.protocol import parse_protocol
from tests.conftest import ROOT
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
            # designed on the daemon as by `rig characterize`: the travel margin as its own window,
            # the predicted peak within the force margin, and the journal says why it is its size
            assert parse_protocol(second["yaml"]).limits.travel_mm == (-5.0, 40.5)
            assert second["sizing"]["predicted_peak_N"] <= 0.8 * 20.0
            assert "mm short of the end of travel (5 mm kept)" in second["size"]
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


# ------------------------------------------------------------------ a campaign cut short
def _running(d: DaemonProc, sim: WireSim, past_mm: float = 2.0) -> None:
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if d.req({"cmd": "status"})["state"] == "running" and sim.rig.slider.position_mm > past_mm:
            return
        time.sleep(0.02)
    raise AssertionError("the campaign's first trial did not get going")


def test_a_campaign_killed_mid_trial_is_recovered_listed_and_ended_in_its_journal(tmp_path):
    """After `kill -9` mid-campaign nothing was recovered (recovery and listing looked only at
    the top folder), the journal had no end, and status forgot the campaign."""
    with WireSim(SimParams(), rtu=False) as sim:
        d = DaemonProc(tmp_path, sim)
        try:
            r = _start(d, max_trials=2, rest_s=1.0)
            assert r["ok"], r
            _running(d, sim)
            os.kill(d.proc.pid, signal.SIGKILL)
            d.proc.wait(10)
            killed = time.monotonic()
            while sim.rig.slider.moving and time.monotonic() - killed < 3:  # the drive's comm timeout
                with sim.rig.lock:
                    sim.drive.sync()
                time.sleep(0.005)
            sim.params.faults.alarm_code = 0  # the technician resets the drive alarm
            folder = Path(r["out"])
            journal = next(folder.glob("characterize-liver-9-*.jsonl"))
            log = folder / "liver-9-trial1.mcap"
            assert _journal(str(journal))[-1]["event"] == "trial"  # what the kill left
            d.log.close()
            d.start()  # the restart recovers
            st = d.req({"cmd": "status"})
            assert st["recovered"] == [str(log), str(journal)], st
            camp = st["campaign"]
            assert camp["status"] == "interrupted" and camp["specimen"] == "liver-9" and camp["trials"] == 1
            assert "during trial 1" in camp["reason"] and camp["journal"] == str(journal), camp
            end = _journal(str(journal))[-1]
            assert end["event"] == "end" and end["status"] == "interrupted" and end["recovered"], end
            assert end["summary"]["trials"][0]["outcome"] == "interrupted"
            trial = read_log(log)
            assert trial.complete and trial.outcome == "interrupted"
            listed = d.req({"cmd": "logs"})["trials"]
            assert [(e["path"], e["outcome"], e["recovered"], e["campaign"]) for e in listed] == \
                [(str(log), "interrupted", True, folder.name)]
            out = subprocess.run([sys.executable, "-m", "rig", "logs", "--dir", str(d.out)],
                                 capture_output=True, text=True, timeout=30)
            assert log.name in out.stdout and "interrupted (recovered)" in out.stdout, out.stdout
            text = subprocess.run([sys.executable, "-m", "rig", "status", "--socket", str(d.sock)],
                                  capture_output=True, text=True, timeout=30).stdout
            assert "campaign  specimen liver-9" in text and "ended: interrupted" in text, text
            # a second restart finds nothing more to do
            d.stop()
            d.start()
            assert d.req({"cmd": "status"})["recovered"] == []
            assert [e["event"] for e in _journal(str(journal))].count("end") == 1
        finally:
            d.stop()


HOLD_OPEN = """
import sys
from rig.recording.recorder import Recorder
rec = Recorder(sys.argv[1], flush_s=0.05)
rec.put("/rig/event", 0, {"t_s": 0.0, "kind": "k", "message": "m"})
rec.wait_idle()
print("writing", flush=True)
sys.stdin.readline()
"""


def _journal_lines(path: Path, *events: dict, torn: str = "") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps({"t": 1.8e9, **e}) + "\n" for e in events) + torn)


def test_recovery_ends_only_the_journals_a_crash_left_open(tmp_path):
    """Built as a crash leaves it: a journal cut mid-line between trials, one ended properly, and
    one whose campaign another process is still running (its trial's log is being written)."""
    out = tmp_path / "trials"
    start = {"event": "start", "specimen": "kidney-2"}
    cut = out / "characterize-kidney-2" / "characterize-kidney-2-20260101-120000.jsonl"
    _journal_lines(cut, start, {"event": "trial", "n": 1, "protocol": "p1", "why": "w"},
                   {"event": "ran", "n": 1, "outcome": "completed", "log": "x.mcap"}, torn='{"t": 1.8e9, "eve')
    done = out / "characterize-ok" / "characterize-ok-20260101-120000.jsonl"
    _journal_lines(done, {**start, "specimen": "ok"}, {"event": "end", "status": "done"})
    live = out / "characterize-live" / "characterize-live-20260101-120000.jsonl"
    _journal_lines(live, {**start, "specimen": "live"}, {"event": "trial", "n": 1})
    done_before = done.read_bytes()
    writer = subprocess.Popen([sys.executable, "-c", HOLD_OPEN, str(live.parent / "live-trial1.mcap")],
                              cwd=ROOT, text=True, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert writer.stdout.readline().strip() == "writing"
        in_use: list[Path] = []
        assert find_open_journals(out, in_use=in_use) == [cut] and in_use == [live]
        ended = end_journal(cut)
    finally:
        writer.kill()
        writer.wait(10)
    assert ended.specimen == "kidney-2" and ended.trials == 1
    assert "after trial 1, between trials" in ended.reason
    lines = cut.read_text().splitlines()
    assert lines[-2] == '{"t": 1.8e9, "eve'  # the torn line stays as it was, on a line of its own
    end = json.loads(lines[-1])
    assert end["event"] == "end" and end["status"] == "interrupted"
    assert end["summary"]["trials"] == [{"n": 1, "protocol": "p1", "why": "w", "outcome": "completed",
                                         "log": "x.mcap"}]
    assert done.read_bytes() == done_before
    assert find_open_journals(out) == [live]  # its writer is gone now: the next daemon ends it
