"""The maps page's data: a batch table (`rig analyze ... --each --table T`) on its grid, and one curve.

A table's rows are put on the map's grid (`grid_x`, `grid_y`), with the axes in um from the
rows' `x_m` and `y_m` (the grid's indices where a table has no places). The maps: E in kPa,
the contact height in um (the contact point's place in the curve's travel: the sample's
topography, up to the sign of the instrument's axis), RMSE over noise and the verdict. A curve
is opened by reading it again from its file and fitting it again as the batch did (the request
kept beside the table, `T.request.json`): force against indentation with the fit, the residual,
the contact point, its verdict and the effect the batch found missing.
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import fields
from pathlib import Path

import numpy as np

from rig.analysis.batch.engine import BatchRequest
from rig.analysis.batch.table import read_rows
from rig.errors import RigError

TABLE_SUFFIXES = (".csv", ".jsonl", ".parquet")
CURVE_POINTS = 3000


def _f(v) -> float | None:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def _axis(values: list[float | None], index: list[int]) -> list[float]:
    """A grid axis in um: each index's place (the median of the rows there), or the index."""
    out = []
    for i in range(max(index) + 1 if index else 0):
        at = [v for v, j in zip(values, index, strict=True) if j == i and v is not None]
        out.append(round(float(np.median(at)) * 1e6, 4) if at else float("nan"))
    if any(math.isnan(v) for v in out):
        return [float(i) for i in range(len(out))]
    return out


class Maps:
    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self._rows: dict[str, tuple[tuple, list[dict]]] = {}
        self._lock = threading.Lock()

    def resolve(self, rel: str) -> Path:
        root = self.folder.resolve()
        path = (root / rel).resolve()
        if (root != path.parent and root not in path.parents) or path.suffix not in TABLE_SUFFIXES \
                or not path.is_file():
            raise RigError(f"no batch table {rel!r} in {self.folder}")
        return path

    def tables(self) -> list[dict]:
        """Tables in the folder (and one level down) that `--table` wrote: a request beside them."""
        out = []
        if not self.folder.is_dir():
            return out
        for path in sorted([*self.folder.glob("*"), *self.folder.glob("*/*")]):
            if path.suffix in TABLE_SUFFIXES and Path(str(path) + ".request.json").is_file():
                out.append({"table": str(path.relative_to(self.folder)), "bytes": path.stat().st_size})
        return out

    def rows(self, rel: str) -> list[dict]:
        path = self.resolve(rel)
        st = path.stat()
        key = (st.st_mtime_ns, st.st_size)
        with self._lock:
            hit = self._rows.get(str(path))
        if hit is not None and hit[0] == key:
            return hit[1]
        rows = read_rows(path)
        with self._lock:
            self._rows[str(path)] = (key, rows)
        return rows

    def request(self, rel: str) -> BatchRequest | None:
        path = Path(str(self.resolve(rel)) + ".request.json")
        try:
            asked = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
        known = {f.name for f in fields(BatchRequest)}
        kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in asked.items() if k in known}
        return BatchRequest(**kwargs)

    def map(self, rel: str) -> dict:
        t0 = time.perf_counter()
        rows = self.rows(rel)
        if not rows:
            raise RigError(f"{rel}: no rows")
        gx = [r.get("grid_x") for r in rows]
        gy = [r.get("grid_y") for r in rows]
        if any(v is None or _f(v) is None for v in gx + gy):
            n = math.ceil(math.sqrt(len(rows)))  # no grid in the table: rows in reading order
            gx, gy = [i % n for i in range(len(rows))], [i // n for i in range(len(rows))]
        gx, gy = [int(v) for v in gx], [int(v) for v in gy]
        nx, ny = max(gx) + 1, max(gy) + 1
        xs = _axis([_f(r.get("x_m")) for r in rows], gx)
        ys = _axis([_f(r.get("y_m")) for r in rows], gy)
        in_um = any(_f(r.get("x_m")) is not None for r in rows) and xs != [float(i) for i in range(nx)]

        def grid(value) -> list[list]:
            z: list[list] = [[None] * nx for _ in range(ny)]
            for i, r in enumerate(rows):
                z[gy[i]][gx[i]] = value(r)
            return z

        def kpa(r):
            v = _f(r.get("E_Pa"))
            return None if v is None else round(v / 1e3, 6)

        def height(r):
            v = _f(r.get("contact_point_m"))
            return None if v is None else round(v * 1e6, 6)

        def ratio(r):
            v = _f(r.get("rmse_over_noise"))
            return None if v is None else round(v, 4)

        def verdict(r):
            if r.get("error"):
                return None
            a = r.get("adequate")
            return 1 if a in (True, "True", "true", 1) else 0

        rowid = grid(lambda r: None)
        for i in range(len(rows)):
            rowid[gy[i]][gx[i]] = i
        req = self.request(rel)
        return {"table": rel, "rows": len(rows), "nx": nx, "ny": ny, "x_um": xs, "y_um": ys,
                "axes_unit": "um" if in_um else "grid index",
                "maps": {"E_kPa": grid(kpa), "contact_height_um": grid(height),
                         "rmse_over_noise": grid(ratio), "adequate": grid(verdict)},
                "row": rowid, "request": req.__dict__ if req else None,
                "failed": sum(1 for r in rows if r.get("error")),
                "adequate": sum(1 for r in rows if verdict(r) == 1),
                "seconds": round(time.perf_counter() - t0, 3)}

    def curve(self, rel: str, index: int) -> dict:
        """One curve of the table, fitted again as the batch fitted it."""
        from rig.analysis.fitting.fit import fit
        from rig.analysis.workflow.inputs import load_inputs
        from rig.analysis.workflow.report import contact_curve
        from rig.models.catalogue import build_model
        from rig.records import ReadOptions

        t0 = time.perf_counter()
        rows = self.rows(rel)
        if not 0 <= index < len(rows):
            raise RigError(f"{rel}: no row {index}")
        row = rows[index]
        base = {"row": index, "file": row.get("file"), "curve": row.get("curve"),
                "x_um": None if _f(row.get("x_m")) is None else _f(row.get("x_m")) * 1e6,
                "y_um": None if _f(row.get("y_m")) is None else _f(row.get("y_m")) * 1e6,
                "table_row": {k: v for k, v in row.items() if not k.startswith("_")}}
        if row.get("error"):
            return {**base, "error": f"this curve could not be analysed: {row['error']}"}
        req = self.request(rel)
        if req is None:
            return {**base, "error": f"no {rel}.request.json beside the table: what the batch asked is unknown"}
        curve = row.get("curve")
        curve = int(curve) if _f(curve) is not None else None
        options = ReadOptions(curve=curve, spring_constant_N_per_m=req.spring_constant_N_per_m,
                              sensitivity_m_per_V=req.sensitivity_m_per_V, block=req.block)
        file = Path(str(row["file"]))
        if not file.is_absolute() and not file.exists():  # named from where the batch ran: beside the table
            file = self.resolve(rel).parent / file
        records = None
        if curve is not None and not req.block:  # the one curve read from the file, as the batch reads
            from rig.records import each_record

            got = dict(each_record(str(file), options, {curve}))
            rec = got.get(curve, RigError(f"curve {curve} is no longer in {file}"))
            if isinstance(rec, Exception):
                return {**base, "error": f"curve {curve} cannot be read: {rec}"}
            records = [rec]
        inputs = load_inputs([str(file)], [], list(req.plugins), options, indenter=req.indenter,
                             poisson=req.poisson, segment=req.segment, records=records)
        model = build_model(req.model, list(req.add), inputs.registry)
        res = fit(model, inputs.trials)
        t = res.trials[0]
        c = contact_curve(res, 0)
        k_len, u_len = t.length_unit
        k_f, u_f = t.force_unit
        if c is None:  # no contact to measure from: against the travel
            d = np.asarray(t.motion.x_m)
            c = {"indentation_m": d, "separation_m": None, "force_N": t.force_N,
                 "model_N": res.predictions[0], "residual_N": res.residuals[0],
                 "branch": np.full(len(d), "approach"), "contact_travel_m": None}
        shift = float(c["indentation_m"][0] - np.asarray(t.motion.x_m)[0])  # the analysed travel to indentation
        every = max(1, math.ceil(len(c["indentation_m"]) / CURVE_POINTS))

        def col(a, scale=1.0, step=every) -> list:
            values = np.asarray(a, dtype=float)[::step]
            return [None if not math.isfinite(v) else round(float(v) / scale, 6) for v in values]

        out = {**base, "model": res.model.name, "segment": req.segment,
               "indentation_um": col(c["indentation_m"], 1e-6), "force": col(c["force_N"], k_f),
               "fit": col(c["model_N"], k_f), "residual": col(c["residual_N"], k_f),
               "branch": [str(v) for v in np.asarray(c["branch"])[::every]],
               "separation": c["separation_m"] is not None,
               "force_unit": u_f, "length_unit": u_len,
               "contact_point_um": None if c["contact_travel_m"] is None else c["contact_travel_m"] / 1e-6,
               "rmse_over_noise": _f(row.get("rmse_over_noise")), "adequate": row.get("adequate"),
               "effect": row.get("effect") or "", "E_kPa": None if _f(row.get("E_Pa")) is None
               else _f(row.get("E_Pa")) / 1e3, "length_scale": k_len}
        out.update(self._retract(records[0] if records else None, t, shift, col, k_f))
        out["seconds"] = round(time.perf_counter() - t0, 3)
        return out

    @staticmethod
    def _retract(rec, t, shift_m: float, col, k_f: float) -> dict:
        """The record's retract (which an approach fit leaves out), on the fit's indentation axis:
        the analysed approach is the raw approach turned and shifted (`prepare` flips the signs so
        that loading is positive and counts the travel from contact), and that same turn and shift,
        read off the approach's samples, carries the raw retract onto the axis (`shift_m` then
        moves it from the analysed travel to the indentation past the fitted contact point)."""
        from rig.analysis.trials.data import approach_only

        if rec is None:
            return {"retract_note": "the retract is drawn only for a curve read on its own"}
        try:
            app = approach_only(rec, rec.name)
        except RigError:
            return {"retract_note": "the record has no approach to place its retract by"}
        end = int(np.flatnonzero(rec.t_s == app.t_s[-1])[-1]) + 1
        if end >= rec.n:
            return {"retract_note": "the record has no retract"}
        tp = np.asarray(t.motion.t_s, dtype=float) - float(app.t_s[0])
        ta = np.asarray(app.t_s, dtype=float) - float(app.t_s[0])
        inside = (tp >= 0) & (tp <= ta[-1])
        turn = {}
        for name, raw, analysed in (("x", app.position_m, t.motion.x_m), ("f", app.force_N, t.force_N)):
            r = np.interp(tp[inside], ta, np.asarray(raw, dtype=float))
            a = np.asarray(analysed, dtype=float)[inside]
            ok = np.isfinite(r) & np.isfinite(a)
            if ok.sum() < 10 or np.ptp(r[ok]) <= 0:
                return {"retract_note": "the retract could not be put on the fit's axis"}
            slope, icpt = np.polyfit(r[ok], a[ok], 1)
            if abs(abs(slope) - 1.0) > 0.02:  # not a turn and a shift: said, not drawn wrong
                return {"retract_note": "the retract could not be put on the fit's axis"}
            turn[name] = (float(round(slope)), float(icpt))
        (sx, bx), (sf, bf) = turn["x"], turn["f"]
        x = sx * np.asarray(rec.position_m[end:], dtype=float) + bx + shift_m
        f = sf * np.asarray(rec.force_N[end:], dtype=float) + bf
        step = max(1, math.ceil(len(x) / CURVE_POINTS))
        return {"retract_indentation_um": col(x, 1e-6, step), "retract_force": col(f, k_f, step)}
