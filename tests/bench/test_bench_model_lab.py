"""Model-lab benchmarks (not in the default run: `python -m pytest tests/bench -s`).

- `rig analyze` on one 100 s trial, whole process including imports, against the 40-line scipy
  peer (tests/bench/peer_fit.py) doing the same fit: median wall time of several alternating
  runs (CPU seconds printed alongside).
- `--explain` on a 120,000-sample record within 30 s; `--auto` on three of them within 60 s.

Figures are printed (wall and CPU seconds); the machine's load is printed too, since another
process competing for the two cores stretches wall time, not CPU time.
"""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rig.recording.logs import export_csv, read_log
from tests.bench.long_records import make
from tests.conftest import PROTOCOLS, ROOT, run_sim

PEER = Path(__file__).with_name("peer_fit.py")


def timed(cmd: list[str]) -> tuple[float, float, str]:
    """Wall and CPU (user + sys of the child) seconds of one command, and its stdout."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert proc.returncode == 0, proc.stderr
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, proc.stdout


def load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def test_analyze_is_no_slower_than_a_scipy_script(tmp_path):
    log = run_sim(PROTOCOLS / "paper-0.75mm_s.yaml", tmp_path=tmp_path, name="p.mcap").log_path
    csv = tmp_path / "trial.csv"
    export_csv(read_log(log), csv)
    rig_cmd = [sys.executable, "-m", "rig", "analyze", str(csv)]
    peer_cmd = [sys.executable, str(PEER), str(csv)]
    rig_runs, peer_runs = [], []
    for _ in range(7):  # alternate, so a burst of load hits both
        rig_runs.append(timed(rig_cmd)[:2])
        peer_runs.append(timed(peer_cmd)[:2])
    rw, rc = (statistics.median(r[i] for r in rig_runs) for i in (0, 1))
    pw, pc = (statistics.median(r[i] for r in peer_runs) for i in (0, 1))
    print(f"\n100 s trial ({load()}): rig analyze {rw:.2f} s wall, {rc:.2f} s CPU; "
          f"scipy peer {pw:.2f} s wall, {pc:.2f} s CPU")
    assert rw <= pw


@pytest.fixture(scope="module")
def long_logs(tmp_path_factory):
    return make(tmp_path_factory.mktemp("long"), n=3, drift_N_per_s=2e-4)


def test_explain_on_a_long_record(long_logs):
    wall, cpu, out = timed([sys.executable, "-m", "rig", "analyze", str(long_logs[0]), "--explain"])
    samples = read_log(long_logs[0]).n
    print(f"\n--explain on {samples} samples ({load()}): {wall:.1f} s wall, {cpu:.1f} s CPU")
    assert samples >= 120_000
    assert "most likely missing: drift" in out
    assert wall <= 30.0


def test_auto_on_three_long_records(long_logs):
    wall, cpu, out = timed([sys.executable, "-m", "rig", "analyze", *map(str, long_logs), "--auto"])
    print(f"\n--auto on three long records ({load()}): {wall:.1f} s wall, {cpu:.1f} s CPU")
    assert "+drift" in out and "final model" in out
    assert wall <= 60.0
