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
    """

    name: str
    source: str  # "mcap", "csv", "jpk", "jpk-text", "mach1", "instron"
    t_s: np.ndarray
    position_m: np.ndarray
    force_N: np.ndarray
    frame: Frame | None = None
    steps: np.ndarray | None = None
    baseline_force_N: np.ndarray | None = None  # force at rest before the record (a tare step)
    length_unit: str = "mm"  # how the file wrote lengths: reports keep it where it reads well
    force_unit: str = "N"
    notes: list[str] = field(default_factory=list)

    @property
    def zero_is_surface(self) -> bool:
        return self.frame is Frame.SURFACE

    @property
    def n(self) -> int:
        return len(self.t_s)
