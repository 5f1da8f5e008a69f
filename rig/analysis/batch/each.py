"""`rig analyze --each`: every curve of every input analysed on its own, a table, a summary.

The Python API for notebooks is `analyze_curves` (a pandas DataFrame, one row per curve) and
`on_grid` (an xarray Dataset on a map's grid); both run the same batch as the command line:

    >>> from rig.analysis.batch.each import analyze_curves, on_grid
    >>> df = analyze_curves(["map.jpk-force-map"], model="hertz", indenter="paraboloid:R=10um",
    ...                     segment="approach")
    >>> df[["curve", "x_m", "y_m", "E_Pa", "E_Pa_stat", "E_Pa_sys", "adequate"]]
    >>> grid = on_grid(df)          # grid["E_Pa"].plot() draws the map
"""

from __future__ import annotations

import math
import statistics
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from rig.analysis.batch.engine import BatchRequest, Curve, expand_inputs, key_of, plan, row_order, run
from rig.analysis.batch.table import Journal, columns, journal_of, read_rows, table_format, write_table
from rig.errors import RigError
from rig.progress import Progress

__all__ = ["EachResult", "analyze_curves", "format_summary", "on_grid", "run_each"]


@dataclass
class EachResult:
    """What a batch did: its table's rows, the curves analysed this time, the rows kept from an earlier run
    (resumed) and from curves not given this time (others), the inputs skipped as not records, the table's
    path and the wall time."""

    rows: list[dict]
    curves: int
    resumed: int = 0  # rows kept from an earlier run (--resume)
    seconds: float = 0.0
    table: str | None = None
    skipped: list[str] = field(default_factory=list)  # files in the folders given that are not records
    others: int = 0  # rows of the table for curves not given this time, kept

    @property
    def analysed(self) -> list[dict]:
        """The rows of this batch's curves (not the table's others)."""
        return self.rows[:len(self.rows) - self.others] if self.others else self.rows

    @property
    def failed(self) -> list[dict]:
        return [r for r in self.rows if r.get("error")]


def run_each(inputs: list[str], req: BatchRequest, *, table: str | None = None, resume: bool = False,
             workers: int | None = None, scheduler: str | None = None, progress: bool = True) -> EachResult:
    """Plan, skip what an earlier run of `table` did (`resume`), analyse the rest, write the table."""
    t0 = time.monotonic()
    table = str(table) if table is not None else None
    if table:
        table_format(table)
        if not resume and (Path(table).exists() or journal_of(table).exists()):
            raise RigError(f"--table {table}: the file (or an interrupted batch's rows beside it) already "
                           "exists: --resume to finish it, or remove it")
        _same_request(table, req, resume)
    skipped: list[str] = []
    files = expand_inputs(inputs, skipped)
    curves = plan(files, req)  # a file named that cannot be opened is one row that says why
    order = row_order(curves)
    done: dict[tuple[str, str], dict] = {}
    others: list[dict] = []  # rows of the table for curves not given this time: kept
    if table and resume:
        for r in read_rows(table):
            k = key_of(r)
            if k in order:
                done[k] = r
            elif all(key_of(o) != k for o in others):
                others.append(r)
    todo = [c for c in curves if c.key not in done]
    # the table stays until the new one replaces it; the journal, started at the first new rows,
    # holds every row done so far (the earlier ones copied in), so a kill loses nothing
    journal = Journal(table, [*done.values(), *others]) if table else None
    shown = Progress(len(todo)) if progress and todo else None
    finished = False
    try:
        for rows in run(todo, req, workers=workers, scheduler=scheduler):
            for r in rows:
                done[key_of(r)] = r
            if journal:
                journal.add(rows)
            if shown:
                shown.add(len(rows))
        finished = True
    finally:
        if shown:
            shown.close()  # a terminal's line left open by a run that stopped short
        if journal:
            journal.close()
    rows = sorted(done.values(), key=lambda r: order[key_of(r)]) + others
    if table and finished:
        write_table(rows, table)
        journal.path.unlink(missing_ok=True)  # the table holds them all now
    return EachResult(rows, len(curves), len(curves) - len(todo), time.monotonic() - t0, table,
                      skipped, len(others))


def _same_request(table: str, req: BatchRequest, resume: bool) -> None:
    """What was asked of a table's curves is kept beside it (`OUT.request.json`): a resumed batch
    that asks something else would mix two analyses in one table, and is refused."""
    import json

    path = Path(table + ".request.json")
    asked = json.loads(json.dumps(asdict(req)))
    if resume and path.exists():
        try:
            before = json.loads(path.read_text())
        except (OSError, ValueError):
            before = None
        if isinstance(before, dict) and before != asked:
            what = ", ".join(f"{k} {before.get(k)!r} then, {v!r} now" for k, v in asked.items()
                             if before.get(k) != v)
            raise RigError(f"--resume {table}: its rows were made with other settings ({what}): give the same "
                           "ones, or a new --table")
    path.write_text(json.dumps(asked, indent=1) + "\n")


def parameters(rows: list[dict]) -> list[str]:
    """The fitted parameters' columns (not their errors), in table order."""
    from rig.analysis.batch.table import PLACE, TAIL

    return [c for c in columns(rows) if c not in PLACE and c not in TAIL and not c.endswith(("_stat", "_sys"))]


def _n(count: int, what: str) -> str:
    return f"{count} {what}" if count == 1 else f"{count} {what}s"


def passes(r: dict, min_quality: float | None) -> bool:
    """Whether a row counts at `min_quality` (None: every row does): an analysed curve rated at
    least that (rig.analysis.batch.quality)."""
    if min_quality is None:
        return True
    q = r.get("quality")
    try:
        return not r.get("error") and float(q) >= min_quality
    except (TypeError, ValueError):
        return False


def format_summary(res: EachResult, req: BatchRequest, min_quality: float | None = None) -> str:
    """The batch's summary; with `min_quality`, its statistics over the curves rated at least
    that (the counts of curves analysed and failed stay the batch's)."""
    rows = res.analysed
    ok = [r for r in rows if not r.get("error")]
    analysed = len(ok)
    if min_quality is not None:
        ok = [r for r in ok if passes(r, min_quality)]
    files = len({r["file"] for r in rows})
    new = len(rows) - res.resumed
    lines = [f"{_n(res.curves, 'curve')} from {_n(files, 'file')}, model {req.model}"
             + (f" (+{', +'.join(req.add)})" if req.add else "")
             + f": {analysed} analysed, {len(res.failed)} could not be"
             + (f"; {res.resumed} kept from the earlier run" if res.resumed else "")
             + (f"; {res.seconds:.1f} s ({_n(new, 'curve')} at {new / max(res.seconds, 1e-9):.3g}/s)" if new
                else "; nothing left to do")]
    if res.others:
        lines.append(f"  the table also keeps {_n(res.others, 'row')} of curves not given this time")
    if res.skipped:
        shown = ", ".join(Path(f).name for f in res.skipped[:6]) + (", ..." if len(res.skipped) > 6 else "")
        lines.append(f"  skipped {_n(len(res.skipped), 'file')} in the folders given that are not records: "
                     f"{shown}")
    if min_quality is not None:
        qs = [float(r["quality"]) for r in rows if not r.get("error") and r.get("quality") not in (None, "")]
        left = analysed - len(ok)
        lines.append(f"  quality >= {min_quality:g} (of 10): {len(ok)} of {analysed} curves kept for the "
                     f"statistics below and the report ({left} left out; the table keeps them all)"
                     + (f"; quality median {statistics.median(qs):.3g}" if qs else ""))
    read = sum(r.get("_read_s", 0.0) for r in rows)
    fitted = sum(r.get("_fit_s", 0.0) for r in rows)
    if read + fitted > 0:
        lines.append(f"  time in the workers: reading {read:.3g} s ({100 * read / (read + fitted):.0f} %), "
                     f"analysing {fitted:.3g} s ({100 * fitted / (read + fitted):.0f} %)")
    for p in parameters(ok):
        vals = [r[p] for r in ok if isinstance(r.get(p), int | float) and math.isfinite(r[p])]
        if len(vals) >= 1:
            q = statistics.quantiles(vals, n=4) if len(vals) >= 2 else [vals[0]] * 3
            lines.append(f"  {p:<28} median {statistics.median(vals):.4g}, quartiles {q[0]:.4g} to {q[2]:.4g} "
                         f"({_n(len(vals), 'curve')})")
    if ok:
        adequate = sum(1 for r in ok if r.get("adequate") in (True, "True"))
        lines.append(f"  adequate (residual at the noise): {adequate} of {len(ok)}")
    if req.explain and ok:
        named = Counter(r["effect"] for r in ok if r.get("effect"))
        if named:
            effect, n = named.most_common(1)[0]
            where = [_where(r, files > 1) for r in ok if r.get("effect") == effect]
            lines.append(f"  most often missing: {effect}, on {n} of {len(ok)} curves ("
                         + ", ".join(where[:8]) + (", ..." if len(where) > 8 else "") + ")"
                         + "".join(f"; {e}: {k}" for e, k in named.most_common()[1:4]))
        else:
            lines.append("  no effect named missing on any curve")
    for r in [r for r in rows if r.get("error")][:10]:
        lines.append(f"  could not analyse {_where(r, True)}: {r['error']}")
    if len(res.failed) > 10:
        lines.append(f"  ... and {len(res.failed) - 10} more (the table's `error` column says why)")
    if res.table:
        lines.append(f"table: {res.table}")
    return "\n".join(lines)


def _where(r: dict, file: bool = False) -> str:
    """The curve as a person finds it: its number and place on the map, and its file where the
    batch has several."""
    name = Path(str(r["file"])).name
    place = f"curve {r['curve']}" if r.get("curve") not in (None, "") else name
    if r.get("grid_x") not in (None, "") and r.get("grid_y") not in (None, ""):
        place += f" at ({r['grid_x']}, {r['grid_y']})"
    return f"{name} {place}" if file and r.get("curve") not in (None, "") else place


def format_rows(rows: list[dict], most: int = 100) -> str:
    """A short table a person reads, for a few curves."""
    ps = parameters(rows)
    several = len({r["file"] for r in rows}) > 1
    head = f"{'curve':<28}" + "".join(f"{p:>14}" for p in ps) + f"{'RMSE/noise':>12}  verdict"
    out = [head]
    for r in rows[:most]:
        if r.get("error"):
            out.append(f"{_where(r, several):<28}  could not analyse: {r['error']}")
            continue
        vals = "".join(f"{_num(r.get(p)):>14}" for p in ps)
        verdict = "adequate" if r.get("adequate") in (True, "True") else "NOT adequate"
        if r.get("effect"):
            verdict += f"; missing: {r['effect']}"
        out.append(f"{_where(r, several):<28}{vals}{_num(r.get('rmse_over_noise')):>12}  {verdict}")
    if len(rows) > most:
        out.append(f"... {len(rows) - most} more (--table OUT.csv writes them all)")
    return "\n".join(out)


def _num(v: Any) -> str:
    if isinstance(v, int | float) and not isinstance(v, bool):
        return f"{v:.4g}"
    return "" if v is None else str(v)


def analyze_curves(inputs: list[str] | str, *, model: str = "hertz", add: list[str] | None = None,
                   indenter: str | None = None, poisson: float = 0.5, segment: str = "approach",
                   explain: bool = False, spring_constant_N_per_m: float | None = None,
                   sensitivity_m_per_V: float | None = None, workers: int | None = None,
                   scheduler: str | None = None, table: str | None = None, resume: bool = False,
                   progress: bool = True):
    """Every curve of `inputs` (files, folders, globs) analysed on its own, as a pandas DataFrame
    with the columns of `rig analyze --each --table` (pandas is needed: `indentation-rig[table]`)."""
    try:
        import pandas as pd
    except ImportError:
        raise RigError("analyze_curves returns a pandas DataFrame: "
                       "pip install 'indentation-rig[table]'") from None
    req = BatchRequest(model=model, add=tuple(add or ()), explain=explain, indenter=indenter, poisson=poisson,
                       segment=segment, spring_constant_N_per_m=spring_constant_N_per_m,
                       sensitivity_m_per_V=sensitivity_m_per_V)
    res = run_each([inputs] if isinstance(inputs, str) else list(inputs), req, table=table, resume=resume,
                   workers=workers, scheduler=scheduler, progress=progress)
    cols = columns(res.rows)
    return pd.DataFrame([{c: r.get(c) for c in cols} for r in res.rows], columns=cols)


def on_grid(df) -> Any:
    """A map's rows on its grid: an xarray Dataset over (grid_y, grid_x) with every numeric column
    and x_m, y_m as coordinates where the instrument gave them (xarray is needed)."""
    try:
        import xarray as xr
    except ImportError:
        raise RigError("on_grid returns an xarray Dataset: pip install xarray") from None
    g = df.dropna(subset=["grid_x", "grid_y"])
    if g.empty:
        raise RigError("these curves carry no grid position (not a map)")
    g = g.astype({"grid_x": int, "grid_y": int}).set_index(["grid_y", "grid_x"])
    numeric = [c for c in g.columns if c != "file" and g[c].dtype.kind in "fiub"]
    return xr.Dataset.from_dataframe(g[numeric])


def is_batch(inputs: list[str], curve: int | None, each: bool, options: Any = None) -> bool:
    """Whether `rig analyze` analyses curve by curve: --each; a folder or a glob; or one file of
    many curves given alone without --curve."""
    if each:
        return True
    if any(Path(i).is_dir() or (not Path(i).exists() and _magic(i)) for i in inputs):
        return True
    if len(inputs) == 1 and curve is None:
        from rig.records.afm import count_curves, format_of

        try:
            format_of(inputs[0])
        except (RigError, OSError):
            return False  # not an AFM file: one record
        # an AFM file that cannot be listed with these options says why here (exit 2), not as a
        # batch's failed row or a refusal of --table
        return count_curves(inputs[0], options) > 1
    return False


def _magic(name: str) -> bool:
    import glob

    return glob.has_magic(name)


__all__ += ["Curve", "format_rows", "is_batch"]
