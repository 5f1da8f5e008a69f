"""The command line as a technician uses it."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from rig.cli import main
from tests.conftest import PROTOCOLS, ROOT


def rig(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "rig.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


def test_run_prints_where_the_log_is(tmp_path):
    proc = rig("run", str(PROTOCOLS / "demo.yaml"), "--speed", "0", "--out", str(tmp_path),
               "--specimen", "S-01", "--quiet")
    assert proc.returncode == 0, proc.stderr
    last = proc.stdout.strip().splitlines()[-1]
    assert last.startswith("log: ")
    path = last[5:]
    assert path.startswith(str(tmp_path)) and path.endswith(".mcap") and "S-01" in path
    assert "trial completed" in proc.stdout


def test_replay_outputs(tmp_path, capsys):
    assert main(["run", str(PROTOCOLS / "demo.yaml"), "--speed", "0", "--out", str(tmp_path),
                 "--quiet", "--specimen", "pig-3"]) == 0
    log = next(tmp_path.glob("*.mcap"))
    capsys.readouterr()
    csv_path, png = tmp_path / "d.csv", tmp_path / "d.png"
    assert main(["replay", str(log), "--csv", str(csv_path), "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    for word in ("specimen   pig-3", "protocol   demo", "samples", "late", "estimator  error mean",
                 "reproduces"):
        assert word in text, word
    assert csv_path.read_text().startswith("t_s,position_mm,force_N,")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    assert main(["replay", str(log), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["specimen"] == "pig-3" and data["outcome"] == "completed"
    assert data["estimator"]["reproduced"] is True


def test_check_shows_plan_and_excitation_order(capsys):
    assert main(["check", str(PROTOCOLS / "paper-0.75mm_s.yaml"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["excitation_order"] == 1
    assert info["depths_mm"] == [30.0] and info["speeds_mm_s"] == [0.75, 5.0]
    assert 106 < info["duration_s"] < 108
    assert main(["check", str(PROTOCOLS / "approach-relax.yaml")]) == 0
    text = capsys.readouterr().out
    assert "up to" in text and "excitation order 1" in text


@pytest.mark.parametrize("args,fragment", [
    (["run", "nope.yaml"], "protocol file not found"),
    (["run", str(PROTOCOLS / "demo.yaml"), "--config", "nope.yaml"], "config file not found"),
    (["replay", "nope.mcap"], "cannot open log"),
    (["run", str(PROTOCOLS / "demo.yaml"), "--speed", "-1"], "must be >= 0"),
    (["frobnicate"], "invalid choice"),
])
def test_bad_arguments_give_one_line(args, fragment):
    proc = rig(*args)
    assert proc.returncode == 2
    assert fragment in proc.stderr and "Traceback" not in proc.stderr


def test_bench_runs_and_reports(capsys):
    assert main(["bench", "--duration", "1", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    loop = r["loop"]
    assert loop["ticks"] >= 90 and loop["outcome"] == "completed"
    assert 1.0 <= loop["bus_transactions_per_tick"] <= 1.2
    assert r["rls"]["update_us"] > 0 and r["record"]["put_us"] > 0
    assert loop["replay"]["samples_per_s"] > 0
