"""The specimen's dimensions as a trial keeps them: its thickness (mm, over the support) and its
contact area (mm^2), given at the start (`rig run`/`rig start --thickness-mm --area-mm2`, the
daemon's start request) and written into the log's header (`thickness_mm`, `area_mm2` in the
"trial" metadata). Read back by the analysis (the bottom effect's thickness, rig.analysis.workflow.inputs)
and by `rig replay` (stress = force / area, strain = indentation / thickness)."""

from __future__ import annotations

import math

from rig.errors import RigError

KEYS = {"thickness_mm": "--thickness-mm", "area_mm2": "--area-mm2"}


def dimensions(thickness_mm: float | None = None, area_mm2: float | None = None) -> dict[str, str]:
    """The header's entries for the dimensions given (none for one not given); a value that is
    not a positive finite number is refused, named by its option."""
    out = {}
    for key, value in (("thickness_mm", thickness_mm), ("area_mm2", area_mm2)):
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int | float) or not (math.isfinite(value)
                                                                                and value > 0):
            raise RigError(f"{KEYS[key]} {value!r}: the specimen's {key.split('_')[0]} is a positive number")
        out[key] = f"{float(value):.6g}"
    return out


def from_header(trial: dict) -> dict[str, float]:
    """The dimensions a log's "trial" metadata holds, as numbers (an unreadable one left out)."""
    out = {}
    for key in KEYS:
        try:
            v = float(trial.get(key) or "nan")
        except ValueError:
            continue
        if math.isfinite(v) and v > 0:
            out[key] = v
    return out
