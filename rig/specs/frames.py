"""The position's reference frames, named once.

A position means nothing without its zero. Three zeros matter, all on the slider's own axis:

- `Frame.SLIDER`: the slider's absolute coordinates (what the drive reports and is told);
- `Frame.TRIAL`: where the trial started;
- `Frame.SURFACE`: where the probe meets the specimen, found by an approach step; a protocol
  without an approach starts at the surface, so there it is the trial's start.

Protocol targets (`ramp: {to_mm: ...}`) are in the *working* frame: the surface once an
approach has found it, the trial's start until then. The loop logs `position_mm` in the working
frame as it stood at the start of each tick, so a log of a protocol with an approach changes
zero at contact; `FrameTrack` puts every sample of such a log into any one frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np


class Frame(StrEnum):
    SLIDER = "slider"
    TRIAL = "trial"
    SURFACE = "surface"


@dataclass(frozen=True)
class Frames:
    """Where the zeros of the trial's frames sit in slider coordinates, mm."""

    start_mm: float
    surface_mm: float | None = None  # None until an approach finds it

    @property
    def working(self) -> Frame:
        """The frame protocol targets are measured in."""
        return Frame.SURFACE if self.surface_mm is not None else Frame.TRIAL

    def zero_mm(self, frame: Frame) -> float:
        """Slider coordinate of `frame`'s zero (the surface is the start while none was found)."""
        if frame is Frame.SLIDER:
            return 0.0
        if frame is Frame.SURFACE and self.surface_mm is not None:
            return self.surface_mm
        return self.start_mm

    def convert(self, x_mm, source: Frame, target: Frame):
        """`x_mm` (a number or an array) measured in `source`, measured in `target`."""
        return x_mm + (self.zero_mm(source) - self.zero_mm(target))

    def at_contact(self, surface_mm: float) -> Frames:
        return replace(self, surface_mm=surface_mm)


@dataclass(frozen=True)
class FrameTrack:
    """Per sample of a trial log: the slider's position and the zeros in effect.

    `working_zero_mm[i]` is the working frame's zero after tick i (what the loop's estimator
    and commands used from then on); `surface_mm[i]` is the surface sample i belongs to: for the
    samples of an approach (and the tare before it) the contact that approach went on to find.
    """

    slider_mm: np.ndarray
    working_zero_mm: np.ndarray
    surface_mm: np.ndarray
    start_mm: float

    def zero_mm(self, frame: Frame) -> np.ndarray | float:
        if frame is Frame.SLIDER:
            return 0.0
        if frame is Frame.TRIAL:
            return self.start_mm
        return self.surface_mm

    def position_mm(self, frame: Frame) -> np.ndarray:
        """Every sample's position measured in `frame`."""
        return self.slider_mm - self.zero_mm(frame)

    def convert_working(self, x_mm: np.ndarray, target: Frame) -> np.ndarray:
        """Per-sample values measured from the working zero after each tick (as the loop logs
        its commanded position), measured in `target`."""
        return x_mm + self.working_zero_mm - self.zero_mm(target)

    @property
    def estimator_x_mm(self) -> np.ndarray:
        """The position the loop's estimator took as x(t-1) on the tick after each sample."""
        return self.slider_mm - self.working_zero_mm

    @property
    def frames(self) -> Frames:
        """The frames at the end of the log."""
        surface = float(self.surface_mm[-1]) if len(self.surface_mm) else self.start_mm
        return Frames(self.start_mm, surface)
