"""CSV files: the rig's own (t_s,position_mm,force_N) and researchers' files whose column
names carry their units (`t_ms`, `position_um`, `indentation_nm`, `force_nN`, `load_mN`,
`force_gf`, `strain`...)."""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rig.errors import SpecError
from rig.records.record import Record
from rig.records.units import quantity, split_header, to_si
from rig.specs.frames import Frame

CANONICAL = ("t_s", "position_mm", "force_N")


def looks_like_csv(head: str) -> bool:
    """A table: its first line has commas and either names a time, length, force or strain
    column (a misspelt or missing one is then an error naming the columns) or is numbers. Prose
    with a comma in its first line ("lab notes, not a measurement") is not a table."""
    first = next((ln for ln in head.splitlines() if ln.strip()), "")
    if "," not in first or first.lstrip().startswith(("#", "<")):
        return False
    cells = [c.strip().strip('"') for c in first.split(",")]
    return any(quantity(split_header(c)[0]) or quantity(c.replace(" ", "_").split("_")[0]) for c in cells) \
        or all(_is_number(c) for c in cells if c)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def pick_columns(header: list[str], where: str) -> dict[str, tuple[int, float, str]]:
    """Which column is time, length and force, with the factor to SI and the written unit."""
    found: dict[str, tuple[int, float, str]] = {}
    for i, h in enumerate(header):
        name, unit = split_header(h)
        kind = quantity(name)
        if kind is None and unit is not None:
            kind = quantity(h.replace(" ", "_").split("_")[0])
        if kind is None or kind in found:
            continue
        if kind == "strain":
            if "length" not in found:
                found["length"] = (i, to_si(h, "strain", unit, where), unit or "1")
            continue
        if kind == "length" and "length" in found and header[found["length"][0]].lower().startswith("strain"):
            found["length"] = (i, to_si(h, kind, unit, where), unit or "")
            continue
        found[kind] = (i, to_si(h, kind, unit, where), unit or "")
    missing = [k for k in ("time", "length", "force") if k not in found]
    if missing:
        want = {"time": "t_s", "length": "position_mm", "force": "force_N"}
        raise SpecError(f"missing column(s) {', '.join(want[k] for k in missing)} (a time, a position or "
                        "indentation, and a force column, each with its unit, e.g. t_s,position_mm,force_N "
                        "or t_ms,indentation_um,force_nN)", path=where, line=1)
    return found


@dataclass
class CsvColumns:
    """A CSV's time, length and force columns in SI, as written (checked, not yet interpreted)."""

    t_s: np.ndarray
    length_m: np.ndarray
    force_N: np.ndarray
    kinds: np.ndarray | None  # the rig's own step_kind column, when there is one
    length_header: str
    units: dict[str, str]


def read_csv_record(path: str | Path) -> Record:
    """A CSV file as a Record: the rig's own samples (`rig replay --csv`), their zero the surface and their
    steps the phases; or any table with time, position and force columns in named units."""
    c = read_csv_columns(path)
    if c.kinds is not None:
        # the rig's own samples (`rig replay --csv`): its zero is the surface and its steps are the phases
        keep = ~np.isin(c.kinds, ["tare", "fault", "done"])
        return Record(Path(path).name, "csv", c.t_s[keep], c.length_m[keep], c.force_N[keep],
                      frame=Frame.SURFACE, steps=c.kinds[keep], baseline_force_N=c.force_N[c.kinds == "tare"],
                      **c.units)
    # an indentation is counted from the surface; a position may start anywhere (contact is found)
    surface = split_header(c.length_header)[0].lower().startswith("indentation")
    return Record(Path(path).name, "csv", c.t_s, c.length_m, c.force_N,
                  frame=Frame.SURFACE if surface else None, **c.units)


def read_csv_trial(path: str | Path) -> dict[str, np.ndarray]:
    """A trial CSV's time, position and force in the rig's units (s, mm, N), every row."""
    c = read_csv_columns(path)
    return {"t_s": c.t_s, "position_mm": c.length_m * 1e3, "force_N": c.force_N}


def read_csv_columns(path: str | Path) -> CsvColumns:
    """The time, position and force columns of a CSV file (and the step of each row for the rig's own), by
    their names and units; SpecError naming the file, line and column for anything it cannot read."""
    where = str(path)
    try:
        fh = open(path, newline="", encoding="utf-8-sig")  # noqa: SIM115
    except OSError as exc:
        raise SpecError(f"cannot open CSV: {exc.strerror or exc}", path=where) from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise SpecError("file is empty", path=where, line=1) from None
        except (csv.Error, UnicodeDecodeError) as exc:
            raise SpecError(f"not a readable CSV ({exc})", path=where, line=1) from None
        cols = pick_columns(header, where)
        idx = [cols[k][0] for k in ("time", "length", "force")]
        rows: list[list[float]] = []
        kinds: list[str] = []
        i_kind = header.index("step_kind") if "step_kind" in header else None
        fast = _fast_rows(fh, idx, i_kind)
        if fast is not None:
            rows, kinds = fast
            reader = iter(())
        else:  # something is wrong somewhere: read row by row to say where
            fh.seek(0)
            reader = csv.reader(fh)
            next(reader)
        try:
            for line_no, row in enumerate(reader, start=2):
                if not row or all(not c.strip() for c in row):
                    continue
                if i_kind is not None:
                    kinds.append(row[i_kind].strip() if i_kind < len(row) else "")
                try:
                    values = [float(row[i]) for i in idx]
                except IndexError:
                    raise SpecError(f"row has {len(row)} fields, header has {len(header)}",
                                    path=where, line=line_no) from None
                except ValueError:
                    bad = next(i for i in idx if not _is_float(row[i]))
                    raise SpecError(f"column {header[bad]}: '{row[bad]}' is not a number",
                                    path=where, line=line_no) from None
                if not all(np.isfinite(values)):
                    col = header[idx[[np.isfinite(v) for v in values].index(False)]]
                    raise SpecError(f"column {col} is NaN or infinite", path=where, line=line_no)
                rows.append(values)
        except (csv.Error, UnicodeDecodeError) as exc:
            raise SpecError(f"not a readable CSV ({exc})", path=where) from None
    if len(rows) < 2:
        raise SpecError("fewer than two data rows", path=where)
    arr = np.array(rows)
    t = arr[:, 0] * cols["time"][1]
    check_time(t, header[idx[0]], where, first_line=2)
    x = arr[:, 1] * cols["length"][1]
    f = arr[:, 2] * cols["force"][1]
    units = {"length_unit": cols["length"][2] or "1", "force_unit": cols["force"][2]}
    return CsvColumns(t, x, f, np.array(kinds) if i_kind is not None else None, header[idx[1]], units)


def _fast_rows(fh, idx: list[int], i_kind: int | None):
    """The three columns (and the step kinds) through numpy's parser, or None if any row is
    not plain: the row-by-row reader then names the line."""
    text = fh.read()
    try:
        arr = np.loadtxt(io.StringIO(text), delimiter=",", skiprows=0, usecols=idx, ndmin=2, dtype=float,
                         comments=None)
    except ValueError:
        return None
    if len(arr) == 0 or not np.all(np.isfinite(arr)):
        return None
    kinds: list[str] = []
    if i_kind is not None:
        lines = [ln for ln in text.splitlines() if ln.strip()]
        kinds = [(ln.split(",")[i_kind].strip() if ln.count(",") >= i_kind else "") for ln in lines]
        if len(kinds) != len(arr):
            return None
    return arr, kinds


def check_time(t: np.ndarray, column: str, where: str, first_line: int) -> None:
    """SpecError, naming the row, if the time column is not strictly increasing."""
    d = np.diff(t)
    if np.any(d <= 0):
        k = int(np.argmax(d <= 0))
        what = "duplicated" if d[k] == 0 else "decreasing (unsorted)"
        raise SpecError(f"{column} is {what} at row {k + first_line + 1} ({column} = {t[k + 1]:g} after "
                        f"{t[k]:g} s)", path=where, line=k + first_line + 1)


IMPORTED = ("t_s", "indentation_mm", "force_N")
# a trial whose contact was only estimated: its travel from the first sample, for every fit to place
ESTIMATED = ("t_s", "position_mm", "force_N")


def write_trial_csv(trial, out: str | Path) -> int:
    """A prepared trial as `rig import` writes it, loading positive: t_s,indentation_mm,force_N
    (indentation from contact, force above the preload) when the record knew its surface or
    started in contact; else t_s,position_mm,force_N (travel from the first sample, force as
    recorded), whose contact point and zero every fit places. Read back, it gives the same trial."""
    m = trial.motion
    x0 = float(m.x_m[0]) if trial.contact_estimated else 0.0
    try:
        fh = open(out, "w", newline="")  # noqa: SIM115
    except OSError as exc:
        raise SpecError(f"cannot write: {exc.strerror or exc}", path=str(out)) from None
    with fh:
        w = csv.writer(fh)
        w.writerow(ESTIMATED if trial.contact_estimated else IMPORTED)
        for t, x, f in zip(m.t_s, (m.x_m - x0) * 1000.0, trial.force_N, strict=True):
            w.writerow([repr(float(t)), repr(float(x)), repr(float(f))])
    return len(m.t_s)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
