"""One measured record as the analysis receives it, whatever file it came from."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rig.specs.frames import Frame


@dataclass
class Record:
    """Time, probe position and force in SI, as the instrument reported them.

    `position_m` and `force_N` keep the instrument's own zero and sign; the analysis finds
    contact, the direction of loading and the baseline itself. `frame` is the frame the position
    is measured in when the file says so: `Frame.SURFACE` (the rig's own logs, indentation
    columns) means its zero is where the probe meets the specimen, so contact is not searched
    for; None means an instrument's own zero. `steps` holds the rig's step kinds per sample
    when the file knows them.

    AFM force curves (rig.records.afm) also carry `segment`, per sample "approach",
    "intermediate" (a pause) or "retract", and `meta`: "instrument" ("JPK", "Asylum", "NT-MDT",
    "AFM Workshop", "Optics11 Chiaro"...), "curve" (its number in the file, as the instrument
    numbers it), "curves_in_file", "x_m"/"y_m" (position on the sample), "grid_index" and
    "grid_shape" ((x, y) on a force map), "spring_constant_N_per_m", "sensitivity", "modality"
    ("force-distance", "stress-relaxation", "creep-compliance"), "indenter" (a spec string such
    as "sphere:R=27.5um" when the file gives the tip), "instrument_result" (the instrument's own
    fit, e.g. {"model": "Hertz", "E_Pa": 117.0, "poisson": 0.5}) and a few more
    ("instrument_model", "format", "curve_id", "position_column", "time_from"); a key the file
    says nothing about is None.
    """

    name: str
    # "mcap", "csv", "jpk", "jpk-text", "mach1", "instron"; AFM: "asylum", "ntmdt", "afm-workshop",
    # "chiaro", "afmformats"
    source: str
    t_s: np.ndarray
    position_m: np.ndarray
    force_N: np.ndarray
    frame: Frame | None = None
    steps: np.ndarray | None = None
    baseline_force_N: np.ndarray | None = None  # force at rest before the record (a tare step)
    length_unit: str = "mm"  # how the file wrote lengths: reports keep it where it reads well
    force_unit: str = "N"
    notes: list[str] = field(default_factory=list)
    segment: np.ndarray | None = None  # per sample: "approach", "intermediate" or "retract"
    meta: dict = field(default_factory=dict)

    @property
    def zero_is_surface(self) -> bool:
        return self.frame is Frame.SURFACE

    @property
    def n(self) -> int:
        return len(self.t_s)
