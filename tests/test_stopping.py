"""The trial's ending as a state machine (rig.control.stopping): one test per transition, and
what each end state reports. The loop tests (test_trial, test_control_path, test_safety) run
the same machine against the simulated drive."""

from __future__ import annotations

import pytest

from rig.control.safety import Fault
from rig.control.states import EndingState, StopMode
from rig.control.stopping import TRANSITIONS, Ending

SETTLE_S, CONFIRM_S, RESEND_S = 0.5, 1.0, 0.1


def stopped(ending: Ending, t: float) -> Ending:
    """A STOP sent at t and confirmed by the next status."""
    ending.on_stop_sent(t)
    assert ending.on_status(t + 0.01, False, CONFIRM_S, RESEND_S) == ("confirmed", "")
    return ending


def test_running_ends_completed_when_the_protocol_is_done():
    e = Ending()
    assert e.result(3.0, SETTLE_S, protocol_done=False) is None
    assert e.result(3.0, SETTLE_S, protocol_done=True) == ("completed", None)


def test_running_to_faulted_ends_after_the_settle_time_with_the_fault():
    e = Ending()
    e.on_fault(Fault("force_limit", "force 5.2 N above the limit 5 N"), 2.0)
    stopped(e, 2.0)
    assert e.state is EndingState.FAULTED and e.outcome == "fault"
    assert e.result(2.2, SETTLE_S, protocol_done=True) is None  # the protocol does not end a fault
    assert e.result(2.5, SETTLE_S, protocol_done=False) == ("fault", "force 5.2 N above the limit 5 N")


def test_running_to_returning_on_abort_ends_aborted_once_back():
    e = Ending()
    assert e.on_request(StopMode.ABORT, 1.0) is None
    assert e.state is EndingState.RETURNING
    assert e.result(5.0, SETTLE_S, protocol_done=False) is None
    assert e.result(5.0, SETTLE_S, protocol_done=True) == ("aborted", None)


@pytest.mark.parametrize(("mode", "outcome"), [(StopMode.ESTOP, "estopped"), (StopMode.HOLD, "stopped")])
def test_running_to_stopping_ends_after_the_settle_time(mode, outcome):
    e = Ending()
    assert e.on_request(mode, 1.0) is None
    stopped(e, 1.0)
    assert e.state is EndingState.STOPPING
    assert e.result(1.4, SETTLE_S, protocol_done=True) is None
    assert e.result(1.5, SETTLE_S, protocol_done=False) == (outcome, None)


def test_returning_to_stopping_on_estop_restarts_the_settle_time():
    e = Ending()
    e.on_request(StopMode.ABORT, 1.0)
    assert e.on_request(StopMode.ESTOP, 3.0) is None
    stopped(e, 3.0)
    assert (e.state, e.outcome, e.since_t) == (EndingState.STOPPING, "estopped", 3.0)
    assert e.result(3.4, SETTLE_S, protocol_done=True) is None
    assert e.result(3.5, SETTLE_S, protocol_done=True) == ("estopped", None)


@pytest.mark.parametrize("mode", [StopMode.ABORT, StopMode.HOLD])
def test_returning_or_stopping_to_faulted(mode):
    e = Ending()
    e.on_request(mode, 1.0)
    e.on_fault(Fault("travel", "position 61 mm beyond the travel 60 mm"), 2.0)
    stopped(e, 2.0)
    assert (e.state, e.outcome) == (EndingState.FAULTED, "fault")
    assert e.result(2.5, SETTLE_S, protocol_done=True) == ("fault", "position 61 mm beyond the travel 60 mm")


@pytest.mark.parametrize("mode", list(StopMode))
def test_faulted_refuses_every_request(mode):
    e = Ending()
    e.on_fault(Fault("loadcell_stale", "no load-cell reading for 250 ms"), 1.0)
    assert e.on_request(mode, 1.5) == "already stopped by a fault: no load-cell reading for 250 ms"
    assert (e.state, e.mode, e.since_t) == (EndingState.FAULTED, None, 1.0)


@pytest.mark.parametrize(("first", "second"), [(StopMode.ABORT, StopMode.ABORT),
                                               (StopMode.HOLD, StopMode.ABORT),
                                               (StopMode.ESTOP, StopMode.HOLD)])
def test_a_second_request_other_than_estop_is_refused(first, second):
    e = Ending()
    e.on_request(first, 1.0)
    state = e.state
    assert e.on_request(second, 2.0) == f"already stopping ({first.value} in progress)"
    assert (e.state, e.mode, e.since_t) == (state, first, 1.0)


def test_a_hold_during_an_abort_cuts_the_return_short():
    """It used to be refused inside the machine while the loop answered it 'ok': the operator
    was told the slider held when it went on returning."""
    e = Ending()
    e.on_request(StopMode.ABORT, 1.0)
    assert e.on_request(StopMode.HOLD, 2.0) is None
    stopped(e, 2.0)
    assert (e.state, e.mode, e.since_t) == (EndingState.STOPPING, StopMode.HOLD, 2.0)
    assert e.result(2.5, SETTLE_S, protocol_done=False) == ("stopped", None)


@pytest.mark.parametrize("mode", [None, StopMode.HOLD, StopMode.ABORT])
def test_an_unconfirmed_stop_becomes_a_fault(mode):
    e = Ending()
    if mode is not None:
        e.on_request(mode, 1.0)
    e.on_stop_sent(1.0)
    actions = []
    for k in range(1, 66):  # ticks of 1/64 s, exact in binary
        t = 1.0 + k / 64
        actions.append(e.on_status(t, True, CONFIRM_S, 0.125))
        if actions[-1] == ("resend", ""):
            e.on_stop_sent(t)  # what the loop does: send it again
    resent = [k + 1 for k, a in enumerate(actions) if a == ("resend", "")]
    assert resent == [8, 16, 24, 32, 40, 48, 56, 64]  # every 1/8 s while the drive still moves
    kind, why = actions[-1]
    assert kind == "gave_up" and why.startswith("STOP not confirmed by the drive within 1 s (8 re-sends)")
    assert (e.state, e.fault.kind, e.since_t) == (EndingState.FAULTED, "stop_unconfirmed", 1.0 + 65 / 64)
    assert e.result(2.6, SETTLE_S, protocol_done=True) == ("fault", why)


def test_an_unconfirmed_stop_after_a_fault_is_added_to_its_message():
    e = Ending()
    e.on_fault(Fault("drive_alarm", "drive alarm code 0x30"), 1.0)
    e.on_stop_sent(1.0)
    kind, why = e.on_status(2.1, True, CONFIRM_S, RESEND_S)
    assert kind == "gave_up"
    assert (e.fault.kind, e.fault.message, e.since_t) == ("drive_alarm", f"drive alarm code 0x30; {why}", 1.0)


def test_stopping_waits_for_the_drive_to_confirm():
    e = Ending()
    e.on_request(StopMode.HOLD, 1.0)
    e.on_stop_sent(1.0)
    assert e.on_status(1.05, None, CONFIRM_S, RESEND_S) is None  # no fresh status: nothing known
    assert e.result(1.9, SETTLE_S, protocol_done=True) is None  # settle time over, STOP unconfirmed
    assert e.on_status(1.95, False, CONFIRM_S, RESEND_S) == ("confirmed", "")
    assert e.result(1.96, SETTLE_S, protocol_done=False) == ("stopped", None)
    assert e.on_status(2.0, True, CONFIRM_S, RESEND_S) is None  # once confirmed, it stays so


def test_a_new_move_releases_the_stop():
    """A protocol's own STOP (a hold after a ramp) is followed by the next move: nothing waits
    for its confirmation any more, and no fault comes of it."""
    e = Ending()
    e.on_stop_sent(1.0)
    e.on_move()
    assert e.stop is None
    assert e.on_status(5.0, True, CONFIRM_S, RESEND_S) is None
    assert e.state is EndingState.RUNNING and e.result(5.0, SETTLE_S, protocol_done=True) == ("completed", None)


def _documented_table() -> dict:
    """The transition table as the module's docstring shows it, read line by line."""
    import rig.control.stopping as stopping

    lines = stopping.__doc__.splitlines()
    head = next(i for i, line in enumerate(lines) if line.split() == ["from", "request", "to"])
    table = {}
    for line in lines[head + 1:]:
        if not line.strip():
            break
        state, rest = line.split(maxsplit=1)
        words, to = rest.split("    ", 1)
        to = to.strip().split("  ")[0].strip()
        for word in words.split(","):
            table[EndingState[state], StopMode(word.strip())] = (
                to.removeprefix("refused: ") if to.startswith("refused") else EndingState[to])
    return table


def test_the_code_consults_the_table_the_docstring_shows():
    assert _documented_table() == TRANSITIONS
    # every state meets every request in it: nothing is left to an `if` elsewhere
    assert set(TRANSITIONS) == {(s, m) for s in EndingState for m in StopMode}


@pytest.mark.parametrize(("state", "mode"), sorted(TRANSITIONS, key=str))
def test_every_transition_in_the_table_is_what_the_machine_does(state, mode):
    e = Ending()
    if state is EndingState.FAULTED:
        e.on_fault(Fault("force_limit", "force above the limit"), 1.0)
    elif state is not EndingState.RUNNING:
        e.on_request(StopMode.ABORT if state is EndingState.RETURNING else StopMode.HOLD, 1.0)
    assert e.state is state
    refused = e.on_request(mode, 2.0)
    to = TRANSITIONS[state, mode]
    if isinstance(to, EndingState):
        assert refused is None and e.state is to and e.mode is mode and e.since_t == 2.0
    else:
        assert refused.startswith(to) and e.state is state and e.since_t == 1.0


def test_a_word_from_the_socket_is_its_member_and_names_its_outcome():
    assert StopMode("hold") is StopMode.HOLD and StopMode.HOLD == "hold"
    assert [m.outcome for m in StopMode] == ["estopped", "stopped", "aborted"]
    with pytest.raises(ValueError):
        StopMode("halt")  # one word for staying in place: "hold"
