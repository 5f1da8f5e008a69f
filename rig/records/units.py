"""Units written in column names and instrument headers, mapped to SI.

A column says its unit as a suffix (`t_ms`, `force_nN`), in brackets (`t [ms]`,
`Indentation (nm)`) or after a comma (`Fz, gf`, the Mach-1 way). A unit that is not
written is never guessed; a unit that is written but unknown is an error naming the column.
"""

from __future__ import annotations

import re

from rig.errors import SpecError

GRAM_FORCE_N = 9.80665e-3

TIME = {"s": 1.0, "sec": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "min": 60.0, "h": 3600.0}
LENGTH = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "μm": 1e-6, "micron": 1e-6, "nm": 1e-9,
          "cm": 1e-2, "pm": 1e-12}
FORCE = {"n": 1.0, "mn": 1e-3, "un": 1e-6, "µn": 1e-6, "μn": 1e-6, "nn": 1e-9, "pn": 1e-12, "kn": 1e3,
         "gf": GRAM_FORCE_N, "g": GRAM_FORCE_N, "kgf": 9.80665, "lbf": 4.4482216152605}
RATIO = {"1": 1.0, "": 1.0, "%": 0.01, "mm/mm": 1.0}

TIME_WORDS = ("t", "time", "seconds", "elapsed")
LENGTH_WORDS = ("position", "pos", "indentation", "displacement", "depth", "extension", "height",
                "deformation", "x", "z", "travel", "stroke", "elongation", "position (z)")
FORCE_WORDS = ("force", "load", "f", "fz", "fn", "vdeflection")
STRAIN_WORDS = ("strain",)

_BRACKETED = re.compile(r"^(?P<name>.*?)\s*[\[(](?P<unit>[^\])]*)[\])]\s*$")
_COMMA = re.compile(r"^(?P<name>[^,]*?)\s*,\s*(?P<unit>\S+)\s*$")


def split_header(text: str) -> tuple[str, str | None]:
    """'force_nN' -> ('force', 'nN'); 't [ms]' -> ('t', 'ms'); 'Fz, gf' -> ('Fz', 'gf');
    'strain' -> ('strain', None)."""
    h = text.strip().strip('"')
    for pattern in (_BRACKETED, _COMMA):
        m = pattern.match(h)
        if m:
            return m["name"].strip(), m["unit"].strip()
    if "_" in h:
        name, unit = h.rsplit("_", 1)
        return name.strip(), unit.strip()
    return h, None


def quantity(name: str) -> str | None:
    """What a column's name measures: "time", "strain", "force" or "length", or None."""
    n = name.strip().lower().replace("_", " ")
    if n in TIME_WORDS or n.endswith(" time"):
        return "time"
    if n in STRAIN_WORDS or n.endswith(" strain"):
        return "strain"
    if n in FORCE_WORDS or "force" in n or "load" in n:
        return "force"
    if n in LENGTH_WORDS or any(w in n for w in ("position", "indentation", "displacement", "extension",
                                                  "height", "depth", "elongation")):
        return "length"
    return None


def to_si(column: str, kind: str, unit: str | None, where: str) -> float:
    """The factor that turns `column`'s values into SI (s, m, N, 1); errors name the column."""
    table = {"time": TIME, "length": LENGTH, "force": FORCE, "strain": RATIO}[kind]
    if unit is None:
        if kind == "strain":
            return 1.0
        raise SpecError(f"column '{column}' does not say its unit (write it, e.g. "
                        f"{_example(kind)})", path=where, line=1)
    key = unit.strip()
    key = key.lower() if kind == "force" else key
    if key in table:
        return table[key]
    known = ", ".join(k for k in table if k)
    raise SpecError(f"column '{column}': unknown {kind} unit '{unit}' (known: {known})", path=where, line=1)


def _example(kind: str) -> str:
    return {"time": "t_s or 'time [ms]'", "length": "position_um or 'indentation (nm)'",
            "force": "force_nN or 'load (mN)'"}[kind]


FORCE_DISPLAY = [(1.0, "N"), (1e-3, "mN"), (1e-6, "µN"), (1e-9, "nN"), (1e-12, "pN")]
LENGTH_DISPLAY = [(1.0, "m"), (1e-3, "mm"), (1e-6, "µm"), (1e-9, "nm")]


def display_unit(magnitude: float, table: list[tuple[float, str]]) -> tuple[float, str]:
    """The unit a person would write a quantity of this size in (0.3 uN reads as 300 nN)."""
    for factor, name in table:
        if magnitude >= 0.5 * factor:
            return factor, name
    return table[-1]
