"""The acquisition loop: one tick every 1/rate_Hz seconds.

A tick is a short sequence of named stages (`Trial._loop`): read (the load cell and the
slider position, status/alarm every `status_every` ticks, a tick later when a force step's
move is due on it), check (the limits), operator
(stop requests), confirm (a STOP until the drive stands still), command (the step's
controller: the sequencer issues at most one command, each move checked against the limits
first, then watched until it arrives by its deadline), estimate (the RLS estimator), record
(one sample queued for the recorder). Each stage is a method on what the loop carries
(`_Loop`) and what the tick read (`_Tick`), so a new kind of step changes `command` alone.
On any fault the slider is told to stop before anything else happens; the STOP is
re-sent until a fresh status says the drive stands still, the loop keeps logging for
`post_fault_s` so the log shows the stop, and finishes the log. The loop never
writes to a terminal or a socket: displays read `Trial.snapshot` from their own
threads.

Timing: ticks are scheduled on a fixed grid t0 + k/rate. A tick that starts more than
`late_tolerance_ms` after its slot is counted late (and `late_ms` is in every
sample); if the loop falls a whole period behind, the skipped slots are counted as
missed, never silently dropped.
"""

from __future__ import annotations

import gc
import math
import socket
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from rig import __version__
from rig.clock import Clock, RealClock, slots_behind
from rig.control.estimator import StiffnessRLS
from rig.control.force import STIFFNESS_FLOOR_SHARE, ForceLoop
from rig.control.forcestats import StepFigures, StepMeter
from rig.control.movewatch import MoveWatch
from rig.control.safety import Fault, SpeedMeter, TickState, check, check_move
from rig.control.sensorwatch import CellNoise, CellWatch, Contact, MotionAnswer, answer_limit_mm
from rig.control.sequencer import Move, Sequencer, Stop, Track
from rig.control.states import Lifecycle, Outcome, StopMode, TrialState
from rig.control.stopping import Ending
from rig.control.zero import Zero, known_zero
from rig.drivers.base import ForceReading, LinkStats, LoadCell, Reading, Slider, SliderStatus
from rig.errors import DeviceError, RigError
from rig.models.online import OnlineModel
from rig.models.saved import SavedModel
from rig.realtime import Realtime, RealtimeState
from rig.recording.messages import EVENT, HEALTH, SAMPLE
from rig.recording.names import file_part
from rig.recording.recorder import Recorder, TrialInfo
from rig.specs.config import RigConfig
from rig.specs.protocol import FORCE_STEPS, Approach, Protocol, RampForce, check_limits

# A force step's depth budget: from the surface, the depth at which the stiffness read when the
# force first reached BUDGET_AT_SHARE of the step's setpoint would carry the force limit. A
# specimen that stiffens reaches the limit before it (the per-tick limit stops it); one that
# tears or a cell that lies stops there
BUDGET_AT_SHARE = 0.5
DRIVE_FOLLOW_S = 1.0  # a drive that has not moved this long while the force loop asked its fastest: a fault
DRIVE_STUCK_MM = 0.05  # "not moved": a few encoder steps
SETPOINT_MISS = 0.05  # a force step that ends further than this from its setpoint is said
# A move is an FC16 write of 16 registers: over RTU at 115200 baud with an adapter's 1 ms it takes
# 6 ms of the bus, and a position read 3.5 ms more: every tick's move would fill the 10 ms tick
# and time out under load. The force loop sends a new target every FORCE_MOVE_TICKS ticks (its
# 8 rad/s crossover is far below 50 Hz), and only when it moved by a drive step.
FORCE_MOVE_TICKS = 2


@dataclass
class Snapshot:
    """What a watcher sees; replaced (not mutated) every tick, so reading it needs no lock."""

    state: TrialState = TrialState.IDLE
    t_s: float = 0.0
    step: int = -1
    step_kind: str = "tare"
    steps_total: int = 0
    time_left_s: float = 0.0
    force_N: float = 0.0
    position_mm: float = 0.0
    stiffness_N_per_m: float = 0.0
    log_path: str = ""
    fault: str = ""
    force_model_N: float | None = None  # the loaded model's force, when one runs in the loop
    preload_N: float = 0.0  # force the probe carried at the tare: force_N + preload_N is absolute
    force_steps: tuple = ()  # the figures of each force step ended so far (`StepFigures.as_dict`)


@dataclass(frozen=True)
class EndPlace:
    """Where the probe was on the trial's last tick, and whether it pressed on the specimen (the
    contact watch of `sensorwatch.Contact`): a trial cut short by an estop or a fault leaves the
    probe where it stopped, which may be in the tissue."""

    position_mm: float  # the slider's position (the drive's frame)
    surface_mm: float  # where the probe was on the last tick out of contact
    in_contact: bool
    force_N: float  # the force the tissue carried, preload included

    @property
    def depth_mm(self) -> float:
        return self.position_mm - self.surface_mm


@dataclass
class TrialResult:
    """How a trial ended, as the operator is told: the ``outcome`` (and the ``fault`` if one
    ended it), the log, the samples recorded, the loop's timing (late and missed ticks, the
    period errors) and the bus's transactions and errors; ``notices``: what the operator should
    know of a trial that completed."""

    outcome: Outcome
    log_path: Path
    samples: int
    late_ticks: int
    missed_ticks: int
    duration_s: float
    fault: str | None = None
    period_errors_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bus_transactions: int = 0
    notices: list[str] = field(default_factory=list)  # what the operator should know of a completed trial
    bus_errors: int = 0  # failed transactions over the whole trial (the log's health lags by up to a period)


@dataclass
class _Loop:
    """What a trial's loop carries from one tick to the next."""

    t0_s: float
    sequencer: Sequencer
    ending: Ending
    speedometer: SpeedMeter
    force_loop: ForceLoop
    taring: bool
    zero_N: float | None
    next_health_s: float
    return_speed_mm_s: float
    status: SliderStatus = field(default_factory=lambda: SliderStatus(True, False, True, False))
    watch: MoveWatch | None = None
    slot: int = 0
    tare_sum: float = 0.0
    tare_n: int = 0
    tare_N: float = 0.0
    preload_N: float = 0.0
    x_prev_m: float = 0.0
    last_step: int = -2
    health_mark: int = 0
    stiffness_N_per_m: float = 0.0  # the force loop's gain: the stiffness from the surface found
    in_contact: bool = False  # the probe pushes on the specimen (`sensorwatch.Contact`)
    noise: CellNoise | None = None  # the load cell's noise, once the tare has measured it
    tare_values: list = field(default_factory=list)  # the tare's new readings
    last_reading_t: float | None = None  # the timestamp of the last new reading
    cell_watch: CellWatch | None = None
    contact: Contact | None = None
    loop_rls: StiffnessRLS | None = None  # the stiffness referenced to the surface, for the gain
    x_contact_prev_m: float = 0.0
    motion: MotionAnswer | None = None
    meter: StepMeter | None = None  # the force step being measured
    budget_mm: float | None = None  # the force segment's depth budget (absolute), once known
    carry_peak_N: float = -math.inf  # a force ramp's peak, carried into the hold it hands over to
    at_budget: bool = False
    figures: list = field(default_factory=list)  # StepFigures of the force steps ended
    force_error_N: float | None = None  # a force step's setpoint less the force, this tick
    force_step: int = -1  # the force step being followed (its index), -1 none
    force_recent: list = field(default_factory=list)  # (t, force, setpoint) over the step's last 0.5 s
    at_depth_limit: bool = False  # the step's max_mm stopped the force loop (said once per step)
    saturated_since: tuple[float, float] | None = None  # (t, position) when the speed cap began to bind
    sent_target: float | None = None  # the force loop's last target sent to the drive
    sent_seq: int = -1000  # the tick it was sent on
    status_seq: int = -1000  # the tick status and alarm were last read on


@dataclass
class _Tick:
    """One tick's readings, as `_read` took them. Times are the clock's, in seconds."""

    now_s: float  # the clock when the tick woke
    t_s: float  # since the first tick's slot (the log's t_s)
    t_log_s: float  # t_s as logged (to the microsecond)
    lateness_s: float  # how late the tick woke against its slot
    reading: ForceReading | None  # the load cell's newest reading (None: none yet, or no cell)
    position: Reading[float]  # the slider's position read, with its freshness
    position_mm: float  # its value
    x_rel_mm: float  # from the trial's zero as it stood at the tick's start
    force_model_N: float | None  # the loaded model's force, when one runs in the loop
    moving: bool | None  # the drive's "moving", from a fresh status read this tick (None: none)
    speed_mm_s: float | None  # from fresh positions (`SpeedMeter`)
    raw_N: float  # the load cell's force as read (or the model's, without a cell)
    age_s: float | None  # the reading's age
    force_N: float  # from the tare: what is logged and sequenced
    checked_N: float  # what the limits see: from the free-air zero, preload included
    status_read: bool = False  # status and alarm were read on this tick (fresh or not)
    new_reading: bool = False  # the load cell's reading is one not seen on an earlier tick


class StopTicket:
    """The answer to a stop request: set once the STOP was sent (or could not be, or was refused)."""

    def __init__(self, mode: StopMode) -> None:
        self.mode = mode
        self.done = threading.Event()
        self.acknowledged = False  # the drive acknowledged the STOP write
        self.message = ""
        self.trial_over = False  # the trial had ended: nothing was done, the caller stops it itself

    def settle(self, acknowledged: bool, message: str) -> None:
        if self.done.is_set():  # the first answer is the one the caller may already have read
            return
        self.acknowledged, self.message = acknowledged, message
        self.done.set()

    def wait(self, timeout_s: float) -> bool:
        return self.done.wait(timeout_s)


class Trial:
    """One trial of a protocol on a slider and a load cell: the 100 Hz loop, its safety checks,
    the estimator and the log.

    ``run()`` tares, runs the steps and writes the MCAP log; ``request_stop``
    asks for a hold, an abort or an estop (`Ending`); a fault stops the slider before anything
    else happens. The outcome, the log's name and the loop's health come back in the result.
    """

    post_fault_s = 0.5
    return_speed_mm_s = 5.0
    resend_stop_s = 0.1  # re-send an unconfirmed STOP this often
    close_timeout_s = 30.0  # a log not finished by then is reported so, not as "completed"

    def __init__(self, proto: Protocol, config: RigConfig, slider: Slider, loadcell: LoadCell,
                 clock: Clock, log_path: Path, info: TrialInfo | None = None,
                 *, start_mm: float | None = None, model: SavedModel | None = None,
                 zero: Zero | None = None) -> None:
        """`zero`: the load cell's free-air zero an earlier trial used (a daemon remembers it);
        a configured or `rig tare`-saved zero takes precedence (`rig.control.zero`)."""
        self.proto = proto
        self.config = config
        self.limits = proto.effective_limits(config.limits)
        self.slider = slider
        self.loadcell = loadcell
        self.clock = clock
        self.log_path = Path(log_path)
        # set once the log's name is final (the recorder may take the next free one) or the trial
        # ended before opening it: a caller that reports the name waits for this
        self.log_named = threading.Event()
        self.recorder: Recorder | None = None  # once the log is open
        self.info = info or TrialInfo()
        self.rate = config.loop.rate_Hz
        self.period = 1.0 / self.rate
        self._start_mm = start_mm
        self._stop_request: tuple[StopMode, str, float, StopTicket] | None = None
        self._tickets: list[StopTicket] = []
        self._lock = threading.Lock()
        # While RUNNING, the loop thread owns the bus and carries out stops on its next tick; at
        # any other time a stop goes out at once from the requesting thread, under this lock (the
        # trial thread holds it for its own bus use).
        self._lifecycle = Lifecycle.STARTING
        self._bus_lock = threading.Lock()
        # Set by a signal handler (plain assignment, no lock): the loop turns it into a request.
        self.signal_stop: StopMode | None = None
        self.signal_handled: StopMode | None = None
        self.zero: Zero | None = (known_zero(config) if loadcell is not None else None) or zero
        self.preload_N: float | None = None  # known once the tare is done
        self.snapshot = Snapshot(steps_total=proto.executed_steps, log_path=str(log_path))
        est = config.estimator
        self.rls = StiffnessRLS.from_config(est, self.rate)
        # Optional callable(Snapshot), called every tick on the loop thread: it must not block
        # (no terminal, socket or disk); displays read `snapshot` from their own thread.
        self.on_tick = None
        self.realtime: RealtimeState | None = None
        self.model = model
        self.online = OnlineModel(model.model, model.values, self.period) if model is not None else None
        if loadcell is None and self.online is None:
            raise RigError("loadcell.backend is none: the force can only come from a model; give --model "
                           "MODEL.json (or model: in the config)")
        if loadcell is None and any(isinstance(s, Approach) for s in proto.steps):
            raise RigError(f"{proto.source_path}: an approach step finds contact by force: it needs a "
                           "load cell")
        self.live = None  # a rig.service.live.LiveView publishing the same messages, if any
        self.warnings: list[str] = []
        self.notices: list[str] = []  # a completed trial's news for the operator (a force not held)
        self.end_place: EndPlace | None = None  # set on the last tick, once the load cell was tared
        if loadcell is not None and self.zero is None:
            self.warnings.append(
                "no free-air zero known for the load cell: this trial's tare is assumed to be taken "
                "out of contact, so a preload at the start would not count against the force limit "
                "(`rig tare` with the probe out of contact, or loadcell.zero_N, fixes that)")
        # the load cell's calibration (`rig calibrate`): its age said now, a force beyond its range
        # said once, when it comes (an event in the log and a notice)
        from rig.control.calibration import calibration_warnings

        self.calibration_warnings = calibration_warnings(config) if loadcell is not None else []
        self.warnings += self.calibration_warnings
        cal = config.calibration if loadcell is not None else None
        self._cal_max_N = cal.range_N[1] if cal is not None and cal.range_N[1] > 0 else math.inf
        self._samples = self._late = self._missed = 0
        self._tick_times: list[float] = []
        self._t0: float | None = None

    # ------------------------------------------------------------- control
    def request_stop(self, mode: StopMode = StopMode.ABORT, user: str = "",
                     received_s: float | None = None) -> StopTicket:
        """Thread-safe, at any moment of the trial's life. While the loop runs, it carries the
        request out on its next tick (it owns the bus); while the trial starts or closes, the
        STOP goes out at once from here (and a trial that has not ticked yet also honours the
        request on its first tick, so nothing moves). Not from a signal handler: it takes locks
        (set `signal_stop` instead).

        `received_s` is when the request arrived (time.monotonic()); the stop event records the
        latency from then to the stop command acknowledged on the bus. The ticket tells the
        caller when the STOP went out and whether the drive acknowledged it.
        """
        ticket = StopTicket(mode)
        received = received_s if received_s is not None else time.monotonic()
        with self._lock:
            lifecycle = self._lifecycle
            if lifecycle is Lifecycle.ENDED:
                ticket.trial_over = True
                ticket.settle(False, "the trial has ended")
                return ticket
            self._tickets.append(ticket)
            if self._stop_request is None or mode == StopMode.ESTOP:
                self._stop_request = (mode, user, received, ticket)
        if lifecycle is not Lifecycle.RUNNING:
            self._stop_now(received)
        return ticket

    @property
    def started_s(self) -> float | None:
        """The clock's reading at the first tick's slot (the log's t_s = 0); None before it."""
        return self._t0

    @property
    def lifecycle(self) -> Lifecycle:
        """Starting, running (the loop owns the bus), closing its log, or ended."""
        return self._lifecycle

    def _stop_now(self, received: float, timeout_s: float = 1.0) -> None:
        """Send STOP from this thread while the loop is not running, and settle every waiting
        ticket with the drive's answer. If the loop starts meanwhile, it has the request."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self._bus_lock.acquire(timeout=0.005):
                try:  # holding the bus lock, the loop cannot be running
                    lifecycle = self._lifecycle
                    ok = self._safe_stop()
                finally:
                    self._bus_lock.release()
                latency_ms = round((time.monotonic() - received) * 1000.0, 3)
                when = ("before its first tick" if lifecycle is Lifecycle.STARTING
                        else "while it closed its log")
                self._settle_tickets(ok, f"STOP sent in {latency_ms:g} ms ({when}), acknowledged by the drive"
                                     if ok else f"STOP sent ({when}) but not acknowledged by the drive (the "
                                     "drive's communication timeout is the backstop)")
                return
            with self._lock:
                if self._lifecycle is Lifecycle.RUNNING:
                    return  # the loop took the bus: it carries the request out on its next tick
            if time.monotonic() > deadline:
                self._settle_tickets(False, f"STOP not sent: the bus stayed busy for {timeout_s:g} s")
                return

    def _take_stop_request(self) -> tuple[StopMode, str, float, StopTicket] | None:
        with self._lock:
            req, self._stop_request = self._stop_request, None
        return req

    def _settle_tickets(self, acknowledged: bool, message: str) -> None:
        with self._lock:
            tickets, self._tickets = self._tickets, []
        for ticket in tickets:
            if not ticket.done.is_set():
                ticket.settle(acknowledged, message)

    # ------------------------------------------------------------- the run
    def run(self) -> TrialResult:
        """Check the limits from where the slider is, then run; `LimitError` before anything moves."""
        try:
            return self._run()
        finally:
            self.log_named.set()
            with self._lock:  # the caller may hand the devices to others now: no more bus use here
                self._lifecycle = Lifecycle.ENDED

    def _run(self) -> TrialResult:
        cfg = self.config
        with self._bus_lock:
            start = self.slider.position()
        if not start.fresh:
            raise DeviceError("cannot read the slider's position: not starting")
        if self._start_mm is None:
            self._start_mm = start.value
        check_limits(self.proto, cfg, start_mm=self._start_mm)
        recorder = Recorder(self.log_path, flush_s=cfg.recorder.flush_s,
                            compression=cfg.recorder.compression, max_queue=cfg.recorder.max_queue)
        self.recorder = recorder
        self.log_path = recorder.path  # the name the recorder could take (another run may have had ours)
        self.log_named.set()
        # After the recorder's thread exists, so only the loop thread runs at real-time priority.
        rt = Realtime(cfg.loop.realtime, cfg.loop.realtime_priority) if isinstance(self.clock, RealClock) \
            else None
        try:
            helpers = [getattr(recorder, "thread", None), getattr(self.loadcell, "thread", None),
                       getattr(self.live, "thread", None)]
            self.realtime = rt.enter(helpers) if rt else RealtimeState("virtual clock", False, "")
        except RigError:
            recorder.close()
            self.log_path.unlink(missing_ok=True)
            raise
        _warm_up()
        # A full collection mid-trial walks every object the interpreter holds (numpy, pymodbus,
        # ...): milliseconds. Collect now and freeze what exists, so later passes are short.
        gc.collect()
        gc.freeze()
        self._t0 = self.clock.now()
        self._write_header(recorder, self._t0)
        # Let the writer put the header on disk before the first tick is due.
        recorder.wait_idle(timeout_s=2.0)
        # Last, right before the first tick: a polled cell's reading ages from its reply, and
        # the header's fsync above can take longer than the stale limit on a busy disk.
        if self.loadcell is not None:
            self._prime_loadcell()
        t0 = self._t0 = self.clock.now()
        outcome, fault_msg = Outcome.COMPLETED, None
        self._bus_lock.acquire()
        with self._lock:
            self._lifecycle = Lifecycle.RUNNING
        try:
            outcome, fault_msg = self._loop(recorder, t0)
        except BaseException as exc:  # a bug or a lost device: stop first, then record it
            self._safe_stop()
            outcome = Outcome.FAULT
            fault_msg = str(exc) if isinstance(exc, RigError) else f"{type(exc).__name__}: {exc}"
            self._event(recorder, self.clock.now() - t0, "fault", fault_msg, {"kind": "exception"})
            if not isinstance(exc, Exception):
                raise
        finally:
            self._leave_loop()
            if rt is not None:
                rt.leave()
            t_end = self.clock.now() - t0
            if recorder.failure and outcome is not Outcome.FAULT:
                outcome, fault_msg = Outcome.FAULT, recorder.failure
            self._event(recorder, t_end, "trial_end", f"trial {outcome}",
                        {"outcome": outcome, "samples": self._samples})
            recorder.close({"outcome": outcome, "samples": str(self._samples),
                            "late_ticks": str(self._late), "missed_ticks": str(self._missed),
                            "duration_s": f"{t_end:.3f}", "fault": fault_msg or "",
                            "end_time": datetime.now(UTC).isoformat()}, timeout_s=self.close_timeout_s)
            if recorder.failure and fault_msg and "recording" not in fault_msg:
                fault_msg = f"{fault_msg}; {recorder.failure}"
            if recorder.unfinished:
                fault_msg = f"{fault_msg}; {recorder.unfinished}" if fault_msg else recorder.unfinished
                outcome = Outcome.FAULT
            if recorder.error is not None:
                fault_msg = (fault_msg or recorder.failure) + (
                    f"; the log holds what was flushed before the failure ({recorder.flushed_messages} "
                    "messages); `rig replay` reads it")
                outcome = Outcome.FAULT
            self.snapshot = replace(self.snapshot, state=TrialState.ended(outcome),
                                     fault=fault_msg or "")
            gc.unfreeze()
        periods = np.diff(np.asarray(self._tick_times)) if len(self._tick_times) > 1 else np.zeros(0)
        return TrialResult(outcome, self.log_path, self._samples, self._late, self._missed,
                           self.clock.now() - t0, fault_msg,
                           np.abs(periods - self.period) * 1000.0,
                           self.slider.stats.transactions, list(self.notices),
                           bus_errors=self.slider.stats.errors)

    def _leave_loop(self) -> None:
        """From now on stops go out at once; one that came after the loop's last tick goes now."""
        with self._lock:
            self._lifecycle = Lifecycle.CLOSING
            waiting = any(not t.done.is_set() for t in self._tickets)
            req = self._stop_request
        self._bus_lock.release()
        if waiting:
            self._stop_now(req[2] if req is not None else time.monotonic())

    def _prime_loadcell(self, timeout_s: float = 3.0) -> None:
        """Wait (real time) for a reading taken after now: a polled cell answers only after a
        request, and a reading left over from an earlier trial must not pass as fresh."""
        since = self.clock.now()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            r = self.loadcell.latest()
            if r is not None and r.t_s >= since:
                return
            time.sleep(0.002)

    def _write_header(self, recorder: Recorder, t0: float) -> None:
        info = self.info
        now_ns = self.clock.wall_ns(t0)
        recorder.write_metadata("trial", {
            "specimen": info.specimen, "operator": info.operator,
            "protocol_name": self.proto.name, "protocol_path": self.proto.source_path,
            "config_name": self.config.name, "config_path": self.config.source_path,
            "config_digest": self.config.digest(),
            "start_time": datetime.fromtimestamp(now_ns / 1e9, UTC).isoformat(),
            "software_version": __version__, "host": socket.gethostname(),
            "clock": info.clock, "rate_Hz": f"{self.rate:g}", "notes": info.notes,
            "python": sys.version.split()[0], "start_mm": f"{self._start_mm:.4f}",
            "realtime": self.realtime.describe() if self.realtime else "",
            "force_source": "load cell" if self.loadcell is not None else "model (no load cell)",
            "model": self.model.model.name if self.model is not None else "",
            "loadcell_zero_N": "" if self.zero is None else f"{self.zero.value_N:.6g}",
            "loadcell_zero_source": "" if self.loadcell is None else self.zero.source if self.zero else
            "none known: the tare is assumed to be taken out of contact", **info.extra,
        })
        if self.loadcell is not None and self.config.calibration is not None:
            from rig.control.calibration import header

            recorder.write_metadata("calibration", {**header(self.config.calibration),
                                                    "warnings": " | ".join(self.calibration_warnings)})
        for w in self.calibration_warnings:
            self._event(recorder, 0.0, "calibration_warning", w)
        recorder.attach("protocol.yaml", "application/yaml", self.proto.source_text.encode(), now_ns)
        recorder.attach("config.yaml", "application/yaml", self.config.text().encode(), now_ns)
        if self.model is not None:
            recorder.attach("model.json", "application/json", self.model.text().encode(), now_ns)

    def _emit(self, recorder: Recorder, topic: str, log_time_ns: int, message: dict) -> None:
        """To the log, and to the live view if there is one (both only queue it)."""
        recorder.put(topic, log_time_ns, message)
        if self.live is not None:
            self.live.put(topic, log_time_ns, message)

    def _event(self, recorder: Recorder, t: float, kind: str, message: str, data: dict | None = None) -> None:
        self._emit(recorder, EVENT.topic, self.clock.wall_ns(self._t0 + t),
                   EVENT.record(t_s=round(t, 6), kind=kind, message=message, data=data or {}))

    def _safe_stop(self) -> bool:
        # nothing more can be done from here if this fails: the drive's comm timeout is the backstop
        try:
            return bool(self.slider.stop())
        except Exception:  # noqa: BLE001 - a dead link; the backstop takes over
            return False

    def _loop(self, recorder: Recorder, t0: float) -> tuple[str, str | None]:
        """One tick per slot, in this order (safety's place in it visible here): read, check
        (a fault stops the slider before anything else), operator (stop requests), confirm (a
        STOP stands until the drive says it stands still), command (the step's controller),
        estimate, record; then whether the trial has ended."""
        loop = self._start_loop(recorder, t0)
        while True:
            tick = self._read(loop)
            self._check(recorder, loop, tick)
            self._operator(recorder, loop, tick)
            self._confirm(recorder, loop, tick)
            self._command(recorder, loop, tick)
            est = self._estimate(loop, tick)
            self._record(recorder, loop, tick, est)
            done = loop.ending.result(tick.t_s, self.post_fault_s, loop.sequencer.done and loop.watch is None)
            if done is not None:
                if loop.contact is not None:
                    self.end_place = EndPlace(tick.position_mm, loop.contact.surface_mm, loop.in_contact,
                                              tick.checked_N)
                return done

    def _start_loop(self, recorder: Recorder, t0: float) -> _Loop:
        cfg = self.config
        self._samples = self._late = self._missed = 0
        self._tick_times = []
        self._last_age: float | None = None
        seq = Sequencer(self.proto, start_mm=self._start_mm, accel_mm_s2=cfg.slider.accel_mm_s2,
                        tare_s=cfg.loop.tare_s, tolerance_mm=cfg.slider.position_tolerance_mm,
                        rate_Hz=self.rate)
        self._event(recorder, 0.0, "trial_start", f"protocol '{self.proto.name}'",
                    {"specimen": self.info.specimen, "start_mm": self._start_mm,
                     "steps": len(seq.steps)})
        if self.online is not None:
            self.online.reset()
        self.snapshot = replace(self.snapshot, state=TrialState.RUNNING)
        lim = self.limits
        span_m = max(lim.travel_mm[1] - lim.travel_mm[0], 1e-3) / 1000.0
        force_loop = ForceLoop(self.period, lim.max_speed_mm_s,
                               STIFFNESS_FLOOR_SHARE * lim.max_force_N / span_m,
                               min_lead_mm=3.0 / self.config.slider.steps_per_mm)
        return _Loop(t0_s=t0, sequencer=seq, ending=Ending(), speedometer=SpeedMeter(2.0 * self.period),
                     force_loop=force_loop,
                     taring=self.loadcell is not None,  # averaging the tare until tare_s, then judging it once
                     zero_N=self.zero.value_N if self.zero is not None else None,
                     next_health_s=cfg.loop.health_every_s,
                     return_speed_mm_s=min(self.return_speed_mm_s, self.limits.max_speed_mm_s))

    # ------------------------------------------------------------- the tick's stages
    def _read(self, loop: _Loop) -> _Tick:
        """Wait for the slot, then measure: only fresh values feed the speed estimate and the
        move checks."""
        cfg, clock = self.config, self.clock
        scheduled = loop.t0_s + loop.slot * self.period
        clock.sleep_until(scheduled)
        now = clock.now()
        lateness = now - scheduled
        skipped = slots_behind(lateness, self.period)
        if skipped:  # fell behind by whole periods: skip, and say so
            self._missed += skipped
            loop.slot += skipped
            scheduled = loop.t0_s + loop.slot * self.period
            lateness = now - scheduled
        if lateness > cfg.loop.late_tolerance_ms / 1000.0:
            self._late += 1
        loop.slot += 1
        t = now - loop.t0_s
        self._tick_times.append(now)
        cell, seq, lim = self.loadcell, loop.sequencer, self.limits
        reading = cell.latest() if cell is not None else None
        pr = self.slider.position()
        pos = pr.value
        x_rel_mm = pos - seq.zero_mm  # from the trial's zero as it stands at the start of the tick
        t_log = round(t, 6)
        force_model = self.online.step(t_log, x_rel_mm / 1000.0) if self.online is not None else None
        status_fresh = status_read = False
        # A move's arrival needs a fresh "standing still": near its target, read it every tick.
        watch, ending = loop.watch, loop.ending
        confirming = ((ending.stop is not None and not ending.stop.confirmed)
                      or (seq.done and watch is not None)
                      or (watch is not None and pr.fresh
                          and abs(pos - watch.to_mm) <= cfg.slider.position_tolerance_mm))
        if confirming or self._status_due(loop):
            sr = self.slider.status()
            loop.status, status_fresh = sr.value, sr.fresh
            status_read = True
            # after the first, reads fall half a status period off the ticks where timed steps start
            # (the tare's end, a hold's: whole tenths of a second): a move on a status tick is 13 ms
            n = self._samples
            loop.status_seq = n - cfg.loop.status_every // 2 if n == 0 else n
        moving = loop.status.moving if status_fresh else None
        speed = loop.speedometer.update(pr)
        raw = reading.force_N if reading else 0.0
        age = reading.age_s if reading else None
        new_reading = reading is not None and (loop.last_reading_t is None or reading.t_s > loop.last_reading_t)
        if new_reading:
            loop.last_reading_t = reading.t_s
        if cell is None:  # no load cell: the model's estimate stands in, and is what is checked
            raw, age = force_model, 0.0
        self._last_age = age
        if loop.taring and reading is not None and not reading.over_range:
            loop.tare_sum += raw  # taring: zero the load cell on the mean of the first tare_s
            loop.tare_n += 1
            loop.tare_N = loop.tare_sum / loop.tare_n
            if new_reading:  # the cell's own noise, for the contact and frozen-cell checks
                loop.tare_values.append(raw)
        force = raw - loop.tare_N  # logged and sequenced relative to the tare, as analysis expects
        if cell is None:
            checked = force * (1.0 + lim.model_force_margin)
        elif loop.zero_N is None:
            checked = force
        else:  # the force the tissue carries, preload included (never less than the tared one)
            checked = max(raw - loop.zero_N, force)
        if loop.contact is not None:
            loop.in_contact = loop.contact.update(force, pos)
        return _Tick(now_s=now, t_s=t, t_log_s=t_log, lateness_s=lateness, reading=reading, position=pr,
                     position_mm=pos, x_rel_mm=x_rel_mm, force_model_N=force_model, moving=moving,
                     speed_mm_s=speed, raw_N=raw, age_s=age, force_N=force, checked_N=checked,
                     status_read=status_read, new_reading=new_reading)

    def _status_due(self, loop: _Loop) -> bool:
        """Status and alarm every `status_every` ticks; a tick on which the force loop's move is
        due reads them one tick later (never more; then the move waits a tick, `_track`), so no
        tick of a force step carries the position read, the status read and a move together: over
        RTU at 115200 baud with a 1 ms adapter that is 13 ms of a 10 ms tick."""
        since = self._samples - loop.status_seq
        every = self.config.loop.status_every
        move_due = loop.force_step >= 0 and self._samples - loop.sent_seq >= FORCE_MOVE_TICKS
        return since > every or (since == every and not move_due)

    def _check(self, recorder: Recorder, loop: _Loop, tick: _Tick) -> None:
        """Safety first: on a fault, stop, then explain. The tare's preload is judged here,
        once, before the sequencer's first move, so a refused preload moves nothing."""
        if loop.ending.fault is not None:
            return
        cfg, lim, seq = self.config, self.limits, loop.sequencer
        status = loop.status
        found = check(TickState(tick.checked_N, tick.position_mm, tick.speed_mm_s, tick.age_s,
                                status.alarm_code if status.alarm else 0,
                                bool(tick.reading and tick.reading.over_range), tick.raw_N,
                                "measured" if self.loadcell is not None else "estimated", loop.preload_N), lim)
        if found is None and loop.cell_watch is not None and tick.new_reading:
            why = loop.cell_watch.update(tick.reading.t_s, tick.raw_N)
            if why is not None:
                found = Fault("loadcell_frozen", why)
        if found is None and recorder.failure:
            found = Fault("recording", recorder.failure)
        if found is None and seq.fault:
            found = Fault("protocol", seq.fault)
        if found is None and loop.watch is not None:
            why = loop.watch.check(tick.t_s, tick.position_mm if tick.position.fresh else None, tick.moving)
            if why is not None:
                found = Fault("move", why)
            elif tick.position.fresh and loop.watch.arrived(tick.position_mm, tick.moving):
                loop.watch = None
        tare_done = found is None and loop.taring and tick.t_s >= cfg.loop.tare_s
        if tare_done:
            loop.taring = False
            if loop.zero_N is None:
                self.zero = Zero(loop.tare_N, assumed=True, source=f"the tare of trial "
                                 f"'{self.proto.name}' ({self.log_path.name}), assumed out of contact")
                loop.zero_N = loop.tare_N
            loop.preload_N = self.preload_N = loop.tare_N - loop.zero_N
            self._cell_known(recorder, loop, tick)
            max_pre = lim.max_preload_share * lim.max_force_N
            if abs(loop.preload_N) > max_pre:
                found = Fault("preload", (
                    f"preload {loop.preload_N:.3f} N at the start (tare {loop.tare_N:.3f} N, free-air zero "
                    f"{loop.zero_N:.3f} N from {self.zero.source}) is beyond {lim.max_preload_share:g} of "
                    f"the force limit {lim.max_force_N:g} N (limits.max_preload_share): refused "
                    "before anything moved; retract the probe (or `rig tare` out of contact if "
                    "the zero is wrong)"))
        if found is not None:
            self._fault(recorder, loop, found, tick)
        if tare_done:
            self._tare_logged(recorder, tick.t_s, loop.tare_N, loop.tare_n, loop.zero_N, loop.preload_N)

    def _cell_known(self, recorder: Recorder, loop: _Loop, tick: _Tick) -> None:
        """The tare is done: the cell's noise is measured, and with it the contact threshold and
        the frozen-cell checks (`rig.control.sensorwatch`)."""
        noise = loop.noise = CellNoise.from_readings(loop.tare_values, self.config.estimator.noise_N)
        loop.tare_values = []
        loop.cell_watch = CellWatch(noise)
        loop.contact = Contact.for_noise(noise, tick.position_mm)
        loop.motion = MotionAnswer(noise.effective_sigma_N)
        # the logged estimator's settings, on the measured noise, gated by `Contact` instead of its own test
        loop.loop_rls = StiffnessRLS.from_config(
            replace(self.config.estimator, noise_N=noise.effective_sigma_N, initial_stiffness_N_per_m=0.0,
                    contact_mm=0.0, contact_N=0.0), self.rate)
        data = {"sigma_N": noise.sigma_N, "diff_sigma_N": noise.diff_sigma_N,
                "repeat_share": noise.repeat_share, "step_N": noise.step_N, "readings": noise.readings,
                "contact_threshold_N": loop.contact.threshold_N, "frozen_run": noise.frozen_run,
                "quiet": noise.quiet}
        msg = (f"{noise.describe()}: contact above {loop.contact.threshold_N:.3g} N; frozen after "
               f"{noise.frozen_run + 1} identical readings")
        if noise.quiet:
            msg = (f"{noise.describe()}: contact above {loop.contact.threshold_N:.3g} N; too quiet to tell a "
                   "frozen reading by its repeats: under force control only the force's answer to the "
                   "motion and the depth budget guard against a frozen cell")
        self._event(recorder, tick.t_s, "load_cell_noise", msg, data)

    def _operator(self, recorder: Recorder, loop: _Loop, tick: _Tick) -> None:
        """The operator's stop requests (an estop may follow an abort that is returning)."""
        sig = self.signal_stop  # Ctrl-C: the handler only set this
        if sig is not None and sig is not self.signal_handled:
            self.signal_handled = sig
            self.request_stop(sig, user="console")
        req = self._take_stop_request()
        if req is None:
            return
        mode, user, received, ticket = req
        t = tick.t_s
        refused = loop.ending.on_request(mode, t)
        if refused and mode is StopMode.ESTOP:  # whatever else is going on, STOP again
            ok = self._send_stop(loop, t)
            ticket.settle(ok, f"{refused}; STOP sent again" + ("" if ok else ", not acknowledged"))
        elif refused:
            ticket.settle(False, f"refused: {refused}")
        else:
            ok = self._send_stop(loop, t)
            sent = time.monotonic()
            latency_ms = round((sent - received) * 1000.0, 3)
            ticket.settle(ok, f"STOP sent in {latency_ms:g} ms" if ok else
                          "STOP not acknowledged by the drive; still trying (the drive's "
                          "communication timeout is the backstop)")
            self._settle_tickets(ok, ticket.message)
            loop.watch = None
            self._event(recorder, t, "stop_requested", f"{mode.value} requested by {user or '?'}",
                        {"mode": mode.value, "user": user, "seq": self._samples,
                         "latency_ms": latency_ms, "acknowledged": ok})
            if mode == StopMode.ABORT:
                loop.sequencer.abort_to_start(t, loop.return_speed_mm_s)
            else:
                loop.sequencer.done = True

    def _confirm(self, recorder: Recorder, loop: _Loop, tick: _Tick) -> None:
        """A STOP stands until a fresh status says the drive stands still."""
        stop = loop.ending.stop
        match loop.ending.on_status(tick.t_s, tick.moving, self.limits.stop_confirm_s, self.resend_stop_s):
            case ("confirmed", _):
                self._event(recorder, tick.t_s, "stop_confirmed", "the drive reports standing still",
                            {"after_s": round(tick.t_s - stop.sent_t, 4), "resends": stop.resends})
            case ("gave_up", why):
                self._event(recorder, tick.t_s, "fault", why,
                            {"kind": "stop_unconfirmed", "seq": self._samples})
            case ("resend", _):
                self._send_stop(loop, tick.t_s)

    def _command(self, recorder: Recorder, loop: _Loop, tick: _Tick) -> None:
        """The step's controller: the sequencer's commands, each move checked against the limits
        before it is sent and watched until it arrives. Step decisions only on a fresh position,
        and a move counts as under way until its watch saw it arrive on fresh readings: a stale
        position is no arrival."""
        loop.force_error_N = None  # nothing is tracked on a tick that tracks nothing (a fault's included)
        if loop.ending.fault is not None:
            return
        seq, lim, t = loop.sequencer, self.limits, tick.t_s
        seq_moving = True if loop.watch is not None else tick.moving
        was = loop.force_step
        tracking = False
        in_contact = loop.in_contact if loop.contact is not None else True
        commands = (seq.tick(t, tick.position_mm, tick.force_N, seq_moving, in_contact) if tick.position.fresh
                    else ())
        if was >= 0 and seq.index != was:  # reported before the next step's first command
            self._force_step_ended(recorder, loop, t, was)
        for cmd in commands:
            if isinstance(cmd, Track):
                tracking = True
                if not self._track(recorder, loop, tick, cmd):
                    break
            elif isinstance(cmd, Move):
                why = check_move(cmd.to_mm, cmd.speed_mm_s, lim)
                if why is not None:
                    self._fault(recorder, loop, Fault("move_limit", f"move refused: {why}"), tick)
                    break
                self.slider.move_to(cmd.to_mm, cmd.speed_mm_s, cmd.accel_mm_s2)
                loop.ending.on_move()
                loop.watch = MoveWatch(tick.position_mm, cmd.to_mm, cmd.speed_mm_s, cmd.accel_mm_s2, t, lim,
                                    self.config.slider.position_tolerance_mm)
            elif isinstance(cmd, Stop):
                loop.watch = None
                self._send_stop(loop, t)
        if not tracking and seq.setpoint_N is None:
            loop.force_loop.release()  # a position step (or the end) took over
        if seq.index != loop.last_step and seq.index >= 0 and not seq.done:
            step = seq.step
            self._event(recorder, t, "step_start", f"step {seq.index}: {step.kind}",
                        {"step": seq.index, "kind": step.kind,
                         "zero_mm": seq.zero_mm, "target_mm": seq.target_mm - seq.zero_mm})
        loop.last_step = seq.index

    def _track(self, recorder: Recorder, loop: _Loop, tick: _Tick, cmd: Track) -> bool:
        """A force step's tick: the force loop's next position, limited to the step's deepest and
        its depth budget, checked against the limits before it is sent (False: refused, and
        faulted). Out of contact the slider seeks the surface at `force.seek_speed_share` of the
        speed limit, as an approach would, and the loop waits; in contact the force must answer
        the loop's motion (`sensorwatch.MotionAnswer`); a drive that does not follow is a fault."""
        seq, lim, fcfg = loop.sequencer, self.limits, self.config.force
        if loop.force_step != seq.index:
            loop.force_step, loop.force_recent = seq.index, []
            loop.at_depth_limit, loop.saturated_since = False, None
            loop.sent_target, loop.meter = None, None
            if loop.motion is not None:
                loop.motion.reset()
        sigma = loop.noise.effective_sigma_N if loop.noise is not None else self.config.estimator.noise_N
        if cmd.seeking:
            fc = loop.force_loop.seek(tick.position_mm, fcfg.seek_speed_share * lim.max_speed_mm_s)
            if loop.motion is not None:
                loop.motion.reset()
        else:
            if loop.meter is None:
                loop.meter = StepMeter(seq.index, seq.kind, tick.t_s, sigma, loop.carry_peak_N,
                                       seq.force_seek_s)
            fc = loop.force_loop.command(cmd.setpoint_N, tick.force_N, loop.stiffness_N_per_m, tick.position_mm,
                                         cmd.rate_N_s)
            loop.meter.update(tick.t_s, tick.force_N, cmd.setpoint_N)
            target_N = seq.step.to_N if isinstance(seq.step, RampForce) else seq.step.force_N
            depth_mm = tick.position_mm - loop.contact.surface_mm if loop.contact is not None else 0.0
            if loop.budget_mm is None and depth_mm > 0 and tick.force_N >= BUDGET_AT_SHARE * target_N:
                # the stiffness from the surface to here, read once the force is well above the noise
                loop.budget_mm = loop.contact.surface_mm + depth_mm * lim.max_force_N / tick.force_N
            if loop.motion is not None:
                why = loop.motion.update(tick.position_mm, tick.force_N, fc.error_N,
                                      answer_limit_mm(sigma, loop.stiffness_N_per_m, fcfg.answer_mm))
                if why is not None:
                    self._fault(recorder, loop, Fault("loadcell_frozen", why), tick)
                    return False
        deepest = cmd.limit_mm if loop.budget_mm is None else min(cmd.limit_mm, loop.budget_mm)
        target = min(fc.target_mm, deepest)
        loop.force_error_N = cmd.setpoint_N - tick.force_N
        loop.force_recent = ([r for r in loop.force_recent if r[0] > tick.t_s - 0.5]
                             + [(tick.t_s, tick.force_N, cmd.setpoint_N)])
        if target < fc.target_mm:
            if cmd.seeking and tick.position_mm >= deepest - self.config.slider.position_tolerance_mm:
                what = "max_mm" if deepest == cmd.limit_mm else "depth budget"
                self._fault(recorder, loop, Fault("protocol", (
                    f"step {seq.index} ({seq.kind}) reached its {what} ({deepest - seq.zero_mm:.4g} mm) "
                    f"without contact: the force stayed below {loop.contact.threshold_N:.3g} N "
                    "(four sigma of the load cell's noise)" if loop.contact is not None else
                    f"step {seq.index} ({seq.kind}) reached its {what} without contact")), tick)
                return False
            if deepest == cmd.limit_mm and not loop.at_depth_limit:
                loop.at_depth_limit = True
                msg = (f"step {seq.index} ({seq.kind}): the force loop reached the step's max_mm "
                       f"({cmd.limit_mm - seq.zero_mm:.4g} mm) at {tick.force_N:.4g} N, short of its setpoint "
                       f"{cmd.setpoint_N:.4g} N: held there")
                self._event(recorder, tick.t_s, "force_limit_depth", msg,
                            {"step": seq.index, "force_N": tick.force_N, "setpoint_N": cmd.setpoint_N})
                self.notices.append(msg)
            elif deepest < cmd.limit_mm and not loop.at_budget:
                loop.at_budget = True
                msg = (f"step {seq.index} ({seq.kind}): the force loop reached its depth budget "
                       f"({deepest - loop.contact.surface_mm:.4g} mm below the surface, where the stiffness "
                       f"it measured would carry the force limit {lim.max_force_N:g} N) at "
                       f"{tick.force_N:.4g} N, "
                       f"short of its setpoint {cmd.setpoint_N:.4g} N: held there (the specimen softened, "
                       "or the load cell reads low)")
                self._event(recorder, tick.t_s, "force_depth_budget", msg,
                            {"step": seq.index, "force_N": tick.force_N, "setpoint_N": cmd.setpoint_N,
                             "budget_mm": deepest - loop.contact.surface_mm})
                self.notices.append(msg)
        if fc.saturated and target >= fc.target_mm:
            if loop.saturated_since is None:
                loop.saturated_since = (tick.t_s, tick.position_mm)
            t0, p0 = loop.saturated_since
            span = tick.t_s - t0
            # a drive that follows moves, if more slowly than asked (it brakes towards a stream that
            # leads it by a tick or two); one that has stopped following does not move at all
            if span >= DRIVE_FOLLOW_S and abs(tick.position_mm - p0) < DRIVE_STUCK_MM:
                self._fault(recorder, loop, Fault("move", f"the drive did not follow the force loop: "
                                                  f"{abs(tick.position_mm - p0):.3g} mm in {span:.2g} s at "
                                                  f"{fc.speed_mm_s:.3g} mm/s commanded"), tick)
                return False
        else:
            loop.saturated_since = None
        why = check_move(target, fc.speed_mm_s, self.limits)
        if why is not None:
            self._fault(recorder, loop, Fault("move_limit", f"force loop move refused: {why}"), tick)
            return False
        step_mm = 1.0 / self.config.slider.steps_per_mm
        # a tick that read status (its turn could wait no longer) leaves the move to the next
        due = self._samples - loop.sent_seq >= FORCE_MOVE_TICKS and not tick.status_read
        if due and (loop.sent_target is None or abs(target - loop.sent_target) >= step_mm):
            self.slider.move_to(target, fc.speed_mm_s, self.config.slider.accel_mm_s2)
            loop.sent_target, loop.sent_seq = target, self._samples
            loop.ending.on_move()
        loop.watch = None  # a stream of small moves: the limits are checked every tick instead
        seq.follow(target)
        return True

    def _force_step_ended(self, recorder: Recorder, loop: _Loop, t: float, index: int) -> None:
        """A force step's figures (overshoot, settling, the hold's RMS error, a ramp's lag) as a
        `force_step` event, said to the operator when beyond `force:`'s warnings; and a force
        step that ended away from its setpoint (its last 0.5 s off by more than SETPOINT_MISS)
        is said too. A ramp that hands over to another force step is on its way, not ended."""
        loop.force_step = -1
        handed_over = isinstance(loop.sequencer.step, FORCE_STEPS)
        if not handed_over:  # the force segment ends: the next one finds its own budget
            loop.budget_mm, loop.at_budget = None, False
        meter, loop.meter = loop.meter, None
        if meter is not None:
            meter.seek_s, meter.lag_s, meter.reached = loop.sequencer.ended_force or (0.0, 0.0, True)
            loop.carry_peak_N = meter.peak_N if handed_over else -math.inf
            self._force_figures(recorder, loop, t, meter.figures())
        if not loop.force_recent or handed_over:
            return
        force = float(np.mean([r[1] for r in loop.force_recent]))
        setpoint = loop.force_recent[-1][2]
        if abs(force - setpoint) > SETPOINT_MISS * abs(setpoint):
            msg = (f"step {index}: the force step ended at {force:.4g} N (its last 0.5 s) against its "
                   f"setpoint {setpoint:.4g} N")
            self._event(recorder, t, "setpoint_missed", msg,
                        {"step": index, "force_N": force, "setpoint_N": setpoint})
            self.notices.append(msg)

    def _force_figures(self, recorder: Recorder, loop: _Loop, t: float, fig: StepFigures) -> None:
        fcfg = self.config.force
        loop.figures.append(fig)
        self._event(recorder, t, "force_step", fig.describe(), fig.as_dict())
        self.snapshot = replace(self.snapshot, force_steps=(*self.snapshot.force_steps[-9:], fig.as_dict()))
        said = []
        if fig.kind == "hold_force" and fig.overshoot_share > fcfg.overshoot_warn_share:
            said.append(f"overshot its setpoint by {100 * fig.overshoot_share:.1f} % (more than "
                        f"{100 * fcfg.overshoot_warn_share:g} %, force.overshoot_warn_share)")
        if fig.rms_over_noise is not None and fig.rms_over_noise > fcfg.rms_warn_sigma:
            said.append(f"held it with an RMS error of {fig.rms_error_N:.3g} N, {fig.rms_over_noise:.1f} sigma "
                        f"of the load cell's noise (more than {fcfg.rms_warn_sigma:g}, force.rms_warn_sigma)")
        if fig.kind == "ramp_force" and not fig.reached:
            said.append(f"ended {fig.lag_s:.2f} s after its planned end at {fig.end_force_N:.4g} N, short of "
                        f"its target {fig.setpoint_N:.4g} N")
        if said:
            msg = f"step {fig.index} ({fig.kind} {fig.setpoint_N:.4g} N) " + "; ".join(said)
            self._event(recorder, t, "force_step_warning", msg, fig.as_dict())
            self.notices.append(msg)

    def _estimate(self, loop: _Loop, tick: _Tick):
        """The online stiffness (RLS) on the previous tick's position and this tick's force, as
        logged (from the working zero); and the force loop's gain, the same estimator on the
        position from the surface the force found (`sensorwatch.Contact`): counted from the
        trial's start, 10 mm above the surface, the stiffness read 30x low and the gain 30x high.
        The larger of that and the force over the depth from the surface: right at contact, with
        the estimator not yet settled, the gain is then the lower, not the higher."""
        est = self.rls.update(loop.x_prev_m, tick.force_N)
        loop.x_prev_m = (tick.position_mm - loop.sequencer.zero_mm) / 1000.0
        if loop.contact is None:  # no load cell (or still taring): the logged estimate, as it stands
            loop.stiffness_N_per_m = est.stiffness_N_per_m
            if self.loadcell is None:
                loop.in_contact = bool(est.updated)
            return est
        x_c = (tick.position_mm - loop.contact.surface_mm) / 1000.0 if loop.in_contact else 0.0
        surface = loop.loop_rls.update(loop.x_contact_prev_m, tick.force_N)
        loop.x_contact_prev_m = x_c
        chord = tick.force_N / x_c if x_c > 0 else 0.0
        loop.stiffness_N_per_m = max(surface.stiffness_N_per_m, chord) if loop.in_contact else 0.0
        return est

    def _record(self, recorder: Recorder, loop: _Loop, tick: _Tick, est) -> None:
        """One sample queued for the recorder; health now and then; the watchers' snapshot."""
        seq, t = loop.sequencer, tick.t_s
        kind = "fault" if loop.ending.fault else seq.kind
        model = {}
        if loop.force_error_N is not None:
            model["force_cmd_N"] = seq.setpoint_N
            model["force_error_N"] = loop.force_error_N
        if tick.force_model_N is not None:
            model["force_model_N"] = tick.force_model_N
            if self.loadcell is not None:
                model["model_error_N"] = tick.force_N - tick.force_model_N
        sample = SAMPLE.record(
            seq=self._samples, t_s=tick.t_log_s, position_mm=tick.x_rel_mm, slider_mm=tick.position_mm,
            position_cmd_mm=round(seq.position_cmd_mm(t), 6), force_N=tick.force_N,
            stiffness_N_per_m=est.stiffness_N_per_m, force_pred_N=est.force_pred_N,
            error_N=est.error_N, forgetting=est.forgetting, contact=est.updated,
            step=seq.index, step_kind=kind, late_ms=round(tick.lateness_s * 1000.0, 4), **model)
        self._emit(recorder, SAMPLE.topic, self.clock.wall_ns(tick.now_s), sample)
        if abs(tick.force_N) > self._cal_max_N:
            self._beyond_calibration(recorder, t, tick.force_N)
        self._samples += 1
        if t >= loop.next_health_s:
            self._health(recorder, t, tick.now_s, loop.health_mark)
            loop.health_mark = len(self._tick_times)
            loop.next_health_s += self.config.loop.health_every_s
        self.snapshot = Snapshot(
            state=self.snapshot.state, t_s=t, step=seq.index, step_kind=kind,
            steps_total=len(seq.steps), time_left_s=seq.time_left_s(t), force_N=tick.force_N,
            position_mm=tick.x_rel_mm, stiffness_N_per_m=est.stiffness_N_per_m,
            log_path=str(self.log_path), fault=self.snapshot.fault, force_model_N=tick.force_model_N,
            preload_N=loop.preload_N, force_steps=self.snapshot.force_steps)
        if self.on_tick is not None:
            self.on_tick(self.snapshot)

    def _beyond_calibration(self, recorder: Recorder, t: float, force_N: float) -> None:
        """A force beyond the calibrated range, the first time: said in the log and to the operator."""
        cal = self.config.calibration
        msg = (f"force {force_N:.4g} N beyond the load cell's calibrated range ({cal.range_N[0]:g}-"
               f"{cal.range_N[1]:.4g} N, {cal.date[:10]}): read uncalibrated from here")
        self._event(recorder, t, "calibration_range", msg, {"force_N": force_N, "range_N": list(cal.range_N)})
        self.notices.append(msg)
        self._cal_max_N = math.inf

    def _send_stop(self, loop: _Loop, t: float) -> bool:
        ok = self._safe_stop()
        loop.ending.on_stop_sent(t)
        return ok

    def _fault(self, recorder: Recorder, loop: _Loop, found: Fault, tick: _Tick) -> None:
        self._send_stop(loop, tick.t_s)  # stop first, explain after
        loop.watch = None
        loop.ending.on_fault(found, tick.t_s)
        self._event(recorder, tick.t_s, "fault", found.message,
                    {"kind": found.kind, "seq": self._samples, "force_N": tick.force_N,
                     "position_mm": tick.position_mm - loop.sequencer.zero_mm})
        self.snapshot = replace(self.snapshot, state=TrialState.STOPPING, fault=found.message)

    def _tare_logged(self, recorder: Recorder, t: float, tare_N: float, readings: int, zero_N: float,
                     preload_N: float) -> None:
        """The tare, the zero it was measured against and the preload: force_N + preload_N is
        the force the tissue carried."""
        z = self.zero
        how = ("no free-air zero known: assumed out of contact (preload 0)" if z.assumed and preload_N == 0
               else f"preload {preload_N:+.4f} N against the zero {zero_N:+.4f} N from {z.source}")
        data = {"tare_N": tare_N, "readings": readings, "zero_N": zero_N, "preload_N": preload_N,
                "zero_source": z.source, "zero_assumed": z.assumed}
        self._event(recorder, t, "tare", f"tare {tare_N:+.4f} N from {readings} readings; {how}", data)
        recorder.write_metadata("tare", {k: f"{v:.6g}" if isinstance(v, float) else v for k, v in data.items()})

    def _health(self, recorder: Recorder, t: float, now: float, mark: int) -> None:
        times = np.asarray(self._tick_times[max(mark - 1, 0):])
        err = np.abs(np.diff(times) - self.period) * 1000.0 if len(times) > 1 else np.zeros(1)
        s = self.slider.stats
        c = self.loadcell.stats if self.loadcell is not None else LinkStats()
        self._emit(recorder, HEALTH.topic, self.clock.wall_ns(now), HEALTH.record(
            t_s=round(t, 6), ticks=self._samples, late_ticks=self._late, missed_ticks=self._missed,
            period_err_p50_ms=float(np.percentile(err, 50)),
            period_err_p99_ms=float(np.percentile(err, 99)),
            period_err_max_ms=float(err.max()),
            bus_transactions=s.transactions, bus_errors=s.errors,
            loadcell_lines_ok=c.lines_ok, loadcell_lines_bad=c.lines_bad,
            loadcell_age_ms=(self._last_age or 0.0) * 1000.0,
            queue_depth=recorder.depth(),
            live_dropped=self.live.dropped if self.live is not None else 0,
        ))


def _warm_up() -> None:
    """Run once what the loop and writer would otherwise import or initialise mid-trial.

    A first call into numpy's percentile or the zstd compressor costs milliseconds
    (lazy imports, holding the GIL): enough to make a tick late.
    """
    np.percentile(np.arange(10.0), [50, 99])
    try:
        import zstandard

        zstandard.ZstdCompressor().compress(b"warm-up" * 100)
    except ImportError:  # pragma: no cover - mcap depends on it
        pass


def default_log_path(out_dir: str | Path, proto: Protocol, specimen: str) -> Path:
    """A new log's path in `out_dir`: the time, the protocol's and the specimen's names made safe for a file
    name."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    # names, never paths (rig.recording.names): the log lies in `out_dir` whatever they say
    slug = file_part(proto.name.replace("_", "-"), default="protocol", max_chars=40, lower=True)
    spec = file_part(specimen, default="specimen", max_chars=20)
    # The name wanted: the recorder opens it exclusively, or the next free `_2`, `_3`... (a
    # check here would race with another run starting in the same second).
    return out / f"{stamp}_{spec}_{slug}.mcap"
