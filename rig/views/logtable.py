"""`rig logs --table FILE`: the trials in the recorder directory as a table, one row per trial.

Columns: `started`, `specimen`, `protocol`, `outcome` (as `rig logs` shows it), `peak_force_N`,
`hold_end_stiffness_N_per_m` (the estimate at the last hold's end), `estimator_error_rms_N`
(the online estimator's RMS error over the contact samples), `duration_s`, `calibration_date`
(the load cell's calibration the log's header names, `rig calibrate`; empty without one),
`thickness_mm` and `area_mm2` (the specimen's dimensions given at the start), `file`. A figure
the log cannot give (a log being written, one without a hold) is empty. CSV, or Parquet for a
`.parquet` name (with pyarrow installed).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

from rig.errors import RigError

COLUMNS = ["started", "specimen", "protocol", "outcome", "peak_force_N", "hold_end_stiffness_N_per_m",
           "estimator_error_rms_N", "duration_s", "calibration_date", "thickness_mm", "area_mm2", "file"]


def _float(v) -> float | None:
    try:
        return float(v) if v not in (None, "") else None
    except ValueError:
        return None


def table_rows(entries, figures: list[dict], out_dir: Path) -> list[dict]:
    """One row per entry of `list_trials`, with its `trial_figures`."""
    rows = []
    for e, f in zip(entries, figures, strict=True):
        shown = str(e.path.relative_to(out_dir)) if e.path.is_relative_to(out_dir) else e.path.name
        rows.append({
            "started": e.start_time, "specimen": e.specimen, "protocol": e.protocol,
            "outcome": e.outcome + (" (recovered)" if e.recovered else ""),
            "peak_force_N": f.get("peak_force_N"),
            "hold_end_stiffness_N_per_m": f.get("hold_end_stiffness_N_per_m"),
            "estimator_error_rms_N": f.get("estimator_error_rms_N"), "duration_s": e.duration_s,
            "calibration_date": f.get("calibration_date") or "",
            "thickness_mm": _float(f.get("thickness_mm")), "area_mm2": _float(f.get("area_mm2")),
            "file": shown})
    return rows


def write_logs_table(rows: list[dict], path: str | Path) -> Path:
    """`rows` to `path`: Parquet for a .parquet name, else CSV; through a temporary file, so
    what is under the name is always a whole table."""
    p = Path(path)
    if p.is_dir() or not p.parent.is_dir():
        raise RigError(f"--table {path}: not a file in an existing directory")
    tmp = p.with_name(p.name + ".tmp")
    if p.suffix.lower() == ".parquet":
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            raise RigError("--table .parquet needs pyarrow: pip install 'indentation-rig[table]' "
                           "(or give a .csv name)") from None
        pq.write_table(pa.Table.from_pylist([{c: r.get(c) for c in COLUMNS} for r in rows],
                                            schema=_schema(pa)), tmp)
    else:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(COLUMNS)
            for r in rows:
                w.writerow(["" if r.get(c) is None else r[c] for c in COLUMNS])
    os.replace(tmp, p)
    return p


def _schema(pa):
    numbers = {"peak_force_N", "hold_end_stiffness_N_per_m", "estimator_error_rms_N", "duration_s",
               "thickness_mm", "area_mm2"}
    return pa.schema([(c, pa.float64() if c in numbers else pa.string()) for c in COLUMNS])
