"""The force loop: the slider moved so that the measured force follows a setpoint.

The slider is a position axis, so the loop commands a speed and streams the position it
integrates to: v = (r + w_c e + w_i integral(e)) / k, e = setpoint - force, r the setpoint's
own rate (a ramp's, fed forward), k the specimen's
stiffness as the online RLS estimator reads it (the paper's estimator put to work). Dividing
by k schedules the gain: whatever the specimen, the force's own loop has the crossover w_c
(a 10 N/m gel and a 10,000 N/m tendon respond alike), and the integral term takes out a
force that keeps falling at a held position (relaxation: the indentation creeps). The speed is
capped at the protocol's limit; while it is capped the integral does not grow (anti-windup).

Why these gains. The loop's own delay (one tick, the load cell's age and the drive's
response, about 30 ms at 100 Hz) takes w_c d of phase: w_c = 8 rad/s keeps the phase margin
near 75 degrees for a stiffness read right and near 60 degrees for one read a factor two low,
and settles a step in about 0.5 s; w_i = w_c / 4 puts the integral's corner well inside it, so
it adds little overshoot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

CROSSOVER_RAD_S = 8.0
INTEGRAL_RATIO = 0.5  # w_i / w_c
# the stiffness the loop assumes at least: a reading near zero (out of contact, or before the
# estimator has settled) would make the gain unbounded; this bounds the first move's speed
STIFFNESS_FLOOR_SHARE = 1e-3  # of (force limit / travel span), in N/m


@dataclass
class ForceCommand:
    target_mm: float
    speed_mm_s: float
    error_N: float
    saturated: bool


class ForceLoop:
    """PI on the slider's speed from the force error, the gain scheduled by the stiffness."""

    def __init__(self, period_s: float, max_speed_mm_s: float, stiffness_floor_N_per_m: float,
                 crossover_rad_s: float | None = None, integral_ratio: float | None = None) -> None:
        self.period_s = period_s
        self.max_speed_mm_s = max_speed_mm_s
        self.floor = stiffness_floor_N_per_m
        self.wc = CROSSOVER_RAD_S if crossover_rad_s is None else crossover_rad_s
        self.wi = self.wc * (INTEGRAL_RATIO if integral_ratio is None else integral_ratio)
        self.integral_Ns = 0.0
        self.target_mm: float | None = None

    def start(self, position_mm: float) -> None:
        """A force step begins where the slider stands (the integral carried over from the previous
        force step, so a ramp into a hold does not restart the loop)."""
        if self.target_mm is None:
            self.target_mm = position_mm
            self.integral_Ns = 0.0

    def release(self) -> None:
        """A position step takes over: the next force step starts afresh."""
        self.target_mm = None
        self.integral_Ns = 0.0

    def command(self, setpoint_N: float, force_N: float, stiffness_N_per_m: float,
                position_mm: float, setpoint_rate_N_s: float = 0.0) -> ForceCommand:
        if self.target_mm is None:
            self.start(position_mm)
        e = setpoint_N - force_N
        k = stiffness_N_per_m if math.isfinite(stiffness_N_per_m) else self.floor
        k = max(k, self.floor)
        # the setpoint's own rate fed forward: a ramp is followed without waiting for its error
        v_mm_s = 1000.0 * (setpoint_rate_N_s + self.wc * e + self.wi * self.integral_Ns) / k
        saturated = abs(v_mm_s) > self.max_speed_mm_s
        if saturated:
            v_mm_s = math.copysign(self.max_speed_mm_s, v_mm_s)
        if not saturated or (e > 0) != (self.integral_Ns > 0):
            self.integral_Ns += e * self.period_s
        # the stream of positions the speed integrates to: the drive follows it tick by tick, and
        # never runs more than a tick's move ahead of where it stands
        self.target_mm += v_mm_s * self.period_s
        lead = abs(v_mm_s) * self.period_s
        self.target_mm = min(max(self.target_mm, position_mm - 2 * lead - 1e-6), position_mm + 2 * lead + 1e-6)
        return ForceCommand(self.target_mm, max(abs(v_mm_s), 1e-6), e, saturated)
