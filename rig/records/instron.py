"""Instron Bluehill raw-data CSV: `Key : Name,"value",unit` header lines, a blank line, a row
of column names, a row of units in parentheses, then quoted numbers. Tension tests report
positive extension and load."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from rig.errors import SpecError
from rig.records.record import Record
from rig.records.units import quantity, to_si


def looks_like_instron(head: str) -> bool:
    """Whether a file's head is an Instron (Bluehill) export: a `name : value` header and a row of units in
    parentheses."""
    lines = [ln for ln in head.splitlines() if ln.strip()]
    units_row = any(ln.strip().startswith("(") and ln.strip().endswith(")") for ln in lines[:40])
    return units_row and any(" : " in ln for ln in lines[:20])


def read_instron(path: Path) -> Record:
    """An Instron (Bluehill) CSV export as a Record, its columns found by name and read in the units its
    units row gives."""
    where = str(path)
    try:
        with open(path, newline="", encoding="utf-8-sig", errors="replace") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise SpecError(f"cannot open: {exc.strerror or exc}", path=where) from None
    units_at = next((i for i, r in enumerate(rows)
                     if r and all(c.strip().startswith("(") and c.strip().endswith(")") for c in r if c.strip())
                     and any(c.strip() for c in r)), None)
    if units_at is None or units_at == 0:
        raise SpecError("an Instron export needs a row of column names followed by a row of units in "
                        "parentheses", path=where)
    names = [c.strip() for c in rows[units_at - 1]]
    units = [c.strip().strip("()") for c in rows[units_at]]
    pick: dict[str, tuple[int, float]] = {}
    for i, (n, u) in enumerate(zip(names, units, strict=False)):
        kind = quantity(n)
        if n.lower() in ("extension", "displacement", "position"):
            kind = "length"
        if kind in ("time", "length", "force") and kind not in pick:
            pick[kind] = (i, to_si(f"{n} ({u})", kind, u, where))
    missing = [k for k in ("time", "length", "force") if k not in pick]
    if missing:
        raise SpecError(f"Instron columns {', '.join(names)}: no {' or '.join(missing)} column",
                        path=where, line=units_at)
    data = []
    for no, r in enumerate(rows[units_at + 1:], start=units_at + 2):
        if not r or not any(c.strip() for c in r):
            continue
        try:
            data.append([float(r[pick[k][0]].replace(",", "")) for k in ("time", "length", "force")])
        except (IndexError, ValueError):
            raise SpecError(f"row is not numbers in the Time, Extension and Load columns: "
                            f"'{','.join(r)[:50]}'", path=where, line=no) from None
    if len(data) < 10:
        raise SpecError(f"{len(data)} data rows: too few", path=where)
    arr = np.array(data)
    t = arr[:, 0] * pick["time"][1]
    from rig.records.csvfile import check_time

    check_time(t, names[pick["time"][0]], where, units_at + 1)
    return Record(path.name, "instron", t, arr[:, 1] * pick["length"][1], arr[:, 2] * pick["force"][1],
                  length_unit=units[pick["length"][0]], force_unit=units[pick["force"][0]],
                  notes=["Instron Bluehill export"])
