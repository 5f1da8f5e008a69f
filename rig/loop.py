"""The acquisition loop: one tick every 1/rate_Hz seconds.

A tick reads the load cell and the slider position (status/alarm every
`status_every` ticks), checks the limits, lets the sequencer issue at most one
command, updates the RLS estimator and queues one sample for the recorder. On any
fault the slider is told to stop before anything else happens; the loop then keeps
logging for `post_fault_s` so the log shows the stop, and finishes the log.

Timing: ticks are scheduled on a fixed grid t0 + k/rate. A tick that starts more than
`late_tolerance_ms` after its slot is counted late (and `late_ms` is in every
sample); if the loop falls a whole period behind, the skipped slots are counted as
missed, never silently dropped.
"""

from __future__ import annotations

import contextlib
import enum
import gc
import socket
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from drivers.base import LoadCell, Slider, SliderStatus
from rig import __version__
from rig.clock import Clock
from rig.config import RigConfig
from rig.estimator import StiffnessRLS
from rig.protocol import Protocol
from rig.recorder import EVENT_TOPIC, HEALTH_TOPIC, SAMPLE_TOPIC, Recorder, TrialInfo
from rig.safety import Fault, TickState, check
from rig.sequencer import Move, Sequencer, Stop


class StopMode(enum.Enum):
    ESTOP = "estop"  # stop the motor now, nothing else
    HOLD = "hold"  # stop and stay
    ABORT = "abort"  # stop, then return to the start position at a safe speed


@dataclass
class Snapshot:
    """What a watcher sees; replaced (not mutated) every tick, so reading it needs no lock."""

    state: str = "idle"  # idle, running, stopping, done, fault, aborted
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


@dataclass
class TrialResult:
    outcome: str  # completed, fault, aborted, stopped, estopped
    log_path: Path
    samples: int
    late_ticks: int
    missed_ticks: int
    duration_s: float
    fault: str | None = None
    period_errors_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bus_transactions: int = 0


class Trial:
    post_fault_s = 0.5
    return_speed_mm_s = 5.0

    def __init__(self, proto: Protocol, config: RigConfig, slider: Slider, loadcell: LoadCell,
                 clock: Clock, log_path: Path, info: TrialInfo | None = None,
                 *, start_mm: float | None = None) -> None:
        self.proto = proto
        self.config = config
        self.limits = proto.effective_limits(config.limits)
        self.slider = slider
        self.loadcell = loadcell
        self.clock = clock
        self.log_path = Path(log_path)
        self.info = info or TrialInfo()
        self.rate = config.loop.rate_Hz
        self.period = 1.0 / self.rate
        self._start_mm = start_mm
        self._stop_request: tuple[StopMode, str, float] | None = None
        self._lock = threading.Lock()
        self.snapshot = Snapshot(steps_total=len(proto.run_steps()), log_path=str(log_path))
        est = config.estimator
        self.rls = StiffnessRLS.from_config(est, self.rate)
        self.on_tick = None  # optional callable(Snapshot), called every tick from the loop thread

    # ------------------------------------------------------------- control
    def request_stop(self, mode: StopMode = StopMode.ABORT, user: str = "",
                     received_s: float | None = None) -> None:
        """Thread-safe; the loop carries it out on its next tick (the loop thread owns the bus).

        `received_s` is when the request arrived (time.monotonic()); the stop event records the
        latency from then to the stop command acknowledged on the bus.
        """
        with self._lock:
            if self._stop_request is None or mode == StopMode.ESTOP:
                self._stop_request = (mode, user, received_s if received_s is not None else time.monotonic())

    def _take_stop_request(self) -> tuple[StopMode, str, float] | None:
        with self._lock:
            req, self._stop_request = self._stop_request, None
        return req

    # ------------------------------------------------------------- the run
    def run(self) -> TrialResult:
        cfg = self.config
        rec = Recorder(self.log_path, flush_s=cfg.recorder.flush_s,
                       compression=cfg.recorder.compression)
        self.recorder = rec
        _warm_up()
        # A full collection mid-trial walks every object the interpreter holds (numpy, pymodbus,
        # ...): milliseconds. Collect now and freeze what exists, so later passes are short.
        gc.collect()
        gc.freeze()
        self._t0 = self.clock.now()
        self._write_header(rec, self._t0)
        # Let the writer put the header on disk before the first tick is due.
        rec.wait_idle(timeout_s=2.0)
        # Last, right before the first tick: a polled cell's reading ages from its reply, and
        # the header's fsync above can take longer than the stale limit on a busy disk.
        self._prime_loadcell()
        t0 = self._t0 = self.clock.now()
        outcome, fault_msg = "completed", None
        try:
            outcome, fault_msg = self._loop(rec, t0)
        except BaseException as exc:  # a bug or a lost device: stop first, then record it
            self._safe_stop()
            outcome, fault_msg = "fault", f"{type(exc).__name__}: {exc}"
            self._event(rec, self.clock.now() - t0, "fault", fault_msg, {"kind": "exception"})
            if not isinstance(exc, Exception):
                raise
        finally:
            t_end = self.clock.now() - t0
            self._event(rec, t_end, "trial_end", f"trial {outcome}",
                        {"outcome": outcome, "samples": self._seq})
            rec.close({"outcome": outcome, "samples": str(self._seq),
                       "late_ticks": str(self._late), "missed_ticks": str(self._missed),
                       "duration_s": f"{t_end:.3f}", "fault": fault_msg or "",
                       "end_time": datetime.now(UTC).isoformat()})
            self.snapshot = replace(self.snapshot, state=outcome if outcome != "completed" else "done",
                                     fault=fault_msg or "")
            gc.unfreeze()
        periods = np.diff(np.asarray(self._tick_times)) if len(self._tick_times) > 1 else np.zeros(0)
        return TrialResult(outcome, self.log_path, self._seq, self._late, self._missed,
                           self.clock.now() - t0, fault_msg,
                           np.abs(periods - self.period) * 1000.0,
                           self.slider.stats.transactions)

    def _prime_loadcell(self, timeout_s: float = 3.0) -> None:
        """Wait (real time) for a first reading: a polled cell answers only after a request."""
        deadline = time.monotonic() + timeout_s
        while self.loadcell.latest() is None and time.monotonic() < deadline:
            time.sleep(0.002)

    def _write_header(self, rec: Recorder, t0: float) -> None:
        info = self.info
        now_ns = self.clock.wall_ns(t0)
        rec.write_metadata("trial", {
            "specimen": info.specimen, "operator": info.operator,
            "protocol_name": self.proto.name, "protocol_path": self.proto.source_path,
            "config_name": self.config.name, "config_path": self.config.source_path,
            "config_digest": self.config.digest(),
            "start_time": datetime.fromtimestamp(now_ns / 1e9, UTC).isoformat(),
            "software_version": __version__, "host": socket.gethostname(),
            "clock": info.clock, "rate_Hz": f"{self.rate:g}", "notes": info.notes,
            "python": sys.version.split()[0], **info.extra,
        })
        rec.attach("protocol.yaml", "application/yaml", self.proto.source_text.encode(), now_ns)
        rec.attach("config.yaml", "application/yaml", self.config.text().encode(), now_ns)

    def _event(self, rec: Recorder, t: float, kind: str, message: str, data: dict | None = None) -> None:
        rec.put(EVENT_TOPIC, self.clock.wall_ns(self._t0 + t),
                {"t_s": round(t, 6), "kind": kind, "message": message, "data": data or {}})

    def _safe_stop(self) -> None:
        # nothing more can be done from here if this fails: the drive's comm timeout is the backstop
        with contextlib.suppress(Exception):
            self.slider.stop()

    def _loop(self, rec: Recorder, t0: float) -> tuple[str, str | None]:
        cfg = self.config
        clock, slider, cell = self.clock, self.slider, self.loadcell
        self._seq = self._late = self._missed = 0
        self._tick_times: list[float] = []
        self._last_age: float | None = None
        late_tol = cfg.loop.late_tolerance_ms / 1000.0
        status_every = cfg.loop.status_every
        start_mm = self._start_mm if self._start_mm is not None else slider.read_position_mm()
        seq = Sequencer(self.proto, start_mm=start_mm, accel_mm_s2=cfg.slider.accel_mm_s2,
                        tare_s=cfg.loop.tare_s, tolerance_mm=cfg.slider.position_tolerance_mm,
                        rate_Hz=self.rate)
        self._event(rec, 0.0, "trial_start", f"protocol '{self.proto.name}'",
                    {"specimen": self.info.specimen, "start_mm": start_mm,
                     "steps": len(seq.steps)})
        rls = self.rls
        status = SliderStatus(True, False, True, False)
        tare_sum, tare_n, tare_N = 0.0, 0, 0.0
        prev_pos = start_mm
        prev_t = 0.0
        x_prev_m = 0.0
        fault: Fault | None = None
        fault_t = 0.0
        outcome = "completed"
        stop_mode: StopMode | None = None
        last_step = -2
        next_health = cfg.loop.health_every_s
        health_mark = 0
        slot = 0
        self.snapshot = replace(self.snapshot, state="running")
        while True:
            scheduled = t0 + slot * self.period
            clock.sleep_until(scheduled)
            now = clock.now()
            lateness = now - scheduled
            if lateness > self.period:  # fell behind by whole periods: skip, and say so
                skipped = int(lateness / self.period)
                self._missed += skipped
                slot += skipped
                scheduled = t0 + slot * self.period
                lateness = now - scheduled
            if lateness > late_tol:
                self._late += 1
            slot += 1
            t = now - t0
            self._tick_times.append(now)

            # ---- measure
            reading = cell.latest()
            pos = slider.read_position_mm()
            if self._seq % status_every == 0:
                status = slider.read_status()
            raw = reading.force_N if reading else 0.0
            age = reading.age_s if reading else None
            self._last_age = age
            speed = (pos - prev_pos) / (t - prev_t) if t > prev_t else 0.0
            prev_pos, prev_t = pos, t
            if seq.index < 0:  # taring: zero the load cell on the mean of the first tare_s
                tare_sum += raw
                tare_n += 1
                tare_N = tare_sum / tare_n
            force = raw - tare_N

            # ---- safety first: stop, then explain
            if fault is None:
                found = check(TickState(force, pos, speed, age, status.alarm_code if status.alarm else 0),
                              self.limits)
                if found is None and seq.fault:
                    found = Fault("protocol", seq.fault)
                if found is not None:
                    slider.stop()
                    fault, fault_t, outcome = found, t, "fault"
                    self._event(rec, t, "fault", found.message,
                                {"kind": found.kind, "seq": self._seq, "force_N": force,
                                 "position_mm": pos - seq.zero_mm})
                    self.snapshot = replace(self.snapshot, state="stopping", fault=found.message)

            # ---- operator stop requests (an estop may follow an abort that is returning)
            req = self._take_stop_request() if fault is None else None
            if req is not None and (stop_mode is None or req[0] == StopMode.ESTOP):
                mode, user, received = req
                slider.stop()
                sent = time.monotonic()
                stop_mode = mode
                outcome = {StopMode.ESTOP: "estopped", StopMode.HOLD: "stopped",
                           StopMode.ABORT: "aborted"}[mode]
                self._event(rec, t, "stop_requested", f"{mode.value} requested by {user or '?'}",
                            {"mode": mode.value, "user": user, "seq": self._seq,
                             "latency_ms": round((sent - received) * 1000.0, 3)})
                if mode == StopMode.ABORT:
                    seq.abort_to_start(t, self.return_speed_mm_s)
                else:
                    seq.done = True
                fault_t = t

            # ---- sequence
            if fault is None:
                was_tare = seq.index < 0
                for cmd in seq.tick(t, pos, force, status.moving if self._seq % status_every == 0
                                    else None):
                    if isinstance(cmd, Move):
                        slider.move_to(cmd.to_mm, cmd.speed_mm_s, cmd.accel_mm_s2)
                    elif isinstance(cmd, Stop):
                        slider.stop()
                if was_tare and seq.index >= 0:
                    self._event(rec, t, "tare", f"tare {tare_N:+.4f} N from {tare_n} readings",
                                {"tare_N": tare_N, "readings": tare_n})
                if seq.index != last_step and seq.index >= 0 and not seq.done:
                    step = seq.step
                    self._event(rec, t, "step_start", f"step {seq.index}: {step.kind}",
                                {"step": seq.index, "kind": step.kind,
                                 "zero_mm": seq.zero_mm, "target_mm": seq.target_mm - seq.zero_mm})
                last_step = seq.index

            # ---- estimate
            est = rls.update(x_prev_m, force)
            x_prev_m = (pos - seq.zero_mm) / 1000.0

            kind = "fault" if fault else seq.kind
            rec.put(SAMPLE_TOPIC, clock.wall_ns(now), {
                "seq": self._seq, "t_s": round(t, 6),
                "position_mm": pos - seq.zero_mm,
                "position_cmd_mm": round(seq.position_cmd_mm(t), 6),
                "force_N": force,
                "stiffness_N_per_m": est.stiffness_N_per_m,
                "force_pred_N": est.force_pred_N, "error_N": est.error_N,
                "forgetting": est.forgetting, "contact": est.updated,
                "step": seq.index, "step_kind": kind,
                "late_ms": round(lateness * 1000.0, 4),
            })
            self._seq += 1

            if t >= next_health:
                self._health(rec, t, now, health_mark)
                health_mark = len(self._tick_times)
                next_health += cfg.loop.health_every_s

            self.snapshot = Snapshot(
                state=self.snapshot.state, t_s=t, step=seq.index, step_kind=kind,
                steps_total=len(seq.steps), time_left_s=seq.time_left_s(t), force_N=force,
                position_mm=pos - seq.zero_mm, stiffness_N_per_m=est.stiffness_N_per_m,
                log_path=str(self.log_path), fault=self.snapshot.fault)
            if self.on_tick is not None:
                self.on_tick(self.snapshot)

            # ---- end?
            if fault is not None and t - fault_t >= self.post_fault_s:
                return outcome, fault.message
            if stop_mode in (StopMode.ESTOP, StopMode.HOLD) and t - fault_t >= self.post_fault_s:
                return outcome, None
            if seq.done and fault is None and stop_mode in (None, StopMode.ABORT):
                return outcome, None

    def _health(self, rec: Recorder, t: float, now: float, mark: int) -> None:
        times = np.asarray(self._tick_times[max(mark - 1, 0):])
        err = np.abs(np.diff(times) - self.period) * 1000.0 if len(times) > 1 else np.zeros(1)
        s, c = self.slider.stats, self.loadcell.stats
        rec.put(HEALTH_TOPIC, self.clock.wall_ns(now), {
            "t_s": round(t, 6), "ticks": self._seq, "late_ticks": self._late,
            "missed_ticks": self._missed,
            "period_err_p50_ms": float(np.percentile(err, 50)),
            "period_err_p99_ms": float(np.percentile(err, 99)),
            "period_err_max_ms": float(err.max()),
            "bus_transactions": s.transactions, "bus_errors": s.errors,
            "loadcell_lines_ok": c.lines_ok, "loadcell_lines_bad": c.lines_bad,
            "loadcell_age_ms": (self._last_age or 0.0) * 1000.0,
            "queue_depth": rec.depth(),
        })


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
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    slug = "".join(c if c.isalnum() else "-" for c in proto.name.lower()).strip("-")
    slug = "-".join(filter(None, slug.split("-")))[:40]
    spec = "".join(c if c.isalnum() or c in "-_" else "-" for c in specimen)[:20] or "specimen"
    path = out / f"{stamp}_{spec}_{slug}.mcap"
    n = 1
    while path.exists():
        n += 1
        path = out / f"{stamp}_{spec}_{slug}_{n}.mcap"
    return path
