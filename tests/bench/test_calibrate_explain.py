"""The calibration benchmark in a small configuration (not in the default run:
`python -m pytest tests/bench/test_calibrate_explain.py`); the full one is
`python tests/bench/calibrate_explain.py run --out calib.jsonl` (see README, `--explain`)."""

from __future__ import annotations

import json

import pytest

from rig.analysis.diagnosis import explain as ex_mod
from tests.bench import calibrate_explain as cal


def test_small_calibration(tmp_path, capsys):
    out = tmp_path / "calib.jsonl"
    assert cal.main(["run", "--out", str(out), "--seeds", "2", "--controls", "2", "--jobs", "1",
                     "--effects", "offset", "--multiples", "0.05", "1"]) == 0
    table = capsys.readouterr().out
    records = [json.loads(line) for line in out.read_text().splitlines()]
    sizes = {r["size"]["multiple"]: r["size"]["noise_units"] for r in records if "size" in r and
             r["size"]["specimen"] == "A"}
    # an offset adds its force wherever the probe has moved: its size is linear in the multiple
    assert sizes[1.0] == pytest.approx(20 * sizes[0.05], rel=0.01) and sizes[1.0] > 1.0
    runs = [r for r in records if "size" not in r]
    assert len(runs) == 2 + 2 * 2
    for r in runs:  # the thresholds replayed offline give the verdict explain gave
        assert cal.best_of(r, ex_mod.DECISIVE_BIC, ex_mod.MIN_DROP, ex_mod.SUGGEST_BIC) == r["best"]
    summary = cal.summarise(records)
    rows = {row["multiple"]: row for row in summary["effects"]["offset"]["rows"]}
    assert rows[1.0]["found"] == 2 and rows[1.0]["runs"] == 2  # 0.3 N, 3.7x the noise: always named
    assert rows[0.05]["found"] == 0  # 0.015 N: below anything the tool can claim
    assert summary["effects"]["offset"]["smallest"]["multiple"] == 1.0
    assert summary["controls"] == 2
    assert "| offset | force_N: " in table and "false suggestions on clean controls:" in table
    # a stricter threshold can only lose suggestions
    strict = cal.summarise(records, min_drop=0.9)
    assert strict["effects"]["offset"]["smallest"] is None and strict["false"] == 0
