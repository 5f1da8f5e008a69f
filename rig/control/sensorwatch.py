"""Whether the load cell can be believed, and whether the probe touches the specimen.

The stale check (`safety.check`) catches a cell that falls silent. A cell can also go on
sending lines that look fresh and say nothing: an indicator stuck on HOLD, or a serial relay
that repeats its last line, sends the same value forever; a saturated or disconnected bridge
amplifier reads steady and plausible. Under position control that costs a trial's data; under
force control it is dangerous, because the force loop drives the probe in until the reading
answers, and a frozen reading never does. Three checks, each from what the tare measured of the
cell's own noise (`CellNoise`), none of them switchable off:

- frozen: a run of identical readings that the cell's noise makes improbable (below 1e-9 by
  the share of repeats the tare saw, and never fewer than 5 readings, 50 ms at 100 Hz);
- noise vanished: over the last 25 readings the spread of successive differences is below a
  tenth of the tare's (a real cell's noise does not fall tenfold in a quarter of a second);
- unanswered motion (force steps in contact, `MotionAnswer`): the slider moved further than
  the force could stay unchanged at the measured stiffness while the loop pushed one way.

The first two are off for a cell too quiet to tell (a third or more of its tare's readings
repeat): then only the motion check and the depth budget stand between a frozen cell and the
specimen, and the trial's log says so.

Contact (`Contact`) is judged from the same noise: several sigma, for three readings in a row
(a threshold below the noise reads a third of the ticks in air as contact), with hysteresis;
the surface is where the probe was on the last tick out of contact.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

FROZEN_P = 1e-9  # how improbable a run of repeats must be before it is called frozen
FROZEN_MIN_RUN = 5
FROZEN_MAX_RUN = 25  # 0.25 s at 100 Hz: the fault comes well within half a second of the freeze
QUIET_SHARE = 1.0 / 3.0  # a cell whose tare repeats this often is too quiet for the repeat checks
SPREAD_WINDOW = 25
SPREAD_FLOOR = 0.1  # of the tare's spread of successive differences
CONTACT_SIGMA = 4.0  # contact: the force above this many sigma of the cell's noise...
CONTACT_RUN = 3  # ...for this many readings in a row (noise alone: below 1e-13)
RELEASE_SHARE = 0.5  # out of contact again below this share of the threshold, as many in a row


@dataclass(frozen=True)
class CellNoise:
    """The load cell's noise as the tare measured it."""

    sigma_N: float  # standard deviation of the readings at rest
    diff_sigma_N: float  # of successive differences (a low-pass filter in the cell lowers it)
    repeat_share: float  # share of successive readings that were identical
    step_N: float  # the smallest change seen between readings (the resolution, as far as seen)
    readings: int

    @classmethod
    def from_readings(cls, values: list[float], fallback_sigma_N: float) -> CellNoise:
        """From the tare's readings (one per new reading); `fallback_sigma_N` (the config's)
        when there are too few to tell."""
        v = np.asarray(values, dtype=float)
        if len(v) < 10:
            return cls(fallback_sigma_N, fallback_sigma_N * math.sqrt(2.0), 0.0, 0.0, len(v))
        d = np.diff(v)
        moved = np.abs(d[d != 0])
        return cls(float(np.std(v)), float(np.std(d)), float(np.mean(d == 0)),
                   float(moved.min()) if len(moved) else 0.0, len(v))

    @property
    def quiet(self) -> bool:
        """Too quiet for the repeat and spread checks: at rest it repeats itself anyway."""
        return self.repeat_share >= QUIET_SHARE or self.diff_sigma_N <= 0.0

    @property
    def frozen_run(self) -> int:
        p = min(max(self.repeat_share, 1e-3), QUIET_SHARE)  # a quiet cell's is never used
        return min(max(math.ceil(math.log(FROZEN_P) / math.log(p)), FROZEN_MIN_RUN), FROZEN_MAX_RUN)

    @property
    def effective_sigma_N(self) -> float:
        """The noise thresholds are built on: never below half the resolution seen."""
        return max(self.sigma_N, 0.5 * self.step_N, 1e-12)

    def describe(self) -> str:
        return (f"load cell noise {self.sigma_N:.3g} N over {self.readings} readings at the tare "
                f"({self.repeat_share:.0%} repeated)")


class CellWatch:
    """Frozen and noise-vanished readings; fed each new reading (a reading seen again on a later
    tick, with its old timestamp, is the stale check's, not this one's)."""

    def __init__(self, noise: CellNoise) -> None:
        self.noise = noise
        self.run = 0
        self._last: tuple[float, float] | None = None  # (t_s, value) of the last new reading
        self._diffs: deque[float] = deque(maxlen=SPREAD_WINDOW)
        self._sum = self._sum2 = 0.0

    def update(self, t_s: float, value_N: float) -> str | None:
        """Why the cell cannot be believed, or None."""
        last = self._last
        if last is not None and t_s <= last[0]:
            return None  # not a new reading
        self._last = (t_s, value_N)
        if last is None or self.noise.quiet:
            return None
        d = value_N - last[1]
        self.run = self.run + 1 if d == 0 else 0
        if len(self._diffs) == self._diffs.maxlen:
            old = self._diffs[0]
            self._sum -= old
            self._sum2 -= old * old
        self._diffs.append(d)
        self._sum += d
        self._sum2 += d * d
        n = self.noise
        if self.run >= n.frozen_run:
            return (f"load cell frozen: {self.run + 1} identical readings of {value_N:.6g} N in a row "
                    f"(its noise, {n.sigma_N:.3g} N at the tare, makes {n.frozen_run + 1} "
                    "improbable): a cell that repeats its last value")
        if len(self._diffs) == self._diffs.maxlen:
            k = len(self._diffs)
            spread = math.sqrt(max(self._sum2 / k - (self._sum / k) ** 2, 0.0))
            if spread < SPREAD_FLOOR * n.diff_sigma_N:
                return (f"load cell noise vanished: the last {k} readings vary by {spread:.3g} N "
                        f"from one to the next against {n.diff_sigma_N:.3g} N at the tare")
        return None


class Contact:
    """In contact or not, from the force and the cell's noise, with the surface's position."""

    def __init__(self, threshold_N: float, start_mm: float) -> None:
        self.threshold_N = threshold_N
        self.in_contact = False
        self.surface_mm = start_mm  # where the probe was on the last tick out of contact
        self._count = 0

    @classmethod
    def for_noise(cls, noise: CellNoise, start_mm: float) -> Contact:
        return cls(CONTACT_SIGMA * noise.effective_sigma_N, start_mm)

    def update(self, force_N: float, position_mm: float) -> bool:
        if self.in_contact:
            self._count = self._count + 1 if force_N < RELEASE_SHARE * self.threshold_N else 0
            if self._count >= CONTACT_RUN:
                self.in_contact, self._count = False, 0
        else:
            self._count = self._count + 1 if force_N > self.threshold_N else 0
            if self._count >= CONTACT_RUN:
                self.in_contact, self._count = True, 0
        if not self.in_contact and self._count == 0:
            self.surface_mm = position_mm
        return self.in_contact


class MotionAnswer:
    """Under force control, in contact: the force must answer the loop's motion.

    Anchored where the force last changed by more than `CONTACT_SIGMA` sigma or the loop's error
    changed sign or fell within two sigma (a creep hold, whose force stays at its setpoint while
    the slider follows the tissue, re-anchors on every sign change of its error): a slider that
    then travels further than `limit_mm` one way with the force unchanged is a fault."""

    def __init__(self, sigma_N: float) -> None:
        self.sigma_N = sigma_N
        self._anchor: tuple[float, float, bool] | None = None  # position, force, sign of the error

    def reset(self) -> None:
        self._anchor = None

    def update(self, position_mm: float, force_N: float, error_N: float, limit_mm: float) -> str | None:
        a = self._anchor
        pushing = error_N > 0
        if (a is None or abs(force_N - a[1]) > CONTACT_SIGMA * self.sigma_N or pushing != a[2]
                or abs(error_N) < 2.0 * self.sigma_N):
            self._anchor = (position_mm, force_N, pushing)
            return None
        moved = abs(position_mm - a[0])
        if moved > limit_mm:
            return (f"the force did not answer the force loop: the slider moved {moved:.3g} mm "
                    f"(more than {limit_mm:.3g} mm) and the force stayed at {a[1]:.4g} N within "
                    f"{CONTACT_SIGMA:g} sigma ({CONTACT_SIGMA * self.sigma_N:.3g} N): a frozen or "
                    "disconnected load cell")
        return None


def answer_limit_mm(sigma_N: float, stiffness_N_per_m: float, most_mm: float) -> float:
    """How far the slider may move with the force unchanged: five times the travel over which
    the force should change by `CONTACT_SIGMA` sigma at the measured stiffness, never more than
    `most_mm`, never less than a tenth of it."""
    if not stiffness_N_per_m > 0 or not math.isfinite(stiffness_N_per_m):
        return most_mm
    expected_mm = 1000.0 * CONTACT_SIGMA * sigma_N / stiffness_N_per_m
    return min(max(5.0 * expected_mm, 0.1 * most_mm), most_mm)
