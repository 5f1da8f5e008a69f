"""Step sequencing: which step runs, when it ends, and which move command it issues.

Pure logic, no I/O: the loop feeds it each tick's measurements and carries out the
`Move`/`Stop` commands it returns. Positions here are absolute (slider coordinates);
`frames` holds the trial's zeros (`rig.specs.frames`): protocol targets are in its working
frame, the trial's start until an approach finds the surface, the surface from then on.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from rig.specs.frames import Frames
from rig.specs.motion import move_time, position_at
from rig.specs.protocol import FORCE_STEPS, Approach, Hold, HoldForce, Protocol, Ramp, RampForce, Return, Step


@dataclass(frozen=True)
class Move:
    """A move the sequencer asks for: to an absolute position, at a speed and acceleration."""

    to_mm: float  # absolute
    speed_mm_s: float
    accel_mm_s2: float


@dataclass(frozen=True)
class Stop:
    """The sequencer asks the trial to stop, and says why."""

    reason: str


@dataclass(frozen=True)
class Track:
    """Force control this tick: move so that the force follows `setpoint_N`, never deeper than
    `limit_mm` (absolute)."""

    setpoint_N: float
    limit_mm: float
    rate_N_s: float = 0.0  # how fast the setpoint moves (a ramp's), fed forward
    seeking: bool = False  # out of contact: seek the surface at the seek speed, the loop idle


Command = Move | Stop | Track

# A force ramp ends once the force is within this share of its target after its planned end, or
# RAMP_GRACE_S later at most (then the lag is said: `rig.control.forcestats`)
RAMP_REACHED_SHARE = 0.05
RAMP_GRACE_S = 1.0
RAMP_REACHED_TICKS = 5  # judged on the force averaged over this many ticks, not on one noisy reading


class Sequencer:
    """A protocol's steps in time: each tick it is told where the probe is and what the force
    reads, and it says where the probe should go (the step in progress, its setpoint and speed),
    when a step is done, and when the protocol is.

    ``index`` is the running step (-1 while taring), ``step_t0`` its start, ``done`` set when
    the last step ends, ``fault`` the reason if a step cannot go on (an approach that reaches
    its depth limit without finding the surface). Positions are in the protocol's frames
    (`rig.specs.frames`), from ``start_mm``. It moves nothing itself: the trial's loop sends
    what it asks.
    """

    def __init__(self, proto: Protocol, *, start_mm: float, accel_mm_s2: float, tare_s: float,
                 tolerance_mm: float, rate_Hz: float) -> None:
        self.steps: list[tuple[int, Step]] = proto.run_steps()
        self.frames = Frames(start_mm)
        self.accel = accel_mm_s2
        self.tare_s = tare_s
        self.tol = tolerance_mm
        self.rate = rate_Hz
        self.index = -1  # -1 = taring
        self.step_t0 = 0.0
        self.done = False
        self.fault: str | None = None
        self._from_mm = start_mm
        self._target_mm = start_mm
        self._speed = 0.0
        self._step_accel = accel_mm_s2
        self._window: deque[tuple[float, float]] = deque()
        self._contact_count = 0
        self._approach_stopping = False
        self._arrived = 0
        self._abort_pending = False
        self._force_from: float | None = None  # the force when a force ramp started
        self._last_force = 0.0
        self._last_pos = start_mm
        self._in_contact = True
        self._recent_force: deque[float] = deque(maxlen=RAMP_REACHED_TICKS)
        self.setpoint_N: float | None = None  # the force step's setpoint this tick
        # A force step's clock starts at contact: one begun in air first seeks the surface, and
        # a ramp timed from the step's start would end before the force had begun to rise
        self.force_t0: float | None = None
        self.force_seek_s = 0.0  # how long the current force step sought the surface
        self.force_lag_s = 0.0  # how long past its planned end the current force ramp ran
        self.force_reached = True  # the current force ramp reached its target (not ended by the grace)
        # (seek_s, lag_s, reached) of the force step the last `tick` ended, for its report; else None
        self.ended_force: tuple[float, float, bool] | None = None
        self._left_after: list[float] = []  # planned time of the steps after each index
        self._plan_left()

    # -------------------------------------------------------------- state
    @property
    def kind(self) -> str:
        if self.done:
            return "done"
        return "tare" if self.index < 0 else self.steps[self.index][1].kind

    @property
    def step(self) -> Step | None:
        return self.steps[self.index][1] if 0 <= self.index < len(self.steps) else None

    @property
    def start_mm(self) -> float:
        return self.frames.start_mm

    @property
    def zero_mm(self) -> float:
        """The working frame's zero in slider coordinates: protocol targets are measured from it."""
        return self.frames.zero_mm(self.frames.working)

    @property
    def target_mm(self) -> float:
        return self._target_mm

    def abort_to_start(self, t: float, speed_mm_s: float) -> None:
        """Drop the remaining steps; once the slider has stopped, return to the start position."""
        self.steps = [*self.steps[:max(self.index, -1) + 1], (0, Return(speed_mm_s=speed_mm_s))]
        self.index = len(self.steps) - 2
        self._speed = 0.0
        self._abort_pending = True
        self.done = False
        self._plan_left()

    def position_cmd_mm(self, t: float) -> float:
        """The ideal commanded position (trapezoidal profile of the current move)."""
        if self._speed <= 0:
            return self._target_mm - self.zero_mm
        return position_at(self._from_mm, self._target_mm, self._speed, self._step_accel,
                             t - self.step_t0) - self.zero_mm

    def time_left_s(self, t: float) -> float:
        """Planned time still to run (holds at their longest; a force step from its contact):
        the current step's rest plus the planned time of the steps after it, summed once when
        the trial starts (constant work a tick, whatever the protocol's length; a later zero
        moves positions, not the time between them)."""
        left = self._left_after[self.index + 1] if self.index + 1 < len(self._left_after) else 0.0
        if self.index < 0:
            return left + max(self.tare_s - t, 0.0)
        if self.index >= len(self.steps):
            return 0.0
        step = self.step
        elapsed = t - self.step_t0
        if isinstance(step, RampForce):
            start = self._force_from if self._force_from is not None else (self.setpoint_N or 0.0)
            elapsed = t - self.force_t0 if self.force_t0 is not None else 0.0
            return left + max(abs(step.to_N - start) / step.rate_N_s - elapsed, 0.0)
        if isinstance(step, HoldForce):
            elapsed = t - self.force_t0 if self.force_t0 is not None else 0.0
            return left + max(step.longest_s - elapsed, 0.0)
        if isinstance(step, Hold):
            return left + max(step.longest_s - elapsed, 0.0)
        return left + max(move_time(self._from_mm, self._target_mm, self._speed, self._step_accel)
                          - elapsed, 0.0)

    def _plan_left(self) -> None:
        """`_left_after[i]`: the planned time of steps i and after, from the frames as they stand."""
        durations: list[float] = []
        pos, force = self._target_mm, self.setpoint_N or 0.0
        for _, step in self.steps:
            if isinstance(step, RampForce):
                durations.append(abs(step.to_N - force) / step.rate_N_s)
                force = step.to_N
            elif isinstance(step, Hold | HoldForce):
                durations.append(step.longest_s)
                force = step.force_N if isinstance(step, HoldForce) else force
            else:
                target = self._resolve_target(step)
                durations.append(move_time(pos, target, step.speed_mm_s, self.accel))
                pos = target
        left = [0.0] * (len(durations) + 1)
        for i in range(len(durations) - 1, -1, -1):
            left[i] = left[i + 1] + durations[i]
        self._left_after = left

    # -------------------------------------------------------------- ticking
    def tick(self, t: float, position_mm: float, force_N: float, moving: bool | None,
             in_contact: bool = True) -> list[Command]:
        """Advance on this tick's measurements; returns commands to carry out now. `in_contact`:
        the probe touches the specimen, as the loop judges it from the force and the cell's noise
        (a force step's clock starts there)."""
        self._last_force = force_N
        self._last_pos = position_mm
        self._in_contact = in_contact
        self.ended_force = None
        self._recent_force.append(force_N)
        if self.done:
            return []
        if self._abort_pending:
            if moving is False:
                self._abort_pending = False
                return self._next(t)
            return []
        if self.index < 0:
            return self._next(t) if t >= self.tare_s else []
        step = self.step
        if isinstance(step, FORCE_STEPS):
            return self._tick_force(step, t, force_N)
        if isinstance(step, Hold):
            return self._tick_hold(step, t, force_N)
        if isinstance(step, Approach):
            return self._tick_approach(step, t, position_mm, force_N, moving)
        # Ramp / Return: done once the slider sits at the target.
        if abs(position_mm - self._target_mm) <= self.tol and moving is not True:
            self._arrived += 1
            if self._arrived >= 2:
                return self._next(t)
        else:
            self._arrived = 0
        return []

    def _tick_force(self, step: RampForce | HoldForce, t: float, force_N: float) -> list[Command]:
        limit = self.zero_mm + step.max_mm
        if self.force_t0 is None:
            if not self._in_contact:  # in air: seek the surface; the step's clock has not started
                self.force_seek_s = t - self.step_t0
                if isinstance(step, HoldForce):
                    self.setpoint_N = step.force_N
                elif self.setpoint_N is None:  # a ramp's setpoint waits at the force in air
                    self.setpoint_N = max(force_N, 0.0)
                return [Track(self.setpoint_N, limit, 0.0, seeking=True)]
            self.force_t0 = t
        elapsed = t - self.force_t0
        if isinstance(step, HoldForce):
            if elapsed >= step.duration_s - 0.5 / self.rate:
                return self._next(t)
            self.setpoint_N = step.force_N
            return [Track(self.setpoint_N, limit, 0.0)]
        if self._force_from is None:
            # from the force at contact, or where a force step before it left the setpoint
            self._force_from = force_N if self.setpoint_N is None or self.force_seek_s > 0 else self.setpoint_N
        span_s = abs(step.to_N - self._force_from) / step.rate_N_s
        if elapsed >= span_s:
            self.setpoint_N = step.to_N
            force = sum(self._recent_force) / len(self._recent_force)
            reached = abs(force - step.to_N) <= RAMP_REACHED_SHARE * step.to_N or (
                (force > step.to_N) == (step.to_N > self._force_from))
            if reached or elapsed >= span_s + RAMP_GRACE_S:
                self.force_lag_s = elapsed - span_s
                self.force_reached = reached
                return self._next(t)
            return [Track(self.setpoint_N, limit, 0.0)]
        gone = math.copysign(step.rate_N_s * elapsed, step.to_N - self._force_from)
        self.setpoint_N = self._force_from + gone
        return [Track(self.setpoint_N, limit, math.copysign(step.rate_N_s, step.to_N - self._force_from))]

    def follow(self, target_mm: float) -> None:
        """Where the force loop sent the slider: the next position step moves on from there."""
        self._target_mm = target_mm

    def _tick_hold(self, step: Hold, t: float, force_N: float) -> list[Command]:
        elapsed = t - self.step_t0
        if step.duration_s is not None:
            return self._next(t) if elapsed >= step.duration_s - 0.5 / self.rate else []
        if elapsed >= (step.max_s or 0.0):
            return self._next(t)
        self._window.append((t, force_N))
        while self._window and self._window[0][0] < t - step.window_s:
            self._window.popleft()
        if elapsed >= step.window_s and abs(_slope(self._window)) < (step.until_rate_N_s or 0.0):
            return self._next(t)
        return []

    def _tick_approach(self, step: Approach, t: float, position_mm: float, force_N: float,
                       moving: bool | None) -> list[Command]:
        if self._approach_stopping:
            if moving is False:
                self.frames = self.frames.at_contact(position_mm)
                self._target_mm = position_mm
                return self._next(t)
            return []
        # Five samples in a row (50 ms at 100 Hz) above threshold: with a threshold of about
        # twice the noise, noise alone does this about once in 10^5 ticks.
        self._contact_count = self._contact_count + 1 if force_N > step.contact_N else 0
        if self._contact_count >= 5:
            self._approach_stopping = True
            self._target_mm = position_mm
            self._speed = 0.0
            return [Stop("contact found")]
        if abs(position_mm - self._target_mm) <= self.tol and moving is not True:
            self.fault = (f"approach reached {step.max_mm:g} mm without force above "
                          f"{step.contact_N:g} N: no contact")
        return []

    def _resolve_target(self, step: Step) -> float:
        if isinstance(step, Return) and step.to_mm is None:
            return self.start_mm
        if isinstance(step, Approach):
            return self.zero_mm + step.max_mm
        return self.zero_mm + step.to_mm

    def _next(self, t: float) -> list[Command]:
        after_force = isinstance(self.step, FORCE_STEPS)
        self.ended_force = (self.force_seek_s, self.force_lag_s, self.force_reached) if after_force else None
        self.force_lag_s, self.force_reached = 0.0, True
        if after_force:
            # the force loop streamed its positions a tick or two ahead of the slider: the next
            # step starts where the slider is, not where the stream had got to
            self._target_mm = self._last_pos
        self.index += 1
        self.step_t0 = t
        self._window.clear()
        self._contact_count = 0
        self._approach_stopping = False
        self._arrived = 0
        self._force_from = None
        # a force step handed over from another starts its clock at once: the probe is in contact
        self.force_t0 = t if after_force and self._in_contact else None
        self.force_seek_s = 0.0
        if self.index >= len(self.steps):
            self.done = True
            self._speed = 0.0
            return []
        step = self.step
        if not isinstance(step, FORCE_STEPS):
            self.setpoint_N = None
        if isinstance(step, Hold | RampForce | HoldForce):
            self._from_mm = self._target_mm
            self._speed = 0.0
            if isinstance(step, FORCE_STEPS):
                return self._tick_force(step, t, self._last_force)
            return [Stop("the force step ended: hold where the slider is")] if after_force else []
        self._from_mm = self._target_mm
        self._target_mm = self._resolve_target(step)
        self._speed = step.speed_mm_s
        self._step_accel = (step.accel_mm_s2 if isinstance(step, Ramp) else None) or self.accel
        return [Move(self._target_mm, self._speed, self._step_accel)]


def _slope(window: deque[tuple[float, float]]) -> float:
    n = len(window)
    if n < 3:
        return math.inf
    st = sf = stt = stf = 0.0
    t0 = window[0][0]
    for t, f in window:
        t -= t0
        st += t
        sf += f
        stt += t * t
        stf += t * f
    den = n * stt - st * st
    return (n * stf - st * sf) / den if den > 0 else math.inf
