"""The words for a trial's states, one vocabulary per kind of state.

Each is a `StrEnum`: a member is its word (``Outcome.FAULT == "fault"``), so what goes into a
log, a socket reply or a JSON file is the word itself, and a word read back parses to the
member (``StopMode("hold")``).

- `StopMode`: what the operator asks for (the words of the socket API, the CLI and the web page).
- `Outcome`: how a trial ended, as its log, `rig run` and `rig status` say it.
- `TrialState`: what a watcher sees in the trial's `Snapshot` while it runs and after it ended.
- `Lifecycle`: who may use the bus: the trial starting, its loop running, the trial closing its
  log, or ended.
- `EndingState`: where the loop's ending stands (`rig.control.stopping.Ending`).

"Hold" is one thing: the probe stays where it is, as a protocol's hold step or as the stop
that keeps the probe in place (`StopMode.HOLD`, ending in `Outcome.STOPPED`). "Phase" is
kept for the segments of a record (approach, hold, return) that the analysis fits.
"""

from __future__ import annotations

from enum import StrEnum


class StopMode(StrEnum):
    """What the operator asks for."""

    ESTOP = "estop"  # stop the motor now, nothing else
    HOLD = "hold"  # stop and stay where it is
    ABORT = "abort"  # stop, then return to the start position at a safe speed

    @property
    def outcome(self) -> Outcome:
        """How a trial that this request ended is said to have ended."""
        return _OUTCOME_OF[self]


class Outcome(StrEnum):
    """How a trial ended."""

    COMPLETED = "completed"  # its protocol ran to the end
    STOPPED = "stopped"  # a hold: stopped where it was
    ESTOPPED = "estopped"  # an emergency stop: the motor stopped, nothing else
    ABORTED = "aborted"  # stopped, then returned to its start
    FAULT = "fault"  # a safety check, a device or the recording stopped it


_OUTCOME_OF = {StopMode.ESTOP: Outcome.ESTOPPED, StopMode.HOLD: Outcome.STOPPED,
               StopMode.ABORT: Outcome.ABORTED}


class TrialState(StrEnum):
    """The snapshot's state: idle before the first tick, running, stopping once a stop or a fault
    is being carried out, and at the end its outcome (``done`` for a completed protocol)."""

    IDLE = "idle"
    RUNNING = "running"
    STOPPING = "stopping"
    DONE = "done"
    STOPPED = "stopped"
    ESTOPPED = "estopped"
    ABORTED = "aborted"
    FAULT = "fault"

    @classmethod
    def ended(cls, outcome: Outcome) -> TrialState:
        """The state a trial is left in by `outcome`."""
        return cls.DONE if outcome is Outcome.COMPLETED else cls(outcome.value)

    @property
    def active(self) -> bool:
        """Running or stopping: the trial still owns the rig."""
        return self in (TrialState.RUNNING, TrialState.STOPPING)


class Lifecycle(StrEnum):
    """Who may use the bus. STARTING -> RUNNING -> CLOSING -> ENDED. While RUNNING the loop
    thread owns it and carries out stops on its next tick; at any other time a stop goes out at
    once from the thread that asks."""

    STARTING = "starting"
    RUNNING = "running"
    CLOSING = "closing"
    ENDED = "ended"


class EndingState(StrEnum):
    """Where a trial's ending stands: running its protocol, returning to the start (an abort),
    stopping where it is (a hold or an estop), or stopped by a fault."""

    RUNNING = "running"
    RETURNING = "returning"
    STOPPING = "stopping"
    FAULTED = "faulted"
