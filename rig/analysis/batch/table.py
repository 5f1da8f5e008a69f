"""The table of a batch: one row per curve, as CSV, JSON lines or Parquet.

While a batch runs, each finished chunk's rows are appended to a journal beside the table
(`OUT.partial.jsonl`, flushed as they come), so a batch killed midway loses only the chunks in
flight; `--resume` reads the rows already there (the journal and any table already written)
and does only the curves missing. The table is written once, at the end, all rows in the
order of the inputs, to a temporary file that then replaces it: what is on disk under the
table's name is always a whole table.

Columns: where the curve is (`file`, `curve`, `x_m`, `y_m`, `grid_x`, `grid_y`), every parameter
with its statistical error (the noise's, given the model: `E_Pa_stat`) and, for a contact fit, its
systematic error (how far the fit's range and baseline move it beyond their noise: `E_Pa_sys`;
rig.analysis.intervals.systematic), `contact_point_m` with the same two, the
error and the noise (`rmse_N`, `noise_N`, `rmse_over_noise`), `adequate`, with `--explain` the
missing effect and its dBIC, the curve's `quality` and its `quality_parts`, and `error`: why a
curve could not be analysed (empty otherwise).

`quality` rates a curve from 0 (unusable) to 10 (clean), the sum of four parts (rig.analysis.batch.quality;
docs/explanation/quality.md), each measured, none trained:

- contact, 0-3: the contact point's uncertainty (statistical and systematic combined) over the
  indentation past it: 3 at 1 % or less, 0 at 30 % or more, log-linear between (3 where the record
  knows its surface; 0 where less than 5 % of the curve is out of contact);
- fit, 0-4: `rmse_over_noise`: 4 at 1.1 or less, 0 at 5 or more, log-linear between;
- baseline, 0-2: the share of the curve's samples out of contact: 2 from 30 % to 90 %, falling
  linearly to 0 at 5 % and at 99 %;
- artefacts, 0-1: 1 with nothing named, 0.5 with one, 0 with more: the reader's caveats, a curve
  that starts in contact, the effect `--explain` names missing, a physics warning of the fit.

`rig analyze --each --min-quality Q` keeps the table whole and leaves the curves rated below Q
out of the summary's statistics and the report's maps and histograms.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterable
from pathlib import Path

from rig.errors import RigError

PLACE = ["file", "curve", "x_m", "y_m", "grid_x", "grid_y"]
TAIL = ["contact_point_m", "contact_point_m_stat", "contact_point_m_sys", "rmse_N", "noise_N",
        "rmse_over_noise", "adequate", "segment", "caveats", "effect", "effect_dbic", "quality",
        "quality_parts", "error"]
FORMATS = {".csv": "csv", ".jsonl": "jsonl", ".json": "jsonl", ".parquet": "parquet"}


def table_format(path: str | Path) -> str:
    """The table's format from its name (csv, jsonl or parquet), or RigError saying which names work and,
    for Parquet, what to install."""
    fmt = FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise RigError(f"--table {path}: a .csv, .jsonl or .parquet file")
    if fmt == "parquet":
        try:
            import pandas  # noqa: F401
            import pyarrow  # noqa: F401
        except ImportError:
            raise RigError("--table .parquet needs pandas and pyarrow: "
                           "pip install 'indentation-rig[table]'") from None
    target = Path(path)
    if target.is_dir() or not target.parent.is_dir():
        raise RigError(f"--table {path}: not a file in an existing directory")
    return fmt


def journal_of(path: str | Path) -> Path:
    """The journal beside a table (`OUT.partial.jsonl`): each finished chunk's rows, flushed as they come,
    so a run cut short resumes from it."""
    p = Path(path)
    return p.with_name(p.name + ".partial.jsonl")


def columns(rows: Iterable[dict]) -> list[str]:
    """The place, then the parameters in the order they first appear, then the rest (a row's
    private columns, `_` first, are left out)."""
    seen = list(PLACE)
    for r in rows:
        for k in r:
            if k not in seen and k not in TAIL and not k.startswith("_"):
                seen.append(k)
    return seen + TAIL


def public(row: dict) -> dict:
    """A row without its private fields (those starting with an underscore: kept for the map's pictures, not
    written)."""
    return {k: v for k, v in row.items() if not k.startswith("_")}


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "True" if v else "False"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")
    return str(v)


def _value(text: str):
    """A CSV cell back as a number where it is one (rows read back for --resume)."""
    if text == "":
        return None
    if text in ("True", "False"):
        return text == "True"
    try:
        f = float(text)
    except ValueError:
        return text
    return int(text) if text.lstrip("-").isdigit() else f


def read_rows(path: str | Path) -> list[dict]:
    """Rows already done: the table (if written) and its journal (a last line cut short by a
    kill is left out)."""
    out: list[dict] = []
    p = Path(path)
    if p.exists():
        fmt = table_format(p)
        if fmt == "csv":
            with open(p, newline="") as fh:
                out += [{k: _value(v) for k, v in row.items()} for row in csv.DictReader(fh)]
        elif fmt == "jsonl":
            out += _jsonl(p)
        else:
            import pandas as pd

            out += [{k: (None if isinstance(v, float) and math.isnan(v) and k in ("curve", "grid_x", "grid_y")
                         else v) for k, v in r.items()} for r in pd.read_parquet(p).to_dict("records")]
    j = journal_of(p)
    if j.exists():
        out += _jsonl(j)
    return out


def _jsonl(p: Path) -> list[dict]:
    rows = []
    with open(p) as fh:
        for line in fh:
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                break  # a line cut short by a kill: that chunk is done again
    return rows


class Journal:
    """Appends finished rows beside the table, flushed, so a kill loses only chunks in flight.
    Started at the first new rows (a batch that fails before any work leaves nothing behind),
    anew with `rows` (those kept from earlier), replacing any journal there."""

    def __init__(self, table: str | Path, rows: list[dict]) -> None:
        self.path = journal_of(table)
        self._kept = rows
        self._fh = None

    def add(self, rows: list[dict]) -> None:
        if self._fh is None:
            tmp = self.path.with_name(self.path.name + ".tmp")
            with open(tmp, "w") as fh:
                for r in self._kept:
                    fh.write(json.dumps(public(r), default=str) + "\n")
            os.replace(tmp, self.path)
            self._fh = open(self.path, "a")  # noqa: SIM115 (held open for the batch: rows go in as chunks finish)
        for r in rows:
            self._fh.write(json.dumps(public(r), default=str) + "\n")
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()


def jsonable(row: dict) -> dict:
    """Non-finite floats as strings ("inf": a parameter the curve does not determine)."""
    return {k: (_cell(v) if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in public(row).items()}


def write_table(rows: list[dict], path: str | Path) -> Path:
    """All rows, written to a temporary file that then replaces `path`."""
    p = Path(path)
    fmt = table_format(p)
    cols = columns(rows)
    tmp = p.with_name(p.name + ".tmp")
    if fmt == "csv":
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(cols)
            for r in rows:
                w.writerow([_cell(r.get(c)) for c in cols])
    elif fmt == "jsonl":
        with open(tmp, "w") as fh:
            for r in rows:
                fh.write(json.dumps(jsonable(r)) + "\n")
    else:
        import pandas as pd

        pd.DataFrame([{c: r.get(c) for c in cols} for r in rows], columns=cols).to_parquet(tmp, index=False)
    os.replace(tmp, p)
    return p
