"""Many curves, one analysis each: every curve of a force map, every file of a folder.

A unit of work is one curve: a file and, for a file of many (an AFM map or QI series), the
curve's number as the instrument numbers it. Each is analysed exactly as `rig analyze` analyses
one record (`rig.analysis.workflow.session.analyze`, the record already read), and gives one row: where
it was taken, every parameter with its standard error, the contact point, the error over the
noise, the verdict and, for a curve that could not be analysed, why.

Curves go to workers in chunks of neighbours (a worker opens each file once per chunk); the
workers are local processes (`concurrent.futures`), or a Dask distributed cluster when a
scheduler's address is given (`rig[cluster]`). A curve's row depends on that curve alone: the
table is the same whatever the order the curves were done in and however many workers did
them (rows are put back in the order of the inputs and, within a file, of its curves).
"""

from __future__ import annotations

import contextlib
import glob
import math
import multiprocessing
import os
import time
from collections.abc import Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from rig.errors import RigError

__all__ = ["BatchRequest", "Curve", "analyze_chunk", "expand_inputs", "plan", "row_order", "run"]

SINGLE_CURVE = (".jpk-force",)  # files that hold one curve by their format's definition
CHUNKS_PER_WORKER = 4  # enough to keep every worker busy to the end, few enough to open each file rarely
MAX_CHUNK = 64


@dataclass(frozen=True)
class Curve:
    """One unit of work: a file, the curve's number in it (None: a file of one record), and where
    the curve was taken (on the sample, in m, and on the map's grid), when the file says."""

    file: str
    curve: int | None = None  # an AFM file's curve; a Mach-1 file's data block (from 1)
    x_m: float | None = None
    y_m: float | None = None
    grid_x: int | None = None
    grid_y: int | None = None
    block: bool = False  # `curve` is a Mach-1 data block

    @property
    def key(self) -> tuple[str, str]:
        """The file as a resolved path (the same file however it was named) and the curve."""
        return _key(self.file, self.curve)


@dataclass(frozen=True)
class BatchRequest:
    """What every curve is asked: the same as `rig analyze` of one record (see AnalyzeRequest)."""

    model: str = "proposed"
    add: tuple[str, ...] = ()
    plugins: tuple[str, ...] = ()
    explain: bool = False
    indenter: str | None = None
    poisson: float = 0.5
    segment: str = "auto"
    spring_constant_N_per_m: float | None = None
    sensitivity_m_per_V: float | None = None
    block: int | None = None


OWN_FILES = (".request.json", ".partial.jsonl")


def expand_inputs(inputs: list[str], skipped: list[str] | None = None) -> list[str]:
    """Files named, found by a glob, or held in a folder (its files, recursively, in name order;
    hidden ones left out). A file named is taken as it is (its row says if it cannot be read);
    one found in a folder or by a glob only if it is a record this tool reads (a folder also
    holds pictures, notes, truth files and tables): the others are listed in `skipped`. One clear
    error for a name that is none of them."""
    from rig.records import recognised

    out: list[str] = []
    for name in inputs:
        p = Path(name)
        if p.is_dir():
            found = sorted(str(f) for f in p.rglob("*") if f.is_file() and not any(
                part.startswith(".") for part in f.relative_to(p).parts))
            if not found:
                raise RigError(f"{name}: an empty folder")
        elif p.is_file():
            out.append(name)
            continue
        elif glob.has_magic(name):
            found = sorted(f for f in glob.glob(name, recursive=True) if Path(f).is_file())
            if not found:
                raise RigError(f"{name}: no file matches")
        else:
            raise RigError(f"{name}: no such file or folder")
        for f in found:
            if f.endswith(OWN_FILES):
                continue  # a table's own journal and request, written beside it
            if recognised(f):
                out.append(f)
            elif skipped is not None:
                skipped.append(f)
    seen: set[str] = set()
    return [f for f in out if not (f in seen or seen.add(f))]


def plan(files: list[str], req: BatchRequest) -> list[Curve]:
    """Every curve of `files`, in order: an AFM file gives one unit per curve (numbered as the
    instrument numbers it, placed as its metadata says), any other file one unit. A file that
    cannot be opened is one unit, whose row will say why."""
    from rig.records import ReadOptions, list_curves
    from rig.records.afm import curve_numbers, format_of
    from rig.records.mach1 import count_blocks, looks_like_mach1

    options = ReadOptions(spring_constant_N_per_m=req.spring_constant_N_per_m,
                          sensitivity_m_per_V=req.sensitivity_m_per_V)
    out: list[Curve] = []
    for f in files:
        try:
            format_of(f)
        except (RigError, OSError):
            if req.block is None and looks_like_mach1(_head(f)):
                n = count_blocks(Path(f))  # one block per site or test function
                out += [Curve(f, b, block=True) for b in range(1, n + 1)] if n > 1 else [Curve(f)]
            else:
                out.append(Curve(f))  # one record
            continue
        if f.lower().endswith(SINGLE_CURVE):
            # a JPK force file holds one curve, numbered 0: opening it here to learn so cost a
            # folder of them a sixth of its time, serially before any worker started (64 ms a
            # file, half of reading it); its place is read by the worker with the curve (`_placed`)
            out.append(Curve(f, 0))
            continue
        try:
            nums = curve_numbers(f, options)
            if nums is not None:
                # an HDF5 map's places are read by the workers with each curve (`_placed`)
                out += [Curve(f, i) for i in nums]
                continue
            infos = list_curves(f, options)
        except RigError:
            out.append(Curve(f))
            continue
        out += [Curve(f, i.enum, i.x_m, i.y_m, i.grid_x, i.grid_y) for i in infos]
    return out


def _head(path: str) -> str:
    try:
        with open(path, "rb") as fh:
            return fh.read(4096).decode("utf-8", errors="replace")
    except OSError:
        return ""


def chunks(curves: list[Curve], workers: int) -> list[list[Curve]]:
    """Neighbouring curves of one file together, about CHUNKS_PER_WORKER chunks per worker."""
    size = max(1, min(MAX_CHUNK, math.ceil(len(curves) / max(1, workers * CHUNKS_PER_WORKER))))
    out: list[list[Curve]] = []
    for c in curves:
        if out and len(out[-1]) < size and out[-1][-1].file == c.file:
            out[-1].append(c)
        else:
            out.append([c])
    return out


def analyze_chunk(chunk: list[Curve], req: BatchRequest) -> list[dict]:
    """The rows of a chunk of curves (of one file: `chunks` never mixes files). Never raises
    for a curve: a curve that cannot be read or fitted gets a row that says why."""
    import warnings

    from rig.records import ReadOptions, Record, each_record, read_record

    options = ReadOptions(spring_constant_N_per_m=req.spring_constant_N_per_m,
                          sensitivity_m_per_V=req.sensitivity_m_per_V, block=req.block)
    rows: list[dict] = []
    with warnings.catch_warnings(), _one_blas_thread():
        warnings.simplefilter("ignore")  # what a curve's fit warns of is in its row
        if chunk[0].curve is not None and not chunk[0].block:
            wanted = {c.curve: c for c in chunk}
            t0 = time.perf_counter()
            try:
                got = dict(each_record(chunk[0].file, options, set(wanted)))
            except (RigError, OSError) as exc:
                return [_failed(c, exc) for c in chunk]
            read_s = (time.perf_counter() - t0) / len(wanted)  # one load of the file, shared
            unplaced = {n for n, c in wanted.items() if c.x_m is None and c.grid_x is None
                        and not isinstance(got.get(n), Record)}
            places = _places(chunk[0].file, unplaced)
            for n, c in wanted.items():
                rec = got.get(n, RigError(f"curve {n} is no longer in the file"))
                if isinstance(rec, Exception):
                    rows.append(_failed(_placed(c, places.get(n)), rec))
                else:
                    rows.append(_analyze(_placed(c, rec.meta), rec, req, read_s))
        else:
            for c in chunk:
                t0 = time.perf_counter()
                try:
                    rec = read_record(c.file, replace(options, block=c.curve) if c.block else options)
                except (RigError, OSError) as exc:
                    rows.append(_failed(c, exc))
                    continue
                rows.append(_analyze(c, rec, req, time.perf_counter() - t0))
    return rows


def _placed(c: Curve, where: Any) -> Curve:
    """`c` with its place on the sample and the grid, when the plan left it to the worker: from
    the curve's record (`Record.meta`) or, for a curve that could not be read, its `CurveInfo`."""
    if c.x_m is not None or c.grid_x is not None or where is None:
        return c
    if isinstance(where, dict):
        grid = where.get("grid_index") or (None, None)
        return replace(c, x_m=where.get("x_m"), y_m=where.get("y_m"), grid_x=grid[0], grid_y=grid[1])
    return replace(c, x_m=where.x_m, y_m=where.y_m, grid_x=where.grid_x, grid_y=where.grid_y)


def _places(file: str, curves: set[int]) -> dict:
    """The places of an HDF5 map's curves that could not be read (nothing to read otherwise)."""
    if not curves:
        return {}
    from rig.records.afm import HDF5, format_of, hdf5_places

    try:
        return hdf5_places(file, curves) if format_of(file) is HDF5 else {}
    except (RigError, OSError):
        return {}


def _one_blas_thread():
    """The linear algebra on one thread while a chunk is analysed: the batch already keeps every
    core busy with its own processes, and a curve's products are small, so the library's
    threads only wait on each other (a tenth of a curve's time in one least-squares call of the
    adequacy limits, on a loaded machine). The same numbers either way; threadpoolctl, where
    installed, sets it."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(1, user_api="blas")


def _analyze(c: Curve, rec: Any, req: BatchRequest, read_s: float) -> dict:
    """The row of one curve already read. Its time reading and analysing go in the private
    columns `_read_s` and `_fit_s` (for the batch's summary; never in the table: a table does
    not depend on how fast the machine was)."""
    from rig.analysis.workflow.session import AnalyzeRequest, analyze

    t0 = time.perf_counter()
    try:
        out = analyze(AnalyzeRequest(
            [c.file], model=req.model, add=list(req.add), plugins=list(req.plugins), explain=req.explain,
            indenter=req.indenter, poisson=req.poisson, segment=req.segment, records=[rec], row_only=True)).json
    except RigError as exc:
        return _failed(c, exc)
    except Exception as exc:  # noqa: BLE001 (a curve the analysis cannot handle must not end the batch)
        return _failed(c, exc, internal=True)
    row = _place(c)
    for name, p in out["parameters"].items():
        row[name] = p["value"]
        row[f"{name}_stat"] = p["stderr"] if p["determined"] else math.inf
        if "sys" in p:
            row[f"{name}_sys"] = p["sys"]
    m = out.get("material") or {}
    placed = out["records"][0]
    if "contact_point_m" in placed:
        row["contact_point_m"] = placed["contact_point_m"]
        row["contact_point_m_stat"] = placed.get("contact_point_m_stderr")
        row["contact_point_m_sys"] = m.get("contact_point_m_sys")
    if m:
        row["E_Pa"], row["E_Pa_stat"], row["E_Pa_sys"] = m["E_Pa"], m["E_Pa_stat"], m.get("E_Pa_sys")
        row["segment"] = m.get("segment")
        row["caveats"] = "; ".join(m.get("caveats", []))
    fit = out["fit"]
    row.update(rmse_N=fit["rmse_N"], noise_N=fit["noise_N"], rmse_over_noise=fit["rmse_over_noise"],
               adequate=out["adequate"])
    if req.explain:
        d = out.get("diagnosis") or {}
        row["effect"] = d.get("best") or ""
        row["effect_dbic"] = next((s["delta_bic"] for s in out.get("suggestions", [])
                                   if s["effect"] == d.get("best")), None)
    from rig.analysis.batch.quality import describe, rate

    row["quality"], parts = rate(out, row.get("effect") or "")
    row["quality_parts"] = describe(parts)
    row.update(error="", _read_s=read_s, _fit_s=time.perf_counter() - t0)
    return row


def _place(c: Curve) -> dict:
    return {"file": c.file, "curve": c.curve, "x_m": c.x_m, "y_m": c.y_m, "grid_x": c.grid_x,
            "grid_y": c.grid_y}


def _failed(c: Curve, exc: BaseException, internal: bool = False) -> dict:
    why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    why = why.removeprefix(f"{c.file}: ")  # the row already names the file
    if internal:
        why = f"internal error ({type(exc).__name__}): {why}"
    return {**_place(c), "error": why}


def row_order(curves: Iterable[Curve]) -> dict[tuple[str, str], int]:
    """Each curve's place in the table: rows are written in the order the curves were planned, whichever
    worker finished first."""
    return {c.key: i for i, c in enumerate(curves)}


def key_of(row: dict) -> tuple[str, str]:
    """A row's key, as its curve's (`Curve.key`); a table read back gives its numbers as text."""
    curve = row.get("curve")
    return _key(str(row["file"]), None if curve in (None, "") else int(float(curve)))


def _key(file: str, curve: int | None) -> tuple[str, str]:
    return str(Path(file).resolve()), "" if curve is None else str(curve)


def run(curves: list[Curve], req: BatchRequest, *, workers: int | None = None,
        scheduler: str | None = None) -> Iterator[list[dict]]:
    """Analyse `curves`, giving each chunk's rows as it is done (in whatever order they finish):
    on local processes (`workers`, default every core), or on the Dask cluster at `scheduler`."""
    if not curves:
        return
    workers = max(1, workers or os.cpu_count() or 1)
    parts = chunks(curves, workers)
    if scheduler:
        yield from _on_dask(parts, req, scheduler)
        return
    if workers == 1 or len(parts) == 1:
        for part in parts:
            yield analyze_chunk(part, req)
        return
    # workers start afresh (not forked): a forked worker would share the parent's open files, and
    # afmformats keeps a map's archive open to read its curves lazily
    ctx = multiprocessing.get_context("forkserver")
    with ProcessPoolExecutor(max_workers=min(workers, len(parts)), mp_context=ctx) as pool:
        futures = []
        try:
            futures.extend(pool.submit(analyze_chunk, part, req) for part in parts)
            for f in as_completed(futures):
                yield f.result()
        except BrokenProcessPool as exc:
            # analyze_chunk never raises: a worker that died is one that could not start, most
            # often a script run without the main guard (each worker imports it again)
            raise RigError("the worker processes could not start (a script that analyses curves in "
                           "parallel must keep its own code under `if __name__ == \"__main__\":`, as "
                           "Python's multiprocessing re-imports it in every worker; or pass workers=1)"
                           ) from exc
        finally:
            for f in futures:
                f.cancel()


def _on_dask(parts: list[list[Curve]], req: BatchRequest, scheduler: str) -> Iterator[list[dict]]:
    try:
        from distributed import Client
        from distributed import as_completed as dask_completed
    except ImportError:
        raise RigError("--scheduler needs Dask distributed: pip install 'indentation-rig[cluster]'") from None
    try:
        client = Client(scheduler, timeout="5s")  # a scheduler on the lab's network answers at once
    except (OSError, TimeoutError) as exc:
        raise RigError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})") from None
    try:
        futures = client.map(analyze_chunk, parts, req=req, pure=False)
        for f in dask_completed(futures):
            yield f.result()
    finally:
        client.close()
