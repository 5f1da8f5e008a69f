"""How well a force step followed its setpoint: overshoot, settling time and the hold's RMS error.

Measured on every force step as the loop runs (constant work a tick: running sums and a
0.1 s moving average, no history kept), reported at the step's end as a `force_step` event in
the log, in `rig replay` and in the daemon's status, and said to the operator when the
overshoot or the hold's error is beyond what the config allows (`force:`).

The overshoot and the settling are read on the force averaged over 0.25 s (25 ticks at 100 Hz),
so the sensor's noise does not pass for overshoot (its noise there is sigma / 5; over 0.1 s the
largest noise excursion of a 10 s hold at 19 sigma of setpoint read as 6 % overshoot where the
0.25 s force never passed 1.6 %), and the overshoot over the transient alone: the ramp that
leads into the hold and the hold's first OVERSHOOT_WINDOW_S. A ramp into a hold is one approach
to the hold's setpoint: the hold's overshoot counts the ramp's peak too. The RMS error is the
hold's past its first second (the settling), against the noise the tare measured.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

SMOOTH_TICKS = 25
END_TICKS = 5  # a step's end force: averaged as the sequencer judges a ramp's end
OVERSHOOT_WINDOW_S = 2.0
RMS_AFTER_S = 1.0
SETTLE_BAND_SHARE = 0.05  # settled: the smoothed force within 5 % of the setpoint from then on


@dataclass(frozen=True)
class StepFigures:
    """How a force step went, as a technician reads a controller's step response: its setpoint and
    duration, the overshoot, the settling time, the error over the hold (and over the noise), the
    force at its end, and for a ramp how late it ran and whether it reached its target."""

    index: int
    kind: str
    setpoint_N: float
    duration_s: float
    overshoot_share: float  # (peak smoothed force - setpoint) / setpoint; negative: never reached
    settle_s: float | None  # from the step's start (the contact, if it started in air); None: never
    rms_error_N: float | None  # hold past its first second; None for a ramp or a shorter hold
    rms_over_noise: float | None
    end_force_N: float  # at the step's end, averaged over its last END_TICKS ticks
    lag_s: float = 0.0  # a ramp: how long past its planned end it ran
    seek_s: float = 0.0  # how long it sought the surface before contact
    reached: bool = True  # a ramp: it reached its target (not ended RAMP_GRACE_S after its planned end)

    def as_dict(self) -> dict:
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in out.items()}

    def describe(self) -> str:
        if self.kind == "ramp_force":
            if not self.reached:
                how = (f"ended {self.lag_s:.2f} s after its planned end at {self.end_force_N:.4g} N, "
                       "short of its target")
            else:
                how = f"reached its target {self.lag_s:.2f} s after its planned end" if self.lag_s else \
                    "reached its target on time"
            parts = [f"step {self.index} (ramp_force to {self.setpoint_N:.4g} N): {how}"]
        else:
            parts = [f"step {self.index} ({self.kind} {self.setpoint_N:.4g} N): overshoot "
                     f"{100 * self.overshoot_share:+.1f} %",
                     f"settled in {self.settle_s:.2f} s" if self.settle_s is not None else "never settled"]
            if self.rms_error_N is not None:
                parts.append(f"RMS error {self.rms_error_N:.3g} N ({self.rms_over_noise:.2f} sigma)")
        if self.seek_s > 0:
            parts.append(f"sought the surface for {self.seek_s:.2f} s")
        return ", ".join(parts)


class StepMeter:
    """Fed every tick of one force step (after contact); `figures` at its end."""

    def __init__(self, index: int, kind: str, t0_s: float, sigma_N: float, carried_peak_N: float = -math.inf,
                 seek_s: float = 0.0) -> None:
        self.index, self.kind, self.t0_s, self.sigma_N = index, kind, t0_s, sigma_N
        self.seek_s = seek_s
        self.peak_N = carried_peak_N  # a ramp's peak carries into the hold it hands over to
        self.setpoint_N = 0.0
        self._window: deque[float] = deque(maxlen=SMOOTH_TICKS)
        self._end: deque[float] = deque(maxlen=END_TICKS)
        self._sum = 0.0
        self._last_out_s: float | None = None  # the last tick the smoothed force was out of band
        self._sq = 0.0
        self._n_rms = 0
        self._t = t0_s
        self.lag_s = 0.0
        self.reached = True

    @property
    def smoothed_N(self) -> float:
        return self._sum / len(self._window) if self._window else 0.0

    def update(self, t_s: float, force_N: float, setpoint_N: float) -> None:
        w = self._window
        if len(w) == w.maxlen:
            self._sum -= w[0]
        w.append(force_N)
        self._end.append(force_N)
        self._sum += force_N
        self._t, self.setpoint_N = t_s, setpoint_N
        if len(w) == w.maxlen:
            smooth = self._sum / len(w)
            if self.kind != "hold_force" or t_s - self.t0_s <= OVERSHOOT_WINDOW_S:
                self.peak_N = max(self.peak_N, smooth)
            if abs(smooth - setpoint_N) > SETTLE_BAND_SHARE * abs(setpoint_N):
                self._last_out_s = t_s
        else:
            self._last_out_s = t_s
        if t_s - self.t0_s >= RMS_AFTER_S:
            e = force_N - setpoint_N
            self._sq += e * e
            self._n_rms += 1

    def figures(self) -> StepFigures:
        sp = self.setpoint_N
        settled = None if self._last_out_s is not None and self._last_out_s >= self._t else (
            0.0 if self._last_out_s is None else self._last_out_s - self.t0_s)
        rms = math.sqrt(self._sq / self._n_rms) if self.kind == "hold_force" and self._n_rms >= 10 else None
        return StepFigures(self.index, self.kind, sp, self._t - self.t0_s,
                           (self.peak_N - sp) / sp if sp else 0.0, settled, rms,
                           rms / self.sigma_N if rms is not None and self.sigma_N > 0 else None,
                           sum(self._end) / len(self._end) if self._end else 0.0, self.lag_s, self.seek_s,
                           self.reached)
