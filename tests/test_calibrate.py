"""`rig calibrate` on the simulated rig, through the simulated load cell's serial line (real
clock): three masses, the sensitivity found within 0.5 % of the simulated cell's, the linearity
reported, the calibration in the config and in the next log's header."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GAIN = 1.02  # the simulated cell reads 2 % high


def _rig(*args, cwd, stdin="", timeout=120):
    return subprocess.run([sys.executable, "-m", "rig", *args], cwd=cwd, input=stdin, capture_output=True,
                          text=True, timeout=timeout)


def test_three_masses_give_the_simulated_cell_s_sensitivity_and_the_next_log_carries_it(tmp_path):
    cfg = tmp_path / "rig.yaml"
    cfg.write_text(f"# the bench's rig\nsim: {{loadcell: {{gain: {GAIN}}}}}\n"
                   f"recorder: {{out_dir: {tmp_path / 'trials'}}}\n")
    # the technician confirms the empty probe, then each of the three masses
    done = _rig("calibrate", "200", "500", "1000", "--config", str(cfg), "--json", cwd=tmp_path, stdin="\n" * 4)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout[done.stdout.index("{"):])
    assert done.stdout.count("press Enter") == 4 and "simulator placed 1000 g" in done.stdout
    assert out["masses_g"] == [0, 200, 500, 1000]
    s, u = out["sensitivity"], out["sensitivity_u"]
    print(f"sensitivity {s:.6f} +/- {u:.2g} vs the simulated {GAIN}: {100 * (s / GAIN - 1):+.3f} %; "
          f"linearity {out['linearity_N']:.4f} +/- {out['linearity_u_N']:.2g} N ({out['linearity_pct']:.3f} %)")
    assert abs(s / GAIN - 1) < 0.005 and 0 < u < 0.005 * GAIN
    assert math.isfinite(out["linearity_N"]) and out["linearity_N"] >= 0 and out["linearity_pct"] >= 0
    assert out["linearity_N"] < 0.05  # the simulated cell is linear: its deviation is the readings' noise
    assert out["range_N"] == [0.0, 1.0 * 9.80665]
    text = cfg.read_text()
    assert text.startswith("# the bench's rig\n") and f"sensitivity: {s:.8g}" in text
    # the next trial's log carries it in its header
    run = _rig("run", str(ROOT / "protocols" / "demo.yaml"), "--config", str(cfg), "--speed", "0", "--quiet",
               cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    from rig.recording.logs import read_log

    (log,) = (tmp_path / "trials").glob("*.mcap")
    header = read_log(log).metadata["calibration"]
    assert header["date"] == out["date"] and float(header["sensitivity"]) == float(f"{s:.8g}")
    assert header["masses_g"] == "0 200 500 1000" and header["range_N"].split() == ["0", "9.80665"]
    table = _rig("logs", "--config", str(cfg), "--table", "day.csv", cwd=tmp_path)
    assert table.returncode == 0, table.stderr
    with open(tmp_path / "day.csv", newline="") as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["calibration_date"] == out["date"]


def test_a_scripted_calibration_reads_the_masses_of_a_file_without_asking(tmp_path):
    cfg = tmp_path / "rig.yaml"
    (tmp_path / "masses.txt").write_text("# mass in g, one a line\n0\n300\n600\n")
    done = _rig("calibrate", "--readings", "masses.txt", "--config", str(cfg), "--seconds", "0.5", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "press Enter" not in done.stdout and "linearity" in done.stdout
    sens = float(next(line for line in done.stdout.splitlines() if line.startswith("sensitivity")).split()[1])
    assert abs(sens - 1.0) < 0.005  # the built-in simulated cell reads true
