"""MCAP logs: readable by the mcap library, messages valid against their own schemas,
readable after a crash, exported to CSV."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader

from rig.errors import RigError
from rig.recording.logs import export_csv, read_log
from rig.recording.messages import EVENT_TOPIC, HEALTH_TOPIC, SAMPLE_TOPIC
from rig.records.csvfile import read_csv_trial
from rig.views.replay import summarize
from tests.conftest import PROTOCOLS, ROOT, run_sim


@pytest.fixture(scope="module")
def demo_log(tmp_path_factory):
    return run_sim(PROTOCOLS / "demo.yaml", tmp_path=tmp_path_factory.mktemp("demo")).log_path


def test_mcap_reader_opens_log(demo_log):
    with open(demo_log, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {SAMPLE_TOPIC, EVENT_TOPIC, HEALTH_TOPIC}
        for ch in topics.values():
            assert ch.message_encoding == "json"
            assert summary.schemas[ch.schema_id].encoding == "jsonschema"
        counts = summary.statistics.channel_message_counts
        samples = counts[topics[SAMPLE_TOPIC].id]
        assert samples > 1000
        assert counts[topics[HEALTH_TOPIC].id] >= 10  # about 1 Hz over an 11 s trial
        names = [m.name for m in reader.iter_metadata()]
        assert names[0] == "trial" and "outcome" in names
        attachments = {a.name: a.data for a in reader.iter_attachments()}
        assert attachments["protocol.yaml"] == (PROTOCOLS / "demo.yaml").read_bytes()
        assert b"rate_Hz" in attachments["config.yaml"]


def test_every_message_validates_against_its_schema(demo_log):
    with open(demo_log, "rb") as fh:
        reader = make_reader(fh)
        validators = {}
        n = 0
        for schema, channel, message in reader.iter_messages():
            if channel.topic not in validators:
                validators[channel.topic] = jsonschema.Draft202012Validator(json.loads(schema.data))
            validators[channel.topic].validate(json.loads(message.data))
            n += 1
    assert n > 1000


def test_schema_rejects_a_bad_message(demo_log):
    """The schemas are real constraints, not decoration."""
    log = read_log(demo_log)
    validator = jsonschema.Draft202012Validator(log.schemas[SAMPLE_TOPIC])
    with pytest.raises(jsonschema.ValidationError):
        validator.validate({"seq": -1, "t_s": "now"})


def test_trial_metadata(demo_log):
    log = read_log(demo_log)
    trial = log.trial
    for key in ("specimen", "operator", "protocol_name", "start_time", "software_version",
                "config_digest"):
        assert key in trial
    assert trial["protocol_name"].startswith("demo")
    assert log.complete and log.outcome == "completed"
    kinds = [e["kind"] for e in log.events]
    assert kinds[0] == "trial_start" and kinds[-1] == "trial_end"
    assert kinds.count("step_start") == 3 and "tare" in kinds


def test_csv_export_round_trip(demo_log, tmp_path):
    log = read_log(demo_log)
    out = tmp_path / "demo.csv"
    assert export_csv(log, out) == log.n
    with open(out) as fh:
        header = next(csv.reader(fh))
    assert header[:3] == ["t_s", "position_mm", "force_N"]
    back = read_csv_trial(out)
    assert np.array_equal(back["force_N"], log.samples["force_N"])
    assert np.array_equal(back["t_s"], log.samples["t_s"])


def test_truncated_log_reads_up_to_the_cut(demo_log, tmp_path):
    data = demo_log.read_bytes()
    full = read_log(demo_log).n
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    log = read_log(cut)
    assert not log.complete and log.outcome == "interrupted"
    assert 0 < log.n < full
    assert np.array_equal(log.samples["seq"], np.arange(log.n))  # a clean prefix
    assert summarize(log)["samples"] == log.n


def test_not_a_log_is_a_clear_error(tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"this is not mcap at all")
    with pytest.raises(RigError, match="not a readable MCAP log"):
        read_log(bad)
    with pytest.raises(RigError, match="cannot open"):
        read_log(tmp_path / "missing.mcap")


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


@pytest.mark.parametrize("text,fragment", [
    ("t_s,position_mm\n0,1\n", "missing column(s) force_N"),
    ("t_s,position_mm,force_N\n0,1,2\n0.01,x,2\n", "bad.csv:3: column position_mm: 'x' is not"),
    ("t_s,position_mm,force_N\n0,1,2\n0.01,1,nan\n", "NaN"),
    ("t_s,position_mm,force_N\n0,1,2\n0.02,1,2\n0.01,1,2\n", "unsorted"),
    ("t_s,position_mm,force_N\n0,1,2\n0,1,2\n", "duplicated"),
    ("", "empty"),
])
def test_bad_csv(tmp_path, text, fragment):
    from rig.errors import SpecError

    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(SpecError) as info:
        read_csv_trial(p)
    assert fragment in str(info.value)
