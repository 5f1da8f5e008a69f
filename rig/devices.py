"""Open the slider and load cell a config names, behind the driver interfaces."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

from drivers.base import LoadCell, Slider
from rig.clock import Clock
from rig.config import RigConfig
from rig.errors import RigError


@dataclass
class Devices:
    slider: Slider
    loadcell: LoadCell
    rig: object | None = None  # the SimRig behind simulated devices (for tests and fault injection)

    def close(self) -> None:
        for dev in (self.slider, self.loadcell):
            with contextlib.suppress(Exception):
                dev.close()


def open_devices(config: RigConfig, clock: Clock) -> Devices:
    if config.slider.backend == "sim" and config.loadcell.backend == "sim":
        from sim_device.inprocess import InProcessLoadCell, InProcessSlider
        from sim_device.physics import SimRig

        sim = SimRig(config.sim)
        origin = clock.now()
        return Devices(InProcessSlider(sim, clock, origin), InProcessLoadCell(sim, clock, origin), sim)
    raise RigError(f"no backend pairing slider '{config.slider.backend}' with load cell "
                   f"'{config.loadcell.backend}'")
