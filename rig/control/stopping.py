"""How a trial ends: the loop's stop and fault handling as one state machine.

The operator's requests move it by this table (`TRANSITIONS`, which the code consults and
tests/test_stopping.py holds to these lines):

    from        request        to
    RUNNING     estop, hold    STOPPING
    RUNNING     abort          RETURNING   (back to the start at a safe speed)
    RETURNING   estop, hold    STOPPING    (either cuts a return short: stop and stay)
    RETURNING   abort          refused: already stopping
    STOPPING    estop          STOPPING    (an estop overrides a hold)
    STOPPING    hold, abort    refused: already stopping
    FAULTED     estop, hold, abort    refused: already stopped by a fault

A fault takes RUNNING, RETURNING or STOPPING to FAULTED, and so does a STOP that the drive
does not confirm (its communication timeout is then the backstop).

A refused request is answered as refused, with the reason: the operator is never told that
something was done that was not.

It ends FAULTED or STOPPING once `settle_s` has passed since the fault or the request and the
drive has confirmed the STOP (or the wait for that ran out); RUNNING or RETURNING once the
protocol (or the return) is done. The loop does the sending and the logging; this decides.
"""

from __future__ import annotations

from dataclasses import dataclass

from rig.control.safety import Fault
from rig.control.states import EndingState, Outcome, StopMode

_R, _T, _S, _F = EndingState.RUNNING, EndingState.RETURNING, EndingState.STOPPING, EndingState.FAULTED
ALREADY_STOPPING = "already stopping"
BY_A_FAULT = "already stopped by a fault"

# (state, request) -> the next state, or the reason the request is refused
TRANSITIONS: dict[tuple[EndingState, StopMode], EndingState | str] = {
    (_R, StopMode.ESTOP): _S, (_R, StopMode.HOLD): _S, (_R, StopMode.ABORT): _T,
    (_T, StopMode.ESTOP): _S, (_T, StopMode.HOLD): _S, (_T, StopMode.ABORT): ALREADY_STOPPING,
    (_S, StopMode.ESTOP): _S, (_S, StopMode.HOLD): ALREADY_STOPPING, (_S, StopMode.ABORT): ALREADY_STOPPING,
    **{(_F, mode): BY_A_FAULT for mode in StopMode},
}


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
    """How a trial ends, as a small state machine: ``state`` (running, stopping, returning,
    faulted), the operator's ``mode`` (hold, abort, estop) or the ``fault`` that ended it,
    ``since_t`` (when: the settle time counts from there) and the STOP standing (``stop``).

    ``on_request`` takes an operator's request or says why it is refused (a fault already
    stopped the trial; another stop is in progress, unless an estop overrides it or a hold cuts
    an abort's return); ``on_fault`` takes precedence over everything. ``outcome`` is what the
    operator is told.
    """

    state: EndingState = EndingState.RUNNING
    mode: StopMode | None = None
    fault: Fault | None = None
    since_t: float = 0.0  # when the request or the fault came: the settle time counts from here
    stop: StopSent | None = None  # the STOP standing, if any

    @property
    def outcome(self) -> Outcome:
        if self.state is EndingState.FAULTED:
            return Outcome.FAULT
        return self.mode.outcome if self.mode is not None else Outcome.COMPLETED

    def on_fault(self, found: Fault, t: float) -> None:
        self.state, self.fault, self.since_t = EndingState.FAULTED, found, t

    def on_request(self, mode: StopMode, t: float) -> str | None:
        """Take an operator's request by `TRANSITIONS`; the reason when it is refused."""
        to = TRANSITIONS[self.state, mode]
        if not isinstance(to, EndingState):  # refused: say why
            return f"{to}: {self.fault.message}" if to == BY_A_FAULT else f"{to} ({self.mode} in progress)"
        self.mode, self.since_t, self.state = mode, t, to
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

    def result(self, t: float, settle_s: float, protocol_done: bool) -> tuple[Outcome, str | None] | None:
        """(outcome, fault message) once the trial is over, else None."""
        if self.state in (EndingState.FAULTED, EndingState.STOPPING):
            settled = self.stop is None or self.stop.settled
            if t - self.since_t >= settle_s and settled:
                return self.outcome, self.fault.message if self.fault else None
            return None
        return (self.outcome, None) if protocol_done else None
