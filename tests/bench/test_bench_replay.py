"""Replay speed: reading a trial log into arrays, as `rig bench` measures it (`bench_replay`):

    python -m pytest -p no:cacheprovider tests/bench/test_bench_replay.py -s -q

- the log `rig bench` reads: a 60 s real-clock trial at 100 Hz with in-process simulated devices
  (one chunk a second, as every real trial's log); and the paper's 107 s protocol run in virtual
  time (chunks of 256 KiB);
- target: at least 500,000 samples/s (median of 5 reads), reached by reading the samples from the
  columns the recorder attaches to a finished log (rig/recording/columns.py) instead of decoding
  every message's JSON;
- and at least 2x the reader that decoded message by message (tests/test_logs.py keeps it as the
  reference), timed the same way on the same log, so a change that loses the speed-up shows here
  even on a slower machine.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import pytest

from rig.diagnostics.bench import _bench_protocol, bench_replay
from rig.service.run import RunOptions, run_trial
from rig.specs.config import RigConfig
from rig.specs.protocol import parse_protocol
from tests.conftest import PROTOCOLS, run_sim
from tests.test_logs import _read_log_per_message, assert_reads_as_per_message

TARGET_SAMPLES_PER_S = 500_000
SPEEDUP_OVER_PER_MESSAGE = 2.0
READS = 5


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("replay")
    real = tmp / "bench.mcap"
    result = run_trial(parse_protocol(_bench_protocol(60.0), "<bench>"), RigConfig(),
                       RunOptions(speed=1.0, progress=False, log_path=real))
    # a trial cut short (a busy machine starves the simulated devices) leaves a log of a few
    # hundred samples, whose reading is mostly a fixed cost: not the figure this is about
    assert result.outcome == "completed", f"the 60 s trial did not complete: {result.fault}"
    paper = run_sim(PROTOCOLS / "paper-0.75mm_s.yaml", tmp_path=tmp, name="paper.mcap").log_path
    return {"rig bench (60 s, real clock)": real, "paper 0.75 mm/s (virtual time)": paper}


def _per_message_rate(path: Path) -> float:
    rates = []
    for _ in range(READS):
        t0 = time.perf_counter()
        log = _read_log_per_message(path)
        rates.append(log.n / (time.perf_counter() - t0))
    return statistics.median(rates)


@pytest.fixture(scope="module")
def figures(logs) -> dict[str, tuple[dict, float]]:
    out = {}
    for name, path in logs.items():
        assert_reads_as_per_message(path, columns=True)  # the speed is for the same result
        out[name] = (bench_replay(path, READS), _per_message_rate(path))
        fast, slow = out[name]
        assert fast["columns"]
        print(f"\n{name}: {fast['samples']} samples, {fast['samples_per_s']:,.0f} samples/s "
              f"(first read {fast['first_read_samples_per_s']:,.0f}); message by message "
              f"{slow:,.0f} samples/s; x{fast['samples_per_s'] / slow:.1f}")
    return out


def test_faster_than_decoding_message_by_message(figures):
    for name, (fast, slow) in figures.items():
        assert fast["samples_per_s"] >= SPEEDUP_OVER_PER_MESSAGE * slow, name


def test_replay_target(figures):
    for name, (fast, _) in figures.items():
        assert fast["samples_per_s"] >= TARGET_SAMPLES_PER_S, (name, round(fast["samples_per_s"]))
