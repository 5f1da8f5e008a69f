"""Batches against nanite 4.2.3 (a GPL benchmark-only peer, imported only under tests/bench/):

    python -m pytest -p no:cacheprovider tests/bench/test_bench_each.py -s -q

- every real map and QI file in ../shared/realdata/afm-fd/ through `rig analyze --each --table`:
  one row per curve, each row's E the same as the curve analysed alone, and E within 3 % of
  nanite's (weight_cp=0, plain least squares) or the difference explained as
  test_bench_nanite.py explains it (rig's residual the lower, or E not determined that closely);
  the table and the comparison printed.

Skipped, saying why, without nanite or the data.
"""

from __future__ import annotations

import csv
import importlib
import importlib.util
import os
import time
from pathlib import Path

import pytest

from rig.cli import main

DATA = Path(__file__).resolve().parents[3] / "shared" / "realdata"
AFM = DATA / "afm-fd"
MAPS = ("fmt-jpk-fd_map2x2_extracted.jpk-force-map", "fmt-jpk-fd_map-data-reference-points.jpk-force-map",
        "fmt-jpk-fd_2020.02.07-16.29.05.036.jpk-qi-data", "fmt-jpk-fd_qi-data-2021.04.13.jpk-qi-series",
        "fmt-afm-workshop-fd_mapping_16_2018-08-01_13.07.zip")

if importlib.util.find_spec("nanite") is None:
    WHY = "nanite is not installed (a benchmark-only peer: pip install nanite==4.2.3)"
elif not AFM.is_dir():
    WHY = f"no shared AFM files at {AFM}"
else:
    WHY = ""
needs_nanite = pytest.mark.skipif(bool(WHY), reason=WHY or "-")


def _table(tmp: Path, name: str) -> list[dict]:
    T = importlib.import_module("tests.bench.nanite_table")
    path = AFM / name
    o = T.override(path) or {}
    extra = [a for k, flag in (("spring constant", "--spring-constant"), ("sensitivity", "--sensitivity"))
             if k in o for a in (flag, str(o[k]))]
    table = tmp / f"{name}.csv"
    code = main(["analyze", str(path), "--each", "--model", "hertz", "--indenter", T.INDENTER,
                 "--segment", "approach", "--table", str(table), *extra])
    assert code == 0, code
    with open(table, newline="") as fh:
        return list(csv.DictReader(fh))


@needs_nanite
@pytest.mark.parametrize("name", MAPS)
def test_each_curve_of_a_map_agrees_with_nanite(name, tmp_path):
    T = importlib.import_module("tests.bench.nanite_table")
    rows = _table(tmp_path, name)
    numbers = [c for p, c in T.curves(DATA) if p.name == name]
    assert [int(r["curve"]) for r in rows] == numbers  # one row per curve, numbered as the instrument does
    for r in rows:
        row = T.fit_row(AFM / name, int(r["curve"]))
        print(f"\n{T.markdown_row(row)}")
        assert row.rig is not None, row.failed
        assert float(r["E_Pa"]) == row.rig.E_Pa  # the batch's row is the curve analysed alone
        if row.nanite0 is None:
            continue
        c = row.same
        close = abs(row.diff) <= T.WITHIN
        better = c.rig_rmse_N <= c.nanite_rmse_N or c.rig_rmse_approach_N <= c.nanite_rmse_approach_N
        se = row.rig.E_stderr
        undetermined = (se is not None and abs(row.rig.E_Pa - row.nanite0.E_Pa) <= 2 * se
                        and c.rig_rmse_N <= 1.005 * c.nanite_rmse_N)
        assert close or better or undetermined, T.explain(row)


PAPER_TRIALS = int(os.environ.get("RIG_BENCH_TRIALS", "1000"))


def _paper_trial(seed: int, out: str) -> str:
    from rig.service.run import RunOptions, run_trial
    from rig.specs.config import RigConfig
    from rig.specs.protocol import load_protocol

    protocols = sorted((Path(__file__).resolve().parents[2] / "protocols").glob("paper-*.yaml"))
    cfg = RigConfig()
    cfg.sim.seed = seed
    proto = load_protocol(protocols[seed % len(protocols)], cfg)
    path = Path(out) / f"paper-{seed:05d}.mcap"
    run_trial(proto, cfg, RunOptions(speed=0, progress=False, log_path=path))
    return str(path)


def test_a_thousand_paper_trials(tmp_path):
    """RIG_BENCH_TRIALS (default 1000) simulated paper trials (the three protocols in turn, a seed
    each), then `rig analyze --each` over the folder with the paper's model: the summary gives the
    wall time and how the workers' time splits between reading the MCAP logs and fitting."""
    from concurrent.futures import ProcessPoolExecutor

    t0 = time.perf_counter()
    with ProcessPoolExecutor() as pool:
        logs = list(pool.map(_paper_trial, range(PAPER_TRIALS), [str(tmp_path)] * PAPER_TRIALS, chunksize=16))
    made = time.perf_counter() - t0
    table = tmp_path / "paper.csv"
    t0 = time.perf_counter()
    code = main(["analyze", str(tmp_path), "--each", "--model", "proposed", "--table", str(table)])
    wall = time.perf_counter() - t0
    with open(table, newline="") as fh:
        rows = list(csv.DictReader(fh))
    print(f"\n{PAPER_TRIALS} paper trials simulated in {made:.1f} s; the batch took {wall:.1f} s "
          f"({PAPER_TRIALS / wall:.3g} trials/s)")
    assert code == 0 and len(rows) == len(logs) and all(r["error"] == "" for r in rows)
