"""The history page's data: every trial in the log folder, a row each, and one trial in full.

A row is read from the log's metadata (`rig logs`) and, once per file (kept while the file is
unchanged), its samples: peak force, the stiffness estimate at the end of the last hold, the
estimator's error (RMS over the contact samples) and the samples' count. A log still being
written gets its metadata only. Paths given by the page are names inside the log folder.

The table is exported as CSV and as an Excel workbook (openpyxl, the web extra's); a trial's
samples as the CSV `rig replay --csv` writes; several trials as one plot's data (force against
time and against indentation, labelled as `rig replay` labels them).
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
import tempfile
import threading
from pathlib import Path

import numpy as np

from rig.errors import RigError
from rig.recording.logs import export_csv, read_log
from rig.recording.recovery import list_trials

COLUMNS = ["start_time", "specimen", "protocol", "outcome", "peak_force_N", "stiffness_hold_end_N_per_m",
           "estimator_rms_error_N", "duration_s", "samples", "requested_by", "campaign", "file"]
PLOT_POINTS = 4000  # a trial's plot is drawn from at most this many samples (every n-th)
COMPARE_MAX = 12  # trials on one comparison plot
HEADINGS = {"start_time": "started", "peak_force_N": "peak force (N)",
            "stiffness_hold_end_N_per_m": "stiffness at the hold's end (N/m)",
            "estimator_rms_error_N": "estimator error, RMS (N)", "duration_s": "duration (s)",
            "requested_by": "requested by"}


def _num(x) -> float | None:
    return round(float(x), 6) if x is not None and math.isfinite(float(x)) else None


class History:
    def __init__(self, out_dir: Path) -> None:
        self.out_dir = Path(out_dir)
        self._cache: dict[str, tuple[tuple, dict]] = {}
        self._lock = threading.Lock()

    def resolve(self, rel: str) -> Path:
        """A log by its path inside the log folder; never a file outside it."""
        root = self.out_dir.resolve()
        path = (root / rel).resolve()
        if root not in path.parents or path.suffix != ".mcap" or not path.is_file():
            raise RigError(f"no trial log {rel!r} in {self.out_dir}")
        return path

    def rows(self) -> list[dict]:
        if not self.out_dir.is_dir():
            return []
        out = []
        for e in list_trials(self.out_dir):
            row = {"start_time": e.start_time, "specimen": e.specimen, "protocol": e.protocol,
                   "outcome": e.outcome + (" (recovered)" if e.recovered else ""),
                   "duration_s": _num(e.duration_s), "requested_by": e.requested_by, "campaign": e.campaign,
                   "file": str(e.path.resolve().relative_to(self.out_dir.resolve()))}
            if e.outcome != "running":
                row.update(self._figures(e.path))
            out.append(row)
        return out

    def _figures(self, path: Path) -> dict:
        try:
            st = path.stat()
        except OSError:
            return {}
        key = (st.st_mtime_ns, st.st_size)
        with self._lock:
            hit = self._cache.get(str(path))
        if hit is not None and hit[0] == key:
            return hit[1]
        try:
            figures = figures_of(read_log(path))
        except RigError as exc:
            figures = {"error": str(exc)}
        with self._lock:
            self._cache[str(path)] = (key, figures)
        return figures

    def csv_text(self) -> str:
        buf = io.StringIO()
        w = csv.DictWriter(buf, COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in self.rows():
            w.writerow({k: "" if r.get(k) is None else r.get(k) for k in COLUMNS})
        return buf.getvalue()

    def xlsx_bytes(self) -> bytes:
        """The table as an Excel workbook: numbers as numbers, the heading frozen and filtered."""
        try:
            from openpyxl import Workbook
            from openpyxl.styles import Font
        except ImportError:
            raise RigError("Excel export needs openpyxl: python3 -m pip install '.[web]'") from None
        wb = Workbook()
        ws = wb.active
        ws.title = "trials"
        ws.append([HEADINGS.get(k, k) for k in COLUMNS])
        for cell in ws[1]:
            cell.font = Font(bold=True)
        rows = self.rows()
        for r in rows:
            ws.append([r.get(k) for k in COLUMNS])
            for cell in ws[ws.max_row]:  # a name starting with "=" is text, never a formula Excel runs
                if isinstance(cell.value, str) and cell.value.startswith("="):
                    cell.data_type = "s"
        ws.freeze_panes = "A2"
        ws.auto_filter.ref = ws.dimensions
        for i, k in enumerate(COLUMNS):
            width = max([len(HEADINGS.get(k, k))] + [len(str(r.get(k) or "")) for r in rows[:500]])
            ws.column_dimensions[ws.cell(1, i + 1).column_letter].width = min(width + 2, 60)
        buf = io.BytesIO()
        wb.save(buf)
        return buf.getvalue()

    def samples_csv(self, rel: str) -> tuple[str, bytes]:
        """One trial's samples as `rig replay LOG --csv OUT` writes them: (file name, CSV)."""
        path = self.resolve(rel)
        log = read_log(path)
        fd, tmp = tempfile.mkstemp(suffix=".csv")
        os.close(fd)
        try:
            export_csv(log, tmp)
            return re.sub(r"[^A-Za-z0-9._-]", "_", path.stem) + ".csv", Path(tmp).read_bytes()
        finally:
            os.unlink(tmp)

    def compare(self, rels: list[str]) -> dict:
        """Several trials for one plot: force against time and against indentation (the position
        from the surface, as `rig replay LOG LOG ...` draws them), labelled as it labels them."""
        from rig.specs.frames import Frame
        from rig.views.replay import log_labels

        if not rels:
            raise RigError("no trials to compare: select some in the history")
        if len(rels) > COMPARE_MAX:
            raise RigError(f"{len(rels)} trials: at most {COMPARE_MAX} on one plot")
        logs = [read_log(self.resolve(r)) for r in rels]
        out = []
        for rel, log, label in zip(rels, logs, log_labels(logs), strict=True):
            n = log.n
            every = max(1, math.ceil(n / PLOT_POINTS))
            s = log.samples
            depth = log.position_mm(Frame.SURFACE) if n else np.zeros(0)
            out.append({"file": rel, "label": label, "outcome": log.outcome, "samples": n, "every": every,
                        "t_s": _col(s.get("t_s"), every), "force_N": _col(s.get("force_N"), every),
                        "indentation_mm": _col(depth, every),
                        "faults": [e.get("t_s") for e in log.events if e.get("kind") == "fault"]})
        return {"trials": out}

    def trial(self, rel: str) -> dict:
        path = self.resolve(rel)
        log = read_log(path)
        s = log.samples
        n = log.n
        every = max(1, math.ceil(n / PLOT_POINTS))

        def col(name: str) -> list:
            a = s.get(name)
            if a is None:
                return []
            return [None if not math.isfinite(v) else round(float(v), 6) for v in a[::every]]

        kinds = log.step_kind
        spans = []  # [t0, t1, kind] of each step, for shading
        t = s.get("t_s", np.zeros(0))
        for i in range(n):
            if not spans or kinds[i] != spans[-1][2]:
                spans.append([float(t[i]), float(t[i]), kinds[i]])
            else:
                spans[-1][1] = float(t[i])
        trial = log.trial
        events = [{k: v for k, v in e.items()} for e in log.events]
        return {"file": rel, "trial": trial, "outcome": log.outcome, "complete": log.complete,
                "read_error": log.read_error, "samples": n, "every": every, "figures": figures_of(log),
                "t_s": col("t_s"), "force_N": col("force_N"), "position_mm": col("position_mm"),
                "position_cmd_mm": col("position_cmd_mm"), "stiffness_N_per_m": col("stiffness_N_per_m"),
                "force_pred_N": col("force_pred_N"), "spans": spans, "events": events,
                "limits": _limits(log)}


def _col(a, every: int) -> list:
    if a is None:
        return []
    return [None if not math.isfinite(v) else round(float(v), 6) for v in np.asarray(a)[::every]]


def _limits(log) -> dict | None:
    """The force limit the trial ran under, from its start event or its metadata, when logged."""
    for e in log.events:
        lim = e.get("limits") if isinstance(e, dict) else None
        if isinstance(lim, dict) and "max_force_N" in lim:
            return lim
    return None


def figures_of(log) -> dict:
    s = log.samples
    f = s.get("force_N")
    if f is None or not len(f):
        return {"samples": 0}
    out: dict = {"samples": int(log.n), "peak_force_N": _num(np.nanmax(f))}
    k = s.get("stiffness_N_per_m")
    holds = [i for i, kind in enumerate(log.step_kind) if kind == "hold"]
    if k is not None and holds:
        out["stiffness_hold_end_N_per_m"] = _num(k[holds[-1]])
    err = s.get("error_N")
    if err is not None and log.contact is not None and np.any(log.contact):
        e = err[log.contact.astype(bool)]
        e = e[np.isfinite(e)]
        if len(e):
            out["estimator_rms_error_N"] = _num(np.sqrt(np.mean(e ** 2)))
    return out
