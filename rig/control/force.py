"""The force loop: the slider moved so that the measured force follows a setpoint.

The slider is a position axis, so the loop commands a speed and streams the position it
integrates to: v = (r + w_c e + w_i integral(e)) / k, e = setpoint - force, r the setpoint's
own rate (a ramp's, fed forward), k the specimen's stiffness from the surface the force found
(an RLS estimator on the depth below that surface: `Trial._estimate`). Dividing by k schedules
the gain: whatever the specimen, the force's own loop has the crossover w_c (a 10 N/m gel and a
10,000 N/m tendon respond alike), and the integral term takes out a force that keeps falling
at a held position (relaxation: the indentation creeps). The depth must be counted from the
surface: counted from the trial's start 10 mm above it, the stiffness read 30x low and the
gain was 30x high (a 5 N hold overshot to 9.4 N and oscillated). The speed is capped at the
protocol's limit; while it is capped, or the slider lags the stream by more than its lead, the
integral does not grow (anti-windup).

Why these gains. With the stiffness read right the force obeys s^2 + w_c s + w_i = 0 to a
disturbance: w_c = 8 rad/s, w_i = 8 rad^2/s^2 (INTEGRAL_RATIO 1) give poles at -1.17 and
-6.83 rad/s. The fast one sets how a step settles (about 0.5 s); the slow one is how long a
relaxation's pull takes to be taken out. On specimens 0.1x to 100x the default's stiffness
(72 simulated trials, force steps first, the surface 0-10 mm below the start) w_i = w_c / 2 left
the stiffest one's hold 0.06 N under its 15 N setpoint on average, an RMS error of up to 1.51
sigma of the cell's noise; w_i = w_c 1.35 sigma, the overshoot at most 4.4 % (with the 10-tick
average's own noise in it). The loop's own delay (one tick, the load cell's age, the drive's
response, about 30 ms) costs w_c d of phase: at 8 rad/s the margin stays near 75 degrees, near
60 for a stiffness read a factor two low.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

CROSSOVER_RAD_S = 8.0
INTEGRAL_RATIO = 1.0  # w_i / w_c
INTEGRAL_BAND_SHARE = 0.1  # of the setpoint: the integral grows only on an error within it
# the stiffness the loop assumes at least: a reading near zero (out of contact, or before the
# estimator has settled) would make the gain unbounded; this bounds the first move's speed
STIFFNESS_FLOOR_SHARE = 1e-3  # of (force limit / travel span), in N/m


@dataclass
class ForceCommand:
    """What the force loop asks of the drive this tick: the target position and speed, the force error it
    acts on, and whether the speed limit capped it."""

    target_mm: float
    speed_mm_s: float
    error_N: float
    saturated: bool


class ForceLoop:
    """PI on the slider's speed from the force error, the gain scheduled by the stiffness."""

    def __init__(self, period_s: float, max_speed_mm_s: float, stiffness_floor_N_per_m: float,
                 crossover_rad_s: float | None = None, integral_ratio: float | None = None,
                 min_lead_mm: float = 0.0) -> None:
        """`min_lead_mm` (a few of the drive's steps): how far the stream of positions may always
        run ahead of the slider (see `command`)."""
        self.min_lead_mm = min_lead_mm
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

    def seek(self, position_mm: float, speed_mm_s: float) -> ForceCommand:
        """Out of contact: stream positions into the specimen at `speed_mm_s` (an approach's
        pace), whatever the error; the loop's integral waits for contact."""
        self.integral_Ns = 0.0
        lead = 2 * speed_mm_s * self.period_s + self.min_lead_mm
        self.target_mm = position_mm + lead
        return ForceCommand(self.target_mm, speed_mm_s, 0.0, True)

    def command(self, setpoint_N: float, force_N: float, stiffness_N_per_m: float,
                position_mm: float, setpoint_rate_N_s: float = 0.0,
                speed_cap_mm_s: float | None = None) -> ForceCommand:
        """The next position and speed; `speed_cap_mm_s` lowers the speed limit for this tick."""
        if self.target_mm is None:
            self.start(position_mm)
        e = setpoint_N - force_N
        k = stiffness_N_per_m if math.isfinite(stiffness_N_per_m) else self.floor
        k = max(k, self.floor)
        # the setpoint's own rate fed forward: a ramp is followed without waiting for its error
        v_mm_s = 1000.0 * (setpoint_rate_N_s + self.wc * e + self.wi * self.integral_Ns) / k
        cap = self.max_speed_mm_s if speed_cap_mm_s is None else min(self.max_speed_mm_s, speed_cap_mm_s)
        saturated = abs(v_mm_s) > cap
        if saturated:
            v_mm_s = math.copysign(cap, v_mm_s)
        # the stream of positions the speed integrates to, never more than two ticks' travel (and
        # a few of the drive's steps, so that a slow stream still moves it) ahead of the slider. A
        # drive brakes towards its target, so that short lead also caps how fast it goes where
        # the loop asks a lot (v ~ sqrt(2 a lead)): measured, a longer lead (the braking distance)
        # let the slider run at the loop's full gain, and with the stiffness read as a secant a
        # stiffening specimen then overshot by 6-10 %
        self.target_mm += v_mm_s * self.period_s
        lead = 2 * abs(v_mm_s) * self.period_s + self.min_lead_mm
        clamped = min(max(self.target_mm, position_mm - lead), position_mm + lead)
        # a slider that lags the stream by more than its lead is as saturated as a capped speed:
        # integrating then winds the loop up, and a ramp the specimen cannot follow at the
        # drive's pace (a soft gel asked for 0.075 N/s needed 8 mm/s) overshot its hold by 5 %
        held_back = clamped != self.target_mm
        self.target_mm = clamped
        # the integral is for the small, slow error a relaxing specimen leaves (conditional
        # integration): a large one (a ramp the specimen lagged, a step) is the proportional
        # term's, and integrated it carried the catch-up past the setpoint
        near = abs(e) <= INTEGRAL_BAND_SHARE * abs(setpoint_N)
        if (near and not (saturated or held_back)) or (e > 0) != (self.integral_Ns > 0):
            self.integral_Ns += e * self.period_s
        return ForceCommand(self.target_mm, max(abs(v_mm_s), 1e-6), e, saturated)
