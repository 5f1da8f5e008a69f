"""How a trial ends: the loop's stop and fault handling as one state machine.

    RUNNING   --fault-->                 FAULTED
    RUNNING   --abort-->                 RETURNING   (back to the start at a safe speed)
    RUNNING   --estop | halt-->          STOPPING
    RETURNING --estop | halt-->          STOPPING    (either cuts a return short: stop and stay)
    RETURNING | STOPPING --fault-->      FAULTED
    any       --STOP unconfirmed-->      FAULTED     (the drive's comm timeout is the backstop)
    FAULTED   --any request-->           refused: already stopped by a fault
    RETURNING --abort-->                 refused: already returning
    STOPPING  --abort | halt-->          refused: already stopping

A refused request is answered as refused, with the reason: the operator is never told that
something was done that was not.

It ends FAULTED or STOPPING once `settle_s` has passed since the fault or the request and the
drive has confirmed the STOP (or the wait for that ran out); RUNNING or RETURNING once the
protocol (or the return) is done. The loop does the sending and the logging; this decides.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from rig.control.safety import Fault


class StopMode(enum.Enum):
    """What the operator asks for; the values are the words of the socket API and the CLI."""

    ESTOP = "estop"  # stop the motor now, nothing else
    HALT = "hold"  # stop and stay where it is
    ABORT = "abort"  # stop, then return to the start position at a safe speed


class Phase(enum.Enum):
    """Where a trial's ending stands: running its protocol, returning to the start (an abort),
    stopping where it is (a hold or an estop), or stopped by a fault."""

    RUNNING = "running"
    RETURNING = "returning"
    STOPPING = "stopping"
    FAULTED = "faulted"


OUTCOMES = {StopMode.ESTOP: "estopped", StopMode.HALT: "stopped", StopMode.ABORT: "aborted"}


@dataclass
class StopSent:
    """A STOP sent to the drive and not yet confirmed by a fresh status saying 'not moving'."""

    sent_t: float
    last_sent_t: float
    resends: int = 0
    confirmed: bool = False
    gave_up: bool = False

    @property
    def settled(self) -> bool:
        return self.confirmed or self.gave_up


@dataclass
class Ending:
    """How a trial ends, as a small state machine: ``phase`` (running, stopping, returning,
    faulted), the operator's ``mode`` (hold, abort, estop) or the ``fault`` that ended it,
    ``since_t`` (when: the settle time counts from there) and the STOP standing (``stop``).

    ``on_request`` takes an operator's request or says why it is refused (a fault already
    stopped the trial; another stop is in progress, unless an estop overrides it or a hold cuts
    an abort's return); ``on_fault`` takes precedence over everything. ``outcome`` is what the
    operator is told.
    """

    phase: Phase = Phase.RUNNING
    mode: StopMode | None = None
    fault: Fault | None = None
    since_t: float = 0.0  # when the request or the fault came: the settle time counts from here
    stop: StopSent | None = None  # the STOP standing, if any

    @property
    def outcome(self) -> str:
        if self.phase is Phase.FAULTED:
            return "fault"
        return OUTCOMES[self.mode] if self.mode is not None else "completed"

    def on_fault(self, found: Fault, t: float) -> None:
        self.phase, self.fault, self.since_t = Phase.FAULTED, found, t

    def on_request(self, mode: StopMode, t: float) -> str | None:
        """Take an operator's request; the reason when it is refused."""
        if self.phase is Phase.FAULTED:
            return f"already stopped by a fault: {self.fault.message}"
        cuts_return = self.phase is Phase.RETURNING and mode is StopMode.HALT
        if self.mode is not None and mode is not StopMode.ESTOP and not cuts_return:
            return f"already stopping ({self.mode.value} in progress)"
        self.mode, self.since_t = mode, t
        self.phase = Phase.RETURNING if mode is StopMode.ABORT else Phase.STOPPING
        return None

    def on_stop_sent(self, t: float) -> None:
        if self.stop is None:
            self.stop = StopSent(t, t)
        self.stop.last_sent_t = t

    def on_move(self) -> None:
        self.stop = None  # a new move releases the STOP

    def on_status(self, t: float, moving: bool | None, confirm_s: float,
                  resend_s: float) -> tuple[str, str] | None:
        """What a tick's status means for a standing STOP: ('confirmed', ''), ('gave_up', why)
        (now FAULTED, or the fault says so too), ('resend', ''), or None."""
        s = self.stop
        if s is None or s.settled:
            return None
        if moving is False:
            s.confirmed = True
            return "confirmed", ""
        if t - s.sent_t > confirm_s:
            s.gave_up = True
            msg = (f"STOP not confirmed by the drive within {confirm_s:g} s ({s.resends} re-sends); "
                   "its communication timeout is the backstop")
            if self.fault is not None:
                self.fault = Fault(self.fault.kind, f"{self.fault.message}; {msg}")
            else:
                self.on_fault(Fault("stop_unconfirmed", msg), t)
            return "gave_up", msg
        if t - s.last_sent_t >= resend_s:
            s.resends += 1
            return "resend", ""
        return None

    def result(self, t: float, settle_s: float, protocol_done: bool) -> tuple[str, str | None] | None:
        """(outcome, fault message) once the trial is over, else None."""
        if self.phase in (Phase.FAULTED, Phase.STOPPING):
            settled = self.stop is None or self.stop.settled
            if t - self.since_t >= settle_s and settled:
                return self.outcome, self.fault.message if self.fault else None
            return None
        return (self.outcome, None) if protocol_done else None
