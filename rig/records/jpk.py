"""JPK (Bruker) AFM force curves: the JPK Data Processing TEXT EXPORT. The binary files
(`.jpk-force`, force maps, QI data) are read through afmformats in rig.records.afm;
`read_jpk_force` stays here for the callers that import it.

Heights fall as the tip goes in, so the travel into the sample is -(height - height at the
start); the tip-sample indentation subtracts the cantilever's deflection (force / spring
constant), which matters for soft cantilevers.
"""

from __future__ import annotations

import contextlib
import re
from pathlib import Path

import numpy as np

from rig.errors import SpecError
from rig.records.afm import JPK, in_time_order, read_afm, tip_travel
from rig.records.record import Record
from rig.records.units import FORCE, LENGTH, TIME


def looks_like_jpk_text(head: str) -> bool:
    """Whether a file's head is a JPK text export (its `# segment:`, `# columns:` or `# TEXT EXPORT` lines)."""
    return "# segment:" in head or head.lstrip().startswith("# TEXT EXPORT") or "# columns:" in head


def read_jpk_force(path: str | Path, options=None) -> Record:
    """A binary JPK force file through afmformats: its first curve, or `options.curve`
    (a rig.records.afm.ReadOptions)."""
    return read_afm(Path(path), options, JPK)


def _jpk_record(path: Path, source: str, t, h, f, spring_N_per_m: float | None, notes: list[str]) -> Record:
    t, h, f = in_time_order(t, h, f)
    travel = tip_travel(h, f, spring_N_per_m, notes)
    return Record(path.name, source, t, travel, f, length_unit="µm", force_unit="nN", notes=notes)


_TEXT_NUM = re.compile(r"^\s*[-+0-9.]")


def read_jpk_text(path: Path) -> Record:
    """# segment / # columns / # units headers, then whitespace-separated rows, per segment."""
    where = str(path)
    cols: list[str] = []
    units: list[str] = []
    spring = None
    t_all: list[float] = []
    h_all: list[float] = []
    f_all: list[float] = []
    t_offset = 0.0
    new_segment = True
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as exc:
        raise SpecError(f"cannot open: {exc.strerror or exc}", path=where) from None
    for no, line in enumerate(lines, start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            key, _, val = s.lstrip("#").strip().partition(":")
            key = key.strip().lower()
            if key == "segment":
                new_segment = True
            elif key == "columns":
                cols = val.split()
            elif key == "units":
                units = val.split()
            elif key.endswith(("springconstant", "spring constant")):
                with contextlib.suppress(ValueError):
                    spring = float(val)
            continue
        if not _TEXT_NUM.match(s):
            raise SpecError(f"unexpected line in a JPK text export: '{s[:40]}'", path=where, line=no)
        if not cols:
            raise SpecError("data before a '# columns:' line", path=where, line=no)
        try:
            values = [float(v) for v in s.split()]
        except ValueError:
            raise SpecError(f"not a row of numbers: '{s[:40]}'", path=where, line=no) from None
        if len(values) != len(cols):
            raise SpecError(f"row has {len(values)} values, '# columns:' names {len(cols)}",
                            path=where, line=no)
        ix = _jpk_text_columns(cols, units, where, no)
        t_raw = values[ix["time"][0]] * ix["time"][1]
        if new_segment and t_all and t_raw + t_offset <= t_all[-1]:
            # seriesTime restarts in every segment: carry on from the previous one
            step = t_all[-1] - t_all[-2] if len(t_all) > 1 else 0.0
            t_offset = t_all[-1] + step - t_raw
        new_segment = False
        t_all.append(t_raw + t_offset)
        h_all.append(values[ix["height"][0]] * ix["height"][1])
        f_all.append(values[ix["force"][0]] * ix["force"][1])
    if len(t_all) < 10:
        raise SpecError("a JPK text export with fewer than ten rows of data", path=where)
    return _jpk_record(path, "jpk-text", np.array(t_all), np.array(h_all), np.array(f_all), spring,
                       ["JPK text export"])


def _jpk_text_columns(cols: list[str], units: list[str], where: str, line: int) -> dict:
    """time (seriesTime restarts per segment: it is made continuous), height, force."""
    low = [c.lower() for c in cols]
    unit = (units + [""] * len(cols))[: len(cols)]

    def find(names: list[str]) -> int | None:
        return next((low.index(n.lower()) for n in names if n.lower() in low), None)

    i_t = find(["time", "seriesTime", "segmentTime"])
    i_h = find(["measuredHeight", "capacitiveSensorHeight", "height", "tipSampleSeparation"])
    i_f = find(["vDeflection", "force"])
    if i_t is None or i_h is None or i_f is None:
        raise SpecError(f"a JPK text export needs time, height and vDeflection columns; '# columns:' has "
                        f"{' '.join(cols)}", path=where, line=line)
    for i, table, kind in ((i_t, TIME, "time"), (i_h, LENGTH, "length")):
        if unit[i] not in table:
            raise SpecError(f"column '{cols[i]}': '{unit[i] or '?'}' is not a {kind} unit",
                            path=where, line=line)
    if unit[i_f].lower() not in FORCE:
        raise SpecError(f"column '{cols[i_f]}': '{unit[i_f] or '?'}' is not a force unit (export vDeflection "
                        "in N)", path=where, line=line)
    fu = unit[i_f]
    return {"time": (i_t, TIME[unit[i_t]]),
            "height": (i_h, LENGTH[unit[i_h]], False),
            "force": (i_f, FORCE[fu.lower()], False)}
