"""`rig analyze --each`: every curve of a map, a folder or a glob analysed on its own, through the
command line as a user runs it, on the shared real AFM records: one row per curve, the same
answer as the curve analysed alone, a table that does not depend on the workers or on an
interruption, bad curves that never stop a batch."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rig.cli import EXIT_CURVES_FAILED, EXIT_ERROR, main

AFM = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "afm-fd"
MAP = AFM / "fmt-jpk-fd_map2x2_extracted.jpk-force-map"
QI = AFM / "fmt-jpk-fd_2020.02.07-16.29.05.036.jpk-qi-data"
HERTZ = ["--model", "hertz", "--indenter", "paraboloid:R=10um", "--segment", "approach"]


@pytest.fixture(autouse=True)
def _records():
    if not MAP.is_file():
        pytest.skip(f"the shared real records are absent ({AFM})")
    pytest.importorskip("afmformats", reason="reading AFM maps needs the afm extra (afmformats)")


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_a_map_alone_gives_one_row_per_curve_each_as_analysed_alone(tmp_path, capsys):
    table = tmp_path / "map.csv"
    assert main(["analyze", str(MAP), *HERTZ, "--table", str(table)]) == 0
    rows = _rows(table)
    assert [r["curve"] for r in rows] == ["0", "1", "2", "3"]
    assert all(r["error"] == "" for r in rows)
    # where each curve was taken, from the map's own metadata
    assert len({(r["grid_x"], r["grid_y"]) for r in rows}) == 4
    assert all(float(r["x_m"]) != 0 or float(r["y_m"]) != 0 for r in rows)
    out = capsys.readouterr().out
    assert "4 curves from 1 file, model hertz: 4 analysed, 0 could not be" in out
    for r in rows:
        assert main(["analyze", str(MAP), *HERTZ, "--curve", r["curve"], "--json"]) == 0
        alone = json.loads(capsys.readouterr().out)
        assert float(r["E_Pa"]) == alone["material"]["E_Pa"]
        assert float(r["E_Pa_stat"]) == alone["material"]["E_Pa_stat"]
        assert (r["adequate"] == "True") == alone["adequate"]
        assert float(r["contact_point_m"]) == alone["material"]["contact_point_m"][0]


def test_the_table_does_not_depend_on_the_workers(tmp_path):
    tables = []
    for workers in ("1", "2"):
        t = tmp_path / f"w{workers}.csv"
        assert main(["analyze", str(MAP), str(QI), "--each", *HERTZ, "--workers", workers,
                     "--table", str(t)]) == 0
        tables.append(t.read_bytes())
    assert tables[0] == tables[1]
    assert len(tables[0].splitlines()) == 1 + 4 + 4


def test_bad_curves_never_stop_a_batch_and_the_exit_status_counts_them(tmp_path, capsys):
    """A folder with a good map, a map cut short in transfer and a note: the cut map is a row that
    says why, the note is not a record and is only listed (a folder also holds pictures, notes,
    truth files and tables); a file named on the command line is always a row."""
    folder = tmp_path / "study"
    folder.mkdir()
    (folder / "a.jpk-force-map").write_bytes(MAP.read_bytes())
    (folder / "b-cut.jpk-force-map").write_bytes(MAP.read_bytes()[:5000])  # cut short in transfer
    (folder / "notes.txt").write_text("specimen 3, second site\n")
    # a table written into the folder it analyses leaves its request and journal there: not inputs
    (folder / "t.csv.request.json").write_text("{}")
    (folder / "t.csv.partial.jsonl").write_text("")
    code = main(["analyze", str(folder), *HERTZ, "--json"])
    captured = capsys.readouterr()
    rows = [json.loads(x) for x in captured.out.splitlines()]
    bad = [r for r in rows if r["error"]]
    assert code == EXIT_CURVES_FAILED + len(bad) and len(bad) == 1, (code, bad)
    assert sum(1 for r in rows if not r["error"]) == 4
    assert Path(bad[0]["file"]).name == "b-cut.jpk-force-map"
    assert len(bad[0]["error"].splitlines()) == 1 and "Traceback" not in bad[0]["error"]
    assert not any(Path(r["file"]).name == "notes.txt" for r in rows)
    code = main(["analyze", str(folder), *HERTZ])
    assert "skipped 1 file in the folders given that are not records: notes.txt" in capsys.readouterr().out
    named = main(["analyze", str(folder / "a.jpk-force-map"), str(folder / "notes.txt"), "--each", *HERTZ,
                  "--json"])
    rows = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert named == EXIT_CURVES_FAILED + 1 and "not a file this tool can read" in rows[-1]["error"]


def test_a_resume_keeps_its_settings_and_knows_a_file_however_it_is_named(tmp_path, monkeypatch, capsys):
    table = tmp_path / "t.csv"
    assert main(["analyze", str(MAP), *HERTZ, "--table", str(table), "--workers", "1"]) == 0
    first = table.read_bytes()
    # the same file named another way: nothing to do, nothing lost
    monkeypatch.chdir(MAP.parent)
    assert main(["analyze", f"./{MAP.name}", *HERTZ, "--table", str(table), "--resume"]) == 0
    assert "4 kept from the earlier run" in capsys.readouterr().out
    assert table.read_bytes() == first
    # other settings would mix two analyses in one table: refused, the table untouched
    assert main(["analyze", str(MAP), "--model", "hertz", "--indenter", "paraboloid:R=20um", "--segment",
                 "approach", "--table", str(table), "--resume"]) == EXIT_ERROR
    err = capsys.readouterr().err
    assert "its rows were made with other settings" in err and "paraboloid:R=20um" in err
    assert table.read_bytes() == first


def test_an_interrupted_batch_resumes_to_the_same_table(tmp_path):
    """Killed (SIGKILL) after its first rows reached the journal, then --resume: the same table,
    byte for byte, as a batch that ran through; without --resume the table is not overwritten."""
    full = tmp_path / "full.csv"
    args = [str(MAP), str(QI), "--each", *HERTZ, "--workers", "1"]
    assert main(["analyze", *args, "--table", str(full)]) == 0
    cut = tmp_path / "cut.csv"
    journal = Path(str(cut) + ".partial.jsonl")
    proc = subprocess.Popen([sys.executable, "-m", "rig", "analyze", *args, "--table", str(cut)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (journal.exists() and journal.read_text().count("\n") >= 2):
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not cut.exists(), "killed midway: no table yet, only the journal"
    done = journal.read_text().count("\n")
    assert 2 <= done < 8, done
    assert main(["analyze", *args, "--table", str(cut)]) == EXIT_ERROR  # refuses to overwrite
    assert main(["analyze", *args, "--table", str(cut), "--resume"]) == 0
    assert cut.read_bytes() == full.read_bytes()
    assert not journal.exists()
    # a finished table resumed: nothing to do, the same table
    assert main(["analyze", *args, "--table", str(cut), "--resume"]) == 0
    assert cut.read_bytes() == full.read_bytes()


def test_what_a_batch_cannot_do_is_refused_in_one_line(tmp_path, capsys):
    cases = [
        ([str(MAP), *HERTZ, "--compare"], "--compare is not for a batch"),
        ([str(MAP), *HERTZ, "--resume"], "--resume continues the table of an earlier batch"),
        ([str(MAP), *HERTZ, "--table", str(tmp_path / "t.xlsx")], "a .csv, .jsonl or .parquet file"),
        ([str(MAP), *HERTZ, "--curve", "1", "--table", str(tmp_path / "t.csv")], "--table is for a batch"),
        ([str(tmp_path / "nothing-*.jpk-force")], "no file matches"),
    ]
    for args, message in cases:
        assert main(["analyze", *args]) == EXIT_ERROR, args
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err


def test_a_dask_cluster_gives_the_same_table(tmp_path):
    """A real Dask scheduler and two workers, started on loopback as a cluster's would be (the
    `dask` command line), do the batch: the table is the local run's, byte for byte."""
    pytest.importorskip("distributed", reason="the cluster extra (Dask distributed) is not installed")
    dask = Path(sys.executable).with_name("dask")
    if not dask.exists():
        pytest.skip(f"the dask command line is not beside {sys.executable}")
    info = tmp_path / "scheduler.json"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [subprocess.Popen([str(dask), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(info)], **quiet)]
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not info.exists():
            time.sleep(0.1)
        address = json.loads(info.read_text())["address"]
        procs.append(subprocess.Popen([str(dask), "worker", address, "--nworkers", "2", "--nthreads", "1",
                                       "--no-dashboard", "--host", "127.0.0.1"], **quiet))
        wait = ("from distributed import Client\n"
                f"with Client({address!r}, timeout='30s') as c: c.wait_for_workers(2, timeout=60)")
        subprocess.run([sys.executable, "-c", wait], check=True, timeout=120)
        args = [str(MAP), str(QI), "--each", *HERTZ]
        local, remote = tmp_path / "local.csv", tmp_path / "dask.csv"
        assert main(["analyze", *args, "--table", str(local)]) == 0
        # in its own process, as a user runs it (a Dask client keeps a thread for its connection)
        done = subprocess.run([sys.executable, "-m", "rig", "analyze", *args, "--table", str(remote),
                               "--scheduler", address], capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        assert remote.read_bytes() == local.read_bytes()
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            p.wait(timeout=30)


def test_a_scheduler_that_does_not_answer_is_said_in_one_line():
    pytest.importorskip("distributed", reason="the cluster extra (Dask distributed) is not installed")
    done = subprocess.run([sys.executable, "-m", "rig", "analyze", str(MAP), *HERTZ, "--scheduler",
                           "tcp://127.0.0.1:9"], capture_output=True, text=True, timeout=120)
    assert done.returncode == EXIT_ERROR, done.stderr
    assert "cannot reach the Dask scheduler" in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_the_notebook_api_gives_a_dataframe_and_a_grid(tmp_path):
    """analyze_curves: the rows of --table as a pandas DataFrame; on_grid: the map on its grid as an
    xarray Dataset; a Parquet table reads back as the same frame."""
    pytest.importorskip("pandas", reason="the table extra (pandas) is not installed")
    pytest.importorskip("xarray", reason="the table extra (xarray) is not installed")
    from rig.analysis.batch.each import analyze_curves, on_grid

    df = analyze_curves(str(MAP), indenter="paraboloid:R=10um", workers=1, progress=False)
    assert list(df["curve"]) == [0, 1, 2, 3] and df["error"].eq("").all()
    table = tmp_path / "map.csv"
    assert main(["analyze", str(MAP), *HERTZ, "--table", str(table), "--workers", "1"]) == 0
    assert [float(r["E_Pa"]) for r in _rows(table)] == list(df["E_Pa"])
    grid = on_grid(df)
    assert grid["E_Pa"].sizes == {"grid_y": 2, "grid_x": 2}
    for gy, gx, v in zip(df["grid_y"], df["grid_x"], df["E_Pa"], strict=True):
        assert float(grid["E_Pa"].sel(grid_y=int(gy), grid_x=int(gx))) == v
    pytest.importorskip("pyarrow", reason="the table extra (pyarrow) is not installed")
    import pandas as pd

    pq = tmp_path / "map.parquet"
    assert main(["analyze", str(MAP), *HERTZ, "--table", str(pq), "--workers", "1"]) == 0
    back = pd.read_parquet(pq)
    assert list(back["E_Pa"]) == list(df["E_Pa"]) and list(back.columns) == list(df.columns)


def test_a_script_without_the_main_guard_is_told_what_to_do(tmp_path):
    """The workers re-import the script that started them: without `if __name__ == "__main__":`
    they cannot start, and the error says so instead of a broken pool."""
    pytest.importorskip("pandas", reason="the table extra (pandas) is not installed")
    script = tmp_path / "no_guard.py"
    script.write_text("from rig.analysis.batch.each import analyze_curves\n"
                      f"analyze_curves({str(MAP)!r}, indenter='paraboloid:R=10um', workers=2,\n"
                      "               progress=False)\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert done.returncode != 0
    # the last line but multiprocessing's resource tracker's, which may warn at the exit after it
    lines = [line for line in done.stderr.strip().splitlines() if "resource_tracker" not in line]
    last = lines[-1]
    assert last.startswith("rig.errors.RigError: the worker processes could not start"), done.stderr
    assert 'if __name__ == "__main__":' in last


def test_a_batch_report_draws_the_map_and_says_what_is_missing_where(tmp_path, capsys):
    rep = tmp_path / "rep"
    assert main(["analyze", str(MAP), *HERTZ, "--explain", "--report", str(rep), "--table",
                 str(tmp_path / "t.csv")]) == 0
    out = capsys.readouterr().out
    assert f"report: {rep / 'report.md'}" in out
    names = {p.name for p in rep.iterdir()}
    assert {"map1_E_Pa.png", "map1_rmse_over_noise.png", "map1_effect.png", "hist_E_Pa.png",
            "report.md"} <= names
    text = (rep / "report.md").read_text()
    effects = {r["effect"] for r in _rows(tmp_path / "t.csv") if r["effect"]}
    assert effects and all(f"| {e} |" in text for e in effects)
    assert "4 curves from 1 file, model hertz" in text and "![" in text


def test_a_mach1_file_is_analysed_site_by_site(tmp_path, capsys):
    """A Mach-1 file of three test sites (one data block each): one row per block, numbered as the
    file numbers them, each the block analysed alone with --block."""
    from tests.test_records import sls_record, write_mach1

    blocks = []
    for k, stiffness in enumerate((2.0e4, 4.0e4, 8.0e4)):
        t, x, f = sls_record(0.1, 40e-6, 40.0, 120.0, stiffness, 60.0, 3.6e6, seed=k, rest_s=5.0, noise_N=2e-4)
        blocks.append((f"Stress Relaxation site {k + 1}", t, 0.1574 - x * 1000.0, -f))
    path = tmp_path / "sites.txt"
    write_mach1(path, blocks, "N")
    table = tmp_path / "sites.csv"
    assert main(["analyze", str(path), "--each", "--model", "kelvin", "--table", str(table)]) == 0
    assert "3 curves from 1 file, model kelvin: 3 analysed" in capsys.readouterr().out
    rows = _rows(table)
    assert [r["curve"] for r in rows] == ["1", "2", "3"] and all(r["error"] == "" for r in rows)
    for r in rows:
        assert main(["analyze", str(path), "--model", "kelvin", "--block", r["curve"], "--json"]) == 0
        alone = json.loads(capsys.readouterr().out)
        assert float(r["k_N_per_m"]) == alone["parameters"]["k_N_per_m"]["value"]
    k = [float(r["k_N_per_m"]) for r in rows]
    assert k[0] < k[1] < k[2]
