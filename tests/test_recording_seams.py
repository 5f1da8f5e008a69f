"""Logs where processes meet: a name taken exclusively, a log being written left alone by
recovery, a close that does not finish in time reported as such, a trial killed halfway."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from rig.clock import VirtualClock
from rig.control.devices import open_devices
from rig.control.trial import Trial
from rig.recording.logs import read_log
from rig.recording.recorder import Recorder, TrialInfo
from rig.recording.recovery import LogInUse, find_unfinished, list_trials, recover
from rig.specs.config import RigConfig
from rig.specs.protocol import parse_protocol
from tests.conftest import PROTOCOLS, ROOT, run_sim

SHORT = """name: short
steps:
  - ramp: {to_mm: 3, speed_mm_s: 5}
  - hold: {duration_s: 0.3}
  - return: {speed_mm_s: 5}
"""


def _write(rec: Recorder, tag: str, n: int) -> None:
    for i in range(n):
        rec.put("/rig/event", i * 1_000_000, {"t_s": i / 1000, "kind": tag, "message": f"{tag} {i}"})


def test_two_recorders_given_one_name_both_keep_their_data(tmp_path):
    path = tmp_path / "20250101-120000_pig_ramp.mcap"
    first = Recorder(path)
    second = Recorder(path)  # the same instant, the same protocol and specimen: the same name
    assert first.path == path
    assert second.path == tmp_path / "20250101-120000_pig_ramp_2.mcap"
    _write(first, "first", 50)
    _write(second, "second", 70)
    assert first.close({"outcome": "completed"}) and second.close({"outcome": "completed"})
    a, b = read_log(first.path), read_log(second.path)
    assert a.complete and b.complete
    assert [e["kind"] for e in a.events] == ["first"] * 50
    assert [e["kind"] for e in b.events] == ["second"] * 70


def test_trials_racing_for_one_log_name_each_report_the_name_they_got(tmp_path):
    a = run_sim(SHORT, tmp_path=tmp_path, name="same.mcap")
    b = run_sim(SHORT, tmp_path=tmp_path, name="same.mcap")
    assert a.log_path == tmp_path / "same.mcap" and b.log_path == tmp_path / "same_2.mcap"
    for r in (a, b):
        log = read_log(r.log_path)
        assert log.complete and log.outcome == "completed" and log.n == r.samples


HOLD_OPEN = """
import sys, time
from rig.recording.recorder import Recorder
rec = Recorder(sys.argv[1], flush_s=0.05)
for i in range(200):
    rec.put("/rig/event", i, {"t_s": i / 1000, "kind": "k", "message": "m"})
rec.wait_idle()
time.sleep(0.3)  # past a flush: on disk, not finished
print("writing", flush=True)
sys.stdin.readline()
rec.close({"outcome": "completed"})
"""


def test_recovery_leaves_a_log_that_a_live_process_is_writing_alone(tmp_path):
    path = tmp_path / "running.mcap"
    writer = subprocess.Popen([sys.executable, "-c", HOLD_OPEN, str(path)], cwd=ROOT, text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert writer.stdout.readline().strip() == "writing"
        before = path.read_bytes()
        in_use: list[Path] = []
        assert find_unfinished(tmp_path, in_use=in_use) == [] and in_use == [path]
        with pytest.raises(LogInUse, match="being written by a live process"):
            recover(path)
        assert path.read_bytes() == before
        assert [e.outcome for e in list_trials(tmp_path)] == ["running"]
        writer.stdin.write("\n")
        writer.stdin.flush()
        assert writer.wait(20) == 0
    finally:
        writer.kill()
    log = read_log(path)
    assert log.complete and log.outcome == "completed" and len(log.events) == 200


def test_a_crashed_writers_log_is_still_recovered(tmp_path):
    path = tmp_path / "crashed.mcap"
    writer = subprocess.Popen([sys.executable, "-c", HOLD_OPEN, str(path)], cwd=ROOT, text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    assert writer.stdout.readline().strip() == "writing"
    writer.kill()  # its flock goes with it
    writer.wait(10)
    assert find_unfinished(tmp_path) == [path]
    recover(path)
    log = read_log(path)
    assert log.complete and log.outcome == "interrupted"


def test_a_close_slower_than_its_timeout_is_not_reported_as_completed(tmp_path, monkeypatch):
    release = threading.Event()
    finish = Writer.finish

    def slow_finish(self):
        release.wait(20)  # a disk that takes its time
        return finish(self)

    monkeypatch.setattr(Writer, "finish", slow_finish)
    config = RigConfig()
    clock = VirtualClock(0)
    dev = open_devices(config, clock, speed=0)
    trial = Trial(parse_protocol(SHORT, "<test>"), config, dev.slider, dev.loadcell, clock,
                  tmp_path / "slow.mcap", TrialInfo(clock="virtual"))
    trial.close_timeout_s = 0.5
    try:
        t0 = time.monotonic()
        result = trial.run()
        assert time.monotonic() - t0 < 15
    finally:
        release.set()
        trial.recorder.thread.join(20)
        dev.close()
    assert result.outcome == "fault", result
    assert "not finished within 0.5 s" in result.fault and str(result.log_path) in result.fault
    assert trial.snapshot.state == "fault"
    assert read_log(result.log_path).complete  # it did finish, later


def test_recorder_holds_its_log_locked_until_closed(tmp_path):
    rec = Recorder(tmp_path / "x.mcap")
    from rig.recording.recorder import is_being_written

    assert is_being_written(rec.path)
    rec.close()
    assert not is_being_written(rec.path)
    assert os.path.getsize(rec.path) > 0


def test_sigkill_halfway_keeps_all_but_the_last_second(tmp_path):
    """A trial killed with SIGKILL leaves a log `rig replay` reads, holding every sample up
    to at least the last second before the kill."""
    out = tmp_path / "logs"
    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", "run", str(PROTOCOLS / "demo.yaml"),
                             "--out", str(out), "--quiet"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not (out.exists() and list(out.iterdir())):
            time.sleep(0.05)
        time.sleep(5.0)  # halfway through the ~11 s demo
        kill_ns = time.time_ns()
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    (path,) = list(out.iterdir())
    log = read_log(path)
    assert not log.complete
    assert log.n > 300
    # wall time of the last sample kept, from its tick's position in the trial
    start_ns = int(np.datetime64(log.trial["start_time"].replace("+00:00", ""), "ns").astype(np.int64))
    last_ns = start_ns + int(log.samples["t_s"][-1] * 1e9)
    assert kill_ns - last_ns <= 1.0e9 + 0.2e9, (kill_ns - last_ns) / 1e9
    assert np.array_equal(log.samples["seq"], np.arange(log.n))
    # and the command-line replay reads it
    rep = subprocess.run([sys.executable, "-m", "rig.cli", "replay", str(path), "--json"],
                         capture_output=True, text=True, timeout=60)
    assert rep.returncode == 0, rep.stderr
    summary = json.loads(rep.stdout)
    assert summary["complete"] is False and summary["samples"] == log.n
