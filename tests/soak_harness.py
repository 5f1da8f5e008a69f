"""Fault-injection soak: a daemon on the simulated rig over Modbus RTU, driven through random
sequences of lab events and faults by a hypothesis state machine, with invariants checked after
every step. Shared by tests/test_soak.py (short, default run) and tests/bench/test_bench_soak.py.

How the faults are made:
- disk full: RLIMIT_FSIZE lowered on the running daemon (`prlimit`, soft limit only, so it can
  be raised back unprivileged) to the running log's size: the next write fails with EFBIG
  (Python ignores SIGXFSZ). No mount needed; the daemon's own output goes to a pipe, so only
  files hit the limit, as on a full data disk.
- clock step: a `sitecustomize` on the daemon's PYTHONPATH (this test only) adds an offset read
  from a file to time.time, time.time_ns and datetime.now. The loop runs on time.monotonic,
  which a wall step does not move; the wall clock names logs (to the second) and stamps them,
  so the step is backwards by the time since the last start: the next log's name is taken.
- the serial port vanishing: both ends of the RTU client's pseudo-terminal closed mid-trial
  (`RtuBridge.vanish`); it comes back behind the same symlink, as a by-id name does.
- drive alarm, dropped, corrupted (bad CRC) and garbled (line noise) replies: `FaultParams`.
- a load cell that freezes (its last line repeated), goes noiseless, or a specimen that triples
  its stiffness mid-trial: `FaultParams.loadcell_frozen`, `loadcell_noiseless`, `stiffness_scale`.
- a stop or estop racing a start's set-up, a campaign (`rig start --characterize`) stopped at
  any moment, a protocol past the repeat cap and one just under it, specimen names that are
  paths: plain requests on the socket, timed from threads.

Rules whose feature is still being built are tagged with a name in FEATURES_PENDING: a broken
invariant under such a tag is recorded in `Soak.pending` (and printed) instead of failing the
run, unless RIG_SOAK_STRICT=1. Remove a name once its feature is merged.
"""

from __future__ import annotations

import contextlib
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import yaml
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule
from rig.sim.params import SimParams
from rig.sim.server import WireSim

from rig.errors import RigError
from rig.recording.logs import read_log
from rig.service.client import request

ROOT = Path(__file__).resolve().parent.parent

# drive_lock: one owner per drive (a second CLI or `rig run` beside the daemon is refused)
# owner_recovery: a second daemon touches no log it does not own
# preload_limit: the force limit holds for the force the tissue carries, whatever was tared
# stop_anytime: a stop or estop is carried out while a trial is starting or closing
# sigint_flag: Ctrl-C in `rig run` only sets a flag (no deadlock)
FEATURES_PENDING: set[str] = set()
STRICT = os.environ.get("RIG_SOAK_STRICT") == "1"

TRAVEL_MM = (-5.0, 45.0)
CONFIG_MAX_FORCE_N = 20.0
TICK_S = 0.01
SPEED_MM_S = 5.0  # the fastest ramp in the soak's protocols
ACCEL_MM_S2 = 50.0  # the driver's default ramp-up
NOISE_N = SimParams().loadcell.noise_N
TAU2 = SimParams().tissue.tau2_N_s_per_m2

SHORT = ("name: short\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: 5}\n  - hold: {duration_s: 0.3}\n"
         "  - return: {speed_mm_s: 5}\n")
SLOW = ("name: slow\nsteps:\n  - ramp: {to_mm: 6, speed_mm_s: 3}\n  - hold: {duration_s: 1}\n"
        "  - return: {speed_mm_s: 5}\n")
# the tissue relaxes (tau1 8 s) while it is loaded: about 5 mm deep from its surface it carries 0.5 N
FORCE = ("name: force\nlimits: {max_force_N: 0.5}\nsteps:\n  - ramp: {to_mm: 8, speed_mm_s: 5}\n"
         "  - hold: {duration_s: 0.3}\n  - return: {speed_mm_s: 5}\n")
# force control: the surface found by an approach, a force ramp and hold (1.5 N, about 12 mm deep)
FORCE_HOLD = ("name: force hold\nsteps:\n  - approach: {speed_mm_s: 3, contact_N: 0.3, max_mm: 15}\n"
              "  - ramp_force: {to_N: 1.5, rate_N_s: 1.5, max_mm: 12}\n"
              "  - hold_force: {force_N: 1.5, duration_s: 1.5, max_mm: 12}\n  - return: {speed_mm_s: 10}\n")
PROTOCOLS = {"short": (SHORT, 3.0, None), "slow": (SLOW, 6.0, None), "force": (FORCE, 8.0, 0.5),
             "force_hold": (FORCE_HOLD, 15.0, None)}
# how far from the start a protocol may reach as `check_limits` sees it (a refusal from further in
# is the truth), where that differs from the depth above (the approach may find contact anywhere)
REACH_MM = {"force_hold": 27.0}
# a protocol past the repeat cap (limits.max_protocol_steps, 10,000 executed steps), and one under it
REPEAT_OVER = "name: too many\nrepeat: 20000\nsteps:\n  - ramp: {to_mm: 1, speed_mm_s: 5}\n" \
              "  - ramp: {to_mm: 0, speed_mm_s: 5}\n"
REPEAT_UNDER = REPEAT_OVER.replace("repeat: 20000", "repeat: 4900").replace("too many", "many")
# specimen names that are paths: the daemon writes nothing outside its log folder
BAD_NAMES = ["/tmp/rig-soak-outside/x", "../../up", "a/b/../../c", ".hidden", "trial\x00nul"]

SITECUSTOMIZE = '''
import datetime as _dt, os as _os, time as _time
_FILE = _os.environ.get("RIG_SOAK_CLOCK_FILE")
_state = [0.0, -1.0]
def _offset():
    now = _time.monotonic()
    if _FILE and now - _state[1] > 0.05:
        _state[1] = now
        try:
            with open(_FILE) as f:
                _state[0] = float(f.read() or 0.0)
        except (OSError, ValueError):
            pass
    return _state[0]
_wall, _wall_ns, _base = _time.time, _time.time_ns, _dt.datetime
_time.time = lambda: _wall() + _offset()
_time.time_ns = lambda: _wall_ns() + int(_offset() * 1e9)
class _SteppedDatetime(_base):
    @classmethod
    def now(cls, tz=None):
        return _base.now(tz) + _dt.timedelta(seconds=_offset())
_dt.datetime = _SteppedDatetime
'''


def force_margin_N(deepest_mm: float) -> float:
    """How far above its limit the tissue's true force may get before the slider stops.

    The design target is one tick's rise. The loop sees a noisy reading up to one load-cell
    line old, and on a shared 2-core machine a tick can start a tick late, so this allows
    two ticks of the fastest rise the soak can make, plus four standard deviations of sensor
    noise. The fastest rise is the damping term's (tau2 x dx/dt) derivative at the deepest
    point with the slider still accelerating: tau2 (v^2 + x a), plus the elastic slope times v.
    """
    x = max(deepest_mm, 0.0) / 1000.0
    v, a = SPEED_MM_S / 1000.0, ACCEL_MM_S2 / 1000.0
    tp = SimParams().tissue
    elastic_slope = 3 * tp.k1_N_per_m3 * x * x + 2 * tp.k2_N_per_m2 * x + tp.k3_N_per_m
    rate = TAU2 * (v * v + x * a) + elastic_slope * v
    return 2 * TICK_S * rate + 4 * NOISE_N


@dataclass
class TrialRecord:
    log: str
    protocol: str
    start_mm: float
    preload_N: float
    limit_N: float
    deepest_mm: float
    # what was done to it: each entry an outcome it may then have ("completed" for a fault
    # that must be ridden through)
    causes: list[str] = field(default_factory=list)
    taint: set[str] = field(default_factory=set)  # pending features whose rules touched it
    stop_ok: str | None = None  # the outcome an "ok" stop reply promised
    final: set[str] | None = None  # outcomes the log may say once the trial ended


class Soak:
    """The rig, the daemon and the bookkeeping the invariants need."""

    def __init__(self, tmp: Path, seed: int = 0) -> None:
        self.tmp = tmp
        self.seed = seed
        self.trace: list[str] = []
        self.checks: dict[str, int] = {}
        self.pending: list[str] = []
        # every failure as it happened: hypothesis replays a failing example to report it, and
        # the rig's state (positions, files, the clock) is not replayed, so the replay can draw
        # other steps and end in FlakyStrategyDefinition with the first failure out of sight
        self.failures: list[str] = []
        self.sim = WireSim(SimParams(), tcp=False, rtu_link=str(tmp / "ttyRIG"))
        self.sim.start()
        self.sock = tmp / "rigd.sock"
        self.out = tmp / "trials"
        self.clock_file = tmp / "clock_offset"
        self.clock_file.write_text("0")
        site = tmp / "site"
        site.mkdir(exist_ok=True)
        (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
        self.env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)]),
                    "RIG_SOAK_CLOCK_FILE": str(self.clock_file)}
        cfg = {"slider": {"backend": "modbus-rtu", "port": str(tmp / "ttyRIG"),
                          "profile": "oriental_az_sim", "comm_timeout_s": 0.3},
               "loadcell": {"backend": "serial", "port": self.sim.endpoints.loadcell, "mode": "stream"},
               "limits": {"max_force_N": CONFIG_MAX_FORCE_N, "travel_mm": list(TRAVEL_MM)},
               "recorder": {"out_dir": str(self.out)}}
        self.cfg_path = tmp / "rig.yaml"
        self.cfg_path.write_text(yaml.safe_dump(cfg))
        self.proc: subprocess.Popen | None = None
        self.output: list[str] = []
        self._reader: threading.Thread | None = None
        self.trials: dict[str, TrialRecord] = {}
        self.current: TrialRecord | None = None
        self.last_start_wall = 0.0
        self.clock_offset_s = 0.0
        self.fsize_limited = False
        self.stiffness_seen = 1.0
        self.start_daemon()

    # ------------------------------------------------------------ bookkeeping
    def step(self, text: str) -> None:
        self.trace.append(text)

    def expect(self, cond: bool, invariant: str, detail: str, feature: str | None = None) -> None:
        self.checks[invariant] = self.checks.get(invariant, 0) + 1
        if cond:
            return
        msg = f"[{invariant}] {detail}\n  steps: " + " -> ".join(self.trace[-12:])
        if feature is not None and feature in FEATURES_PENDING and not STRICT:
            self.pending.append(f"({feature}) {msg}")
            return
        tail = "".join(self.output[-30:])
        self.failures.append(msg)
        raise AssertionError(f"{msg}\n  daemon output (last lines):\n{tail}")

    def _pending_feature(self, rec: TrialRecord | None) -> str | None:
        pend = sorted((rec.taint if rec else set()) & FEATURES_PENDING)
        return pend[0] if pend else None

    # ------------------------------------------------------------ the daemon
    def start_daemon(self, timeout_s: float = 30.0) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rig", "daemon", "--config", str(self.cfg_path), "--socket", str(self.sock)],
            cwd=ROOT, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self._reader = threading.Thread(target=self._read_output, args=(self.proc,), name="soak-daemon-out",
                                        daemon=True)
        self._reader.start()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                break
            with contextlib.suppress(RigError):
                if request(self.sock, {"cmd": "ping"}, 1.0)["ok"]:
                    return
            time.sleep(0.05)
        raise AssertionError("daemon did not come up:\n" + "".join(self.output[-30:]))

    def _read_output(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            self.output.append(line)

    def stop_daemon(self, sig: int = signal.SIGTERM, timeout_s: float = 60.0) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        code = self.proc.returncode
        if self._reader is not None:
            self._reader.join(10)
        self.proc.stdout.close()
        self.proc = None
        return code

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.stop_daemon()
        self.sim.stop()

    def req(self, obj: dict, timeout_s: float = 10.0) -> dict:
        return request(self.sock, obj, timeout_s)

    def busy(self) -> bool:
        return self.req({"cmd": "status"})["state"] != "idle"

    def wait_idle(self, timeout_s: float = 40.0) -> dict:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            st = self.req({"cmd": "status"})
            if st["state"] == "idle":
                return st
            time.sleep(0.05)
        raise AssertionError(f"trial did not end within {timeout_s:.0f} s; steps: {' -> '.join(self.trace)}")

    def position_mm(self) -> float:
        with self.sim.rig.lock:
            self.sim.drive.sync()
            return self.sim.rig.slider.position_mm

    def settle(self, timeout_s: float = 5.0) -> None:
        """Until the simulated slider stands still (after a stop the drive decelerates)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.sim.rig.lock:
                self.sim.drive.sync()
                if not self.sim.rig.slider.moving:
                    return
            time.sleep(0.01)

    def cli(self, *args: str, timeout_s: float = 40.0, env: dict | None = None) -> subprocess.CompletedProcess:
        try:
            return subprocess.run([sys.executable, "-m", "rig", *args], cwd=ROOT, capture_output=True,
                                  text=True, timeout=timeout_s, env=env or self.env)
        except subprocess.TimeoutExpired as exc:
            return subprocess.CompletedProcess(exc.cmd, -999, exc.stdout or "", f"hung for {timeout_s} s")

    # ------------------------------------------------------------ trials
    def start(self, name: str) -> dict:
        text, depth_mm, limit = PROTOCOLS[name]
        pos = self.position_mm()
        with self.sim.rig.lock:
            preload = self.sim.rig.tissue_force_N
        moves = self.sim.drive.moves
        before = set(self.out.glob("*.mcap")) if self.out.exists() else set()
        r = self.req({"cmd": "start", "protocol_text": text, "protocol_path": f"{name}.yaml",
                      "specimen": f"s{self.seed}"})
        self.last_start_wall = time.time()
        if not r["ok"]:
            inside = TRAVEL_MM[0] <= pos + REACH_MM.get(name, depth_mm) <= TRAVEL_MM[1]
            # a fault or an estop that left the probe in the specimen: a start is refused until the
            # probe is returned (or the operator confirms it); the soak returns it, as an operator would
            in_contact = "the probe is in contact" in r["error"]
            self.expect(not inside or "busy" in r["error"] or (in_contact and "rig return" in r["error"]),
                        "reply true", f"start '{name}' from {pos:.2f} mm refused: {r['error']}")
            time.sleep(0.1)
            self.expect(self.sim.drive.moves == moves, "reply true",
                        f"a refused start moved the drive ({r['error']})")
            after = set(self.out.glob("*.mcap")) if self.out.exists() else set()
            self.expect(after == before, "reply true", f"a refused start left a log: {after - before}")
            if in_contact:
                back = self.req({"cmd": "return"})
                self.trace.append("return")
                self.expect(back["ok"], "reply true", f"the return after '{r['error']}' was refused: {back}")
                self.settle()
            return r
        self.expect(r["log"] not in self.trials, "logs readable, outcome true",
                    f"the new trial's log {r['log']} has the name of an earlier one")
        rec = TrialRecord(r["log"], name, pos, preload, limit or CONFIG_MAX_FORCE_N,
                          deepest_mm=max(pos + depth_mm - SimParams().tissue.surface_mm, 0.0))
        if name == "force":
            rec.causes.append("fault")  # the limit is meant to trip
        self.trials[r["log"]] = rec
        self.current = rec
        return r

    def end_trial(self) -> None:
        """Wait for the running trial to end and check its outcome against what was done to it."""
        rec = self.current
        if rec is None:
            return
        st = self.wait_idle()
        self.current = None
        last = st.get("last") or {}
        # a lost or damaged reply ("completed") is ridden through: it adds no outcome of its own
        allowed = {"fault" if c == "disk_full" else c for c in rec.causes if c != "completed"} or {"completed"}
        if rec.stop_ok:
            # a fault already under way (a full disk shows at the writer's next flush, up to a
            # second later) may still end a trial whose stop was accepted
            allowed = {rec.stop_ok} | ({"estopped", "stopped"} & set(rec.causes)) \
                | ({"fault"} if {"fault", "disk_full"} & set(rec.causes) else set())
        rec.final = allowed | ({"interrupted"} if "disk_full" in rec.causes else set())
        feature = self._pending_feature(rec)
        self.expect(last.get("outcome") in allowed and last.get("log") == rec.log, "reply true",
                    f"the daemon says {last.get('outcome')!r} for {Path(str(last.get('log'))).name}; "
                    f"after {rec.causes or ['nothing']} expected one of {sorted(allowed)}", feature)
        self.check_log(rec, feature)

    def check_log(self, rec: TrialRecord, feature: str | None = None) -> None:
        try:
            log = read_log(rec.log)
        except RigError as exc:
            self.expect(False, "logs readable, outcome true", f"{rec.log}: {exc}", feature)
            return
        if rec.final is not None:
            self.expect(log.outcome in rec.final, "logs readable, outcome true",
                        f"{Path(rec.log).name} says {log.outcome!r} ({log.n} samples), "
                        f"expected one of {sorted(rec.final)} after {rec.causes or ['nothing']}",
                        feature or self._pending_feature(rec))
            if log.outcome == "completed":
                self.expect(log.complete and any(e["kind"] == "trial_end" for e in log.events),
                            "logs readable, outcome true", f"{rec.log} says completed but has no end")

    # ------------------------------------------------------------ invariants
    def check_all(self) -> None:
        """After every step: the daemon answers, the slider is inside its travel, the tissue never
        carried more than the limit allows, every log reads with a true outcome."""
        if self.proc is not None:
            try:
                ok = self.req({"cmd": "ping"}, 5.0)["ok"]
            except RigError as exc:
                ok, exc_text = False, str(exc)
            else:
                exc_text = ""
            self.expect(ok and self.proc.poll() is None, "daemon answers",
                        f"ping failed ({exc_text}); exit status {self.proc.poll()}")
        pos = self.position_mm()
        self.expect(TRAVEL_MM[0] <= pos <= TRAVEL_MM[1], "slider inside travel",
                    f"slider at {pos:.3f} mm, window {TRAVEL_MM}", self._pending_feature(self.current))
        self.check_force()
        for rec in list(self.trials.values()):
            if rec is not self.current:
                self.check_log(rec)
        known = {Path(p) for p in self.trials}
        for path in self.out.glob("*.mcap") if self.out.exists() else ():
            if path not in known:
                try:
                    read_log(path)
                    ok, why = True, ""
                except RigError as exc:
                    ok, why = False, str(exc)
                self.expect(ok, "logs readable, outcome true", f"{path}: {why}")

    def check_force(self) -> None:
        peak = self.sim.rig.take_peak_force_N()
        # a specimen made stiffer mid-trial rises faster: one tick's rise scales with it
        scale = max(self.sim.params.faults.stiffness_scale, self.stiffness_seen)
        self.stiffness_seen = self.sim.params.faults.stiffness_scale
        rec = self.current
        if rec is None:
            limit, deepest, feature = CONFIG_MAX_FORCE_N, max(self.position_mm(), 0.0), None
        else:
            limit, deepest = rec.limit_N, rec.deepest_mm
            feature = "preload_limit" if rec.preload_N > 0.05 else self._pending_feature(rec)
        margin = force_margin_N(deepest) * scale
        self.expect(peak <= limit + margin, "force within limit + one tick's rise",
                    f"the tissue carried {peak:.2f} N, limit {limit:g} N + {margin:.2f} N"
                    + (f" (trial '{rec.protocol}' started at {rec.start_mm:.2f} mm with "
                       f"{rec.preload_N:.2f} N on the tissue)" if rec else ""), feature)

    # ------------------------------------------------------------ faults
    def fsize_limit(self, limit: int | None) -> None:
        """Disk full for the daemon from now (its next write past `limit` bytes fails), or free."""
        soft = resource.RLIM_INFINITY if limit is None else limit
        _, hard = resource.prlimit(self.proc.pid, resource.RLIMIT_FSIZE)
        resource.prlimit(self.proc.pid, resource.RLIMIT_FSIZE, (soft, hard))
        self.fsize_limited = limit is not None

    def step_clock_back(self) -> float:
        """The wall clock steps back to just before the last start: the next log's name is taken."""
        back = time.time() - self.last_start_wall + 0.2
        self.clock_offset_s -= back
        self.clock_file.write_text(repr(self.clock_offset_s))
        time.sleep(0.1)  # the daemon re-reads the offset every 50 ms
        return back

    def heal_cell(self) -> None:
        """The load cell and the specimen as they were (after a trial that froze or stiffened them)."""
        f = self.sim.params.faults
        f.loadcell_frozen = f.loadcell_noiseless = False
        f.stiffness_scale = 1.0

    def logs_now(self) -> set[Path]:
        return set(self.out.rglob("*.mcap")) if self.out.exists() else set()

    def no_start_after(self, before: set[Path], what: str, returning: bool = False) -> None:
        """An acknowledged stop: the slider stands still, and no trial it met or that came after
        it ran on: every log not in `before` (a campaign's folders included) ended stopped,
        estopped, aborted or faulted, or holds no motion. An abort returns to the start first:
        its trial's end is waited for."""
        if returning:
            self.wait_idle(60)
        self.settle()
        moves = self.sim.drive.moves
        time.sleep(1.0)
        self.expect(self.sim.drive.moves == moves and not self.sim.rig.slider.moving,
                    "stop acknowledged: stopped, nothing starts",
                    f"after {what} was acknowledged the drive took {self.sim.drive.moves - moves} more moves")
        for path in sorted(self.logs_now() - before):
            log = read_log(path)
            started = log.trial.get("start_time", "")
            self.expect(log.n <= 1 or log.outcome in ("estopped", "stopped", "aborted", "fault"),
                        "stop acknowledged: stopped, nothing starts",
                        f"{path.name} (started {started}) ran to {log.outcome!r} after {what} was acknowledged")

    def reset_drive_alarm(self) -> None:
        if not self.sim.params.faults.alarm_code:
            return
        r = self.req({"cmd": "reset_alarm"})
        self.expect(r["ok"] and self.sim.params.faults.alarm_code == 0, "reply true",
                    f"reset_alarm replied {r}; the drive reports 0x{self.sim.params.faults.alarm_code:02X}")





# ---------------------------------------------------------------------- the state machine


STOP_OUTCOME = {"abort": "aborted", "hold": "stopped", "estop": "estopped"}
REPORT: list[Soak] = []  # every soak run, for the bench's printout


class SoakMachine(RuleBasedStateMachine):
    soak: Soak | None = None
    seed_value = 0

    @initialize()
    def up(self) -> None:
        self._dir = Path(tempfile.mkdtemp(prefix="rig-soak-"))
        self.soak = Soak(self._dir, seed=self.seed_value)
        REPORT.append(self.soak)

    def teardown(self) -> None:
        if self.soak is not None:
            try:
                self._finish_trial()
            finally:
                self.soak.close()
                shutil.rmtree(self._dir, ignore_errors=True)

    # ------------------------------------------------------------ helpers
    @property
    def idle(self) -> bool:
        return self.soak is not None and self.soak.proc is not None and self.soak.current is None

    @property
    def running(self) -> bool:
        return self.soak is not None and self.soak.proc is not None and self.soak.current is not None

    def _into_trial(self, timeout_s: float = 8.0) -> bool:
        """Until the slider has left the trial's start by 0.5 mm: False if the trial ended first."""
        s = self.soak
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if abs(s.position_mm() - s.current.start_mm) >= 0.5:
                return True
            if not s.busy():
                return False
            time.sleep(0.01)
        return False

    def _finish_trial(self) -> None:
        s = self.soak
        if s.current is None:
            return
        if s.proc is not None:
            s.end_trial()
        if s.fsize_limited and s.proc is not None:
            s.fsize_limit(None)
        if s.sim.bridge is not None and s.sim.bridge.client_master < 0:
            s.sim.bridge.restore()
            s.step("port back; daemon restarted")
            s.stop_daemon()
            s.start_daemon()
        s.settle()
        if s.proc is not None:
            s.reset_drive_alarm()
        s.heal_cell()

    # ------------------------------------------------------------ rules
    def start(self, name: str) -> None:
        self.soak.step(f"start {name}")
        self.soak.start(name)

    def move_back_through_the_daemon(self) -> None:
        s = self.soak
        back = -round(s.position_mm(), 2)
        s.step(f"start back {back:+.2f} mm")
        PROTOCOLS["back"] = (f"name: back\nsteps:\n  - ramp: {{to_mm: {back}, speed_mm_s: 5}}\n", back, None)
        s.start("back")
        s.end_trial()

    def finish(self) -> None:
        self.soak.step("wait for the end")
        self._finish_trial()

    def start_while_busy(self) -> None:
        s = self.soak
        s.step("start while busy")
        if not s.busy():  # it ended by itself (a force fault is quick)
            return
        r = s.req({"cmd": "start", "protocol_text": SHORT, "protocol_path": "b.yaml"})
        if r["ok"]:  # only true if the trial ended between the two requests
            s.expect(read_log(s.current.log).complete, "reply true",
                     f"a start while a trial runs was answered {r}")
            s.end_trial()
            rec = TrialRecord(r["log"], "short", s.position_mm(), 0.0, CONFIG_MAX_FORCE_N, 3.0)
            s.trials[r["log"]] = s.current = rec
            return
        s.expect("busy" in r["error"], "reply true", f"a start while a trial runs was answered {r}")

    def stop(self, mode: str, delay: float) -> None:
        s = self.soak
        rec = s.current
        s.step(f"{mode} after {delay:g} s")
        time.sleep(delay)
        stops = s.sim.drive.stops
        r = s.req({"cmd": "estop"} if mode == "estop" else {"cmd": "stop", "mode": mode})
        if r["ok"] and "already stopped" in r.get("message", ""):
            return  # the truth: a fault stopped the slider first
        if r["ok"] and ("no trial was running" in r.get("message", "")
                        or "while it closed its log" in r.get("message", "")):
            # the trial ended (a quick fault) or was closing its log when the request came: the
            # STOP reached the drive, and the trial's outcome stays its own
            s.expect(s.sim.drive.stops > stops, "reply true", f"{mode} answered ok but no STOP reached "
                     f"the drive ({r})")
            return
        if r["ok"]:
            s.expect(s.sim.drive.stops > stops, "reply true",
                     f"{mode} answered ok but no STOP reached the drive ({r})")
            if rec.stop_ok is None or mode == "estop":
                rec.stop_ok = STOP_OUTCOME[mode]
            elif mode == "hold" and rec.stop_ok == "aborted":
                # a hold during an abort's return stops it where it is ("stopped"), unless the
                # return had already arrived ("aborted")
                rec.causes.append("stopped")
            return
        ended = "no trial is running" in r["error"] or "ended" in r["error"]
        # refused because the trial had ended by itself, or because a fault had already stopped the
        # slider (its STOP went first), is the truth; anything else is a lost stop
        faulted = "already stopped by a fault" in r["error"] and s.sim.drive.stops > 0
        # a stop of another kind in progress (an estop a moment earlier) is a true refusal too
        stopping = "already stopping" in r["error"] and s.sim.drive.stops > 0
        # with the port pulled no STOP can reach the drive, and the reply says exactly that
        unreachable = (("did not acknowledge" in r["error"] or "not acknowledged" in r["error"])
                       and s.sim.bridge is not None and s.sim.bridge.client_master < 0)
        s.expect(ended or faulted or stopping or unreachable, "reply true",
                 f"{mode} {delay:g} s after the start was refused: {r['error']}", "stop_anytime")

    def cell_fault(self, kind: str) -> None:
        """The load cell freezes or goes noiseless (a fault within half a second, under any step),
        or the specimen triples its stiffness (the force loop holds; position steps carry on)."""
        s = self.soak
        s.step(kind)
        if not self._into_trial():
            return
        if kind == "stiffness_jump":
            s.sim.params.faults.stiffness_scale = 3.0
            if s.current.protocol == "force":  # its limit trips the sooner; nothing else changes
                return
            s.current.causes.append("completed")  # ridden through
            return
        setattr(s.sim.params.faults, kind, True)
        s.current.causes.append("fault")

    def start_racing_stop(self, mode: str, delay: float) -> None:
        """A start and a stop (or estop) `delay` apart, from two clients: whatever the order, a stop
        that was acknowledged leaves the slider stopped and no trial running after it; a start that
        it cancelled says so and wrote no log."""
        s = self.soak
        s.step(f"start racing a {mode} {delay:g} s later")
        replies: dict = {}
        before = s.logs_now()

        def start() -> None:
            replies["start"] = s.req({"cmd": "start", "protocol_text": SLOW, "protocol_path": "race.yaml",
                                      "specimen": f"race{s.seed}"})

        t = threading.Thread(target=start)
        t.start()
        time.sleep(delay)
        r = s.req({"cmd": "estop"} if mode == "estop" else {"cmd": "stop", "mode": mode})
        t.join(30)
        rs = replies.get("start") or {"ok": False, "error": "no reply"}
        s.last_start_wall = time.time()
        log = rs.get("log") if rs.get("ok") else None
        if not rs["ok"]:
            s.expect("cancelled" in rs["error"] or "busy" in rs["error"], "reply true",
                     f"a start racing a {mode} was refused: {rs['error']}")
        # what the stop met, as its reply says: a trial running or a start being set up; a stop that
        # met neither came before the start reached the daemon, and that start runs as usual
        met = bool(r["ok"] and (r.get("trial_running") or r.get("cancelled")))
        if met:
            s.no_start_after(before, f"{mode} racing a start", returning=mode == "abort")
        elif not r["ok"]:  # refused: only because nothing was running or being set up when it came
            s.expect("no trial is running" in r["error"], "reply true",
                     f"a {mode} racing a start was refused: {r['error']}")
        if log is not None:
            rec = TrialRecord(log, "slow", 0.0, 0.0, CONFIG_MAX_FORCE_N, 6.0)
            rec.final = {STOP_OUTCOME[mode]} if met else {"completed"}
            s.trials[log] = rec
            s.wait_idle()
            s.check_log(rec)
        s.wait_idle()
        s.settle()
        s.heal_cell()

    def campaign(self, mode: str, delay: float) -> None:
        """`rig start --characterize`, stopped (or estopped) `delay` seconds in: whatever the campaign
        was doing (its first approach, between trials, fitting), the stop ends it, the slider
        stops, and no trial of it starts after the acknowledged stop."""
        s = self.soak
        s.step(f"campaign, {mode} after {delay:g} s")
        before = s.logs_now()
        r = s.req({"cmd": "start", "characterize": {"max_trials": 3, "budget_min": 3},
                   "specimen": f"camp{s.seed}"})
        s.last_start_wall = time.time()
        if not r["ok"]:
            s.expect("busy" not in r["error"], "reply true", f"a campaign on an idle daemon: {r['error']}")
            return
        time.sleep(delay)
        stop = s.req({"cmd": "estop"} if mode == "estop" else {"cmd": "stop", "mode": mode})
        if stop["ok"]:
            s.no_start_after(before, f"{mode} of a campaign", returning=mode == "abort")
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            st = s.req({"cmd": "status"})
            if st["state"] == "idle" and (st.get("campaign") or {}).get("status") != "running":
                break
            time.sleep(0.1)
        st = s.req({"cmd": "status"})
        camp = st.get("campaign") or {}
        s.expect(camp.get("status") not in (None, "running"), "reply true",
                 f"a campaign stopped by {mode} ({stop}) still says {camp}")
        s.settle()

    def repeats(self) -> None:
        """A protocol past the repeat cap is refused at once, naming `repeat`; one just under it
        runs, its status answers, and an estop during it is acknowledged within the second."""
        s = self.soak
        s.step("repeat 20000, then 4900 estopped")
        t0 = time.monotonic()
        r = s.req({"cmd": "start", "protocol_text": REPEAT_OVER, "protocol_path": "many.yaml"})
        # refused for its size, or (true as well, nothing moved) for a position read the wire lost
        why = r.get("error", "")
        s.expect(not r["ok"] and ("repeat" in why or "cannot read the slider's position" in why)
                 and time.monotonic() - t0 < 5.0, "reply true",
                 f"a protocol of 40,000 steps: {r} after {time.monotonic() - t0:.1f} s")
        r = s.req({"cmd": "start", "protocol_text": REPEAT_UNDER, "protocol_path": "many.yaml"})
        s.last_start_wall = time.time()
        if not r["ok"]:
            s.expect("cannot read the slider's position" in r["error"], "reply true",
                     f"a protocol of 9,800 steps was refused: {r['error']}")
            return
        time.sleep(1.0)
        st = s.req({"cmd": "status"})
        snap = st.get("snapshot") or {}
        s.expect(snap.get("steps_total") == 9800 and snap.get("time_left_s", 0) > 100, "reply true",
                 f"status of the 9,800-step trial: {snap}")
        t0 = time.monotonic()
        stop = s.req({"cmd": "estop"})
        took = time.monotonic() - t0
        s.expect(stop["ok"] and took < 1.5, "reply true",
                 f"estop of the 9,800-step trial: {stop} in {took:.2f} s")
        rec = TrialRecord(r["log"], "many", 0.0, 0.0, CONFIG_MAX_FORCE_N, 1.0)
        rec.final = {"estopped"}
        s.trials[r["log"]] = rec
        s.wait_idle()
        s.check_log(rec)
        s.settle()

    def bad_name(self, name: str) -> None:
        """A specimen name that is a path: refused, or written inside the log folder, never outside."""
        s = self.soak
        s.step(f"specimen {name!r}")
        outside = Path("/tmp/rig-soak-outside")
        r = s.req({"cmd": "start", "protocol_text": SHORT, "protocol_path": "short.yaml", "specimen": name})
        s.last_start_wall = time.time()
        if r["ok"]:
            s.expect(Path(r["log"]).resolve().parent == s.out.resolve(), "names stay inside the log folder",
                     f"specimen {name!r} wrote {r['log']}")
            rec = TrialRecord(r["log"], "short", s.position_mm(), 0.0, CONFIG_MAX_FORCE_N, 3.0)
            s.trials[r["log"]] = s.current = rec
            s.end_trial()
        else:
            s.expect("specimen" in r["error"], "reply true", f"specimen {name!r} refused: {r['error']}")
        stray = [p for p in s.tmp.rglob("*.mcap") if s.out.resolve() not in p.resolve().parents]
        s.expect(not stray and not outside.exists() and not (s.tmp.parent / "up").exists(),
                 "names stay inside the log folder", f"specimen {name!r} left {stray}")

    def estop_idle(self) -> None:
        s = self.soak
        s.step("estop (idle)")
        stops = s.sim.drive.stops
        r = s.req({"cmd": "estop"})
        s.expect(r["ok"] and s.sim.drive.stops > stops, "reply true",
                 f"estop on an idle daemon: {r}, drive STOPs {stops} -> {s.sim.drive.stops}")

    def fault(self, kind: str) -> None:
        s = self.soak
        s.step(kind)
        if not self._into_trial():
            return
        if kind == "alarm":
            s.sim.params.faults.alarm_code = 0x30
        elif kind == "vanish":
            s.sim.bridge.vanish()
        else:
            s.fsize_limit(os.path.getsize(s.current.log))
        s.current.causes.append("disk_full" if kind == "disk_full" else "fault")

    def line_fault(self, kind: str) -> None:
        """One lost or damaged reply: ridden through."""
        s = self.soak
        s.step(f"one {kind.split('_')[0]} reply")
        if not self._into_trial():
            return
        setattr(s.sim.params.faults, kind, 1)
        s.current.causes.append("completed")

    def clock_step(self) -> None:
        back = self.soak.step_clock_back()
        self.soak.step(f"wall clock back {back:.1f} s")

    def second_daemon(self) -> None:
        s = self.soak
        s.step("second daemon" + (" during a trial" if s.current else ""))
        if s.current is not None:
            s.current.taint.add("owner_recovery")
        r = s.cli("daemon", "--config", str(s.cfg_path), "--socket", str(s.sock), timeout_s=20)
        s.expect(r.returncode not in (0, -999) and "another daemon" in r.stderr, "reply true",
                 f"a second daemon exited {r.returncode}: {r.stderr.strip()[-300:]}")

    def second_cli(self, kind: str) -> None:
        """A second process wants the drive the daemon owns: refused, naming the holder."""
        s = self.soak
        s.step(f"rig {kind} beside the daemon" + (" during a trial" if s.current else ""))
        if s.current is not None:
            s.current.taint.add("drive_lock")
        cfg = ["--config", str(s.cfg_path)]
        target = round(max(s.position_mm() - 1.0, 0.0), 2)
        before = sorted(s.out.glob("*.mcap"))
        if kind == "position":
            r = s.cli("position", *cfg)
        elif kind == "move":
            r = s.cli("move", "--to-mm", str(target), "--speed-mm-s", "5", *cfg)
        else:
            proto = s.tmp / "second.yaml"
            proto.write_text(SHORT)
            r = s.cli("run", str(proto), *cfg, "--quiet", "--specimen", "second")
        s.expect(r.returncode != -999, "daemon answers", f"rig {kind} hung")
        # with the port pulled the device itself is gone: "cannot open" is the truth then
        gone = s.sim.bridge is not None and s.sim.bridge.client_master < 0 and "cannot open" in r.stderr
        refused = r.returncode != 0 and ("daemon" in r.stderr or "in use" in r.stderr or gone)
        s.expect(refused, "reply true", f"rig {kind} beside a daemon owning the drive was not refused "
                 f"(exit {r.returncode}: {(r.stdout + r.stderr).strip()[-200:]})", "drive_lock")
        if refused:
            s.expect(sorted(s.out.glob("*.mcap")) == before, "reply true", f"a refused rig {kind} left a log")
        elif kind == "move" and r.returncode == 0 and s.current is None:
            pos = s.position_mm()
            s.expect(abs(pos - target) <= 0.05, "reply true",
                     f"rig move said '{r.stdout.strip()}' but the slider is at {pos:.3f} mm")

    def sigint_daemon(self) -> None:
        s = self.soak
        s.step("SIGINT to the daemon" + (" during a trial" if s.current else ""))
        if s.current is not None and not self._into_trial(3.0):
            # a short trial can end while the steps before this one run: an ordinary end, checked
            # as one (the signal then meets an idle daemon)
            self._finish_trial()
        if s.current is not None:
            s.current.causes.append("aborted")
            s.current.stop_ok = s.current.stop_ok or "aborted"
        code = s.stop_daemon(signal.SIGINT)
        s.expect(code == 0, "daemon answers", f"the daemon exited {code} on SIGINT")
        rec, s.current = s.current, None
        if rec is not None:
            rec.final = {rec.stop_ok, "fault"} if "fault" in rec.causes or "disk_full" in rec.causes \
                else {rec.stop_ok}
            if "disk_full" in rec.causes:
                rec.final |= {"interrupted"}
            s.check_log(rec, s._pending_feature(rec))
            if s.fsize_limited:
                s.fsize_limited = False  # the limit went with the process
        if s.sim.bridge.client_master < 0:
            s.sim.bridge.restore()
        s.settle()
        s.start_daemon()
        s.reset_drive_alarm()

    def sigint_rig_run(self) -> None:
        """Ctrl-C in `rig run` (on the built-in simulated rig, beside the daemon's): exit 130, log aborted."""
        s = self.soak
        s.step("Ctrl-C in rig run")
        out = s.tmp / "run-int"
        proto = s.tmp / "int.yaml"
        proto.write_text(SLOW)
        p = subprocess.Popen([sys.executable, "-m", "rig", "run", str(proto), "--out", str(out), "--quiet"],
                             cwd=ROOT, env=s.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 30
            while not list(out.glob("*.mcap")) and time.monotonic() < deadline and p.poll() is None:
                time.sleep(0.05)
            time.sleep(1.0)
            p.send_signal(signal.SIGINT)
            try:
                stdout, stderr = p.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                stdout, stderr = p.communicate(timeout=10)
                s.expect(False, "daemon answers", "rig run hung after Ctrl-C", "sigint_flag")
                return
        finally:
            if p.poll() is None:
                p.kill()
                p.wait(10)
        said = [line for line in (stdout + stderr).splitlines() if "fault" in line or "trial" in line]
        s.expect(p.returncode == 130 and "trial aborted" in stdout, "reply true",
                 f"rig run after Ctrl-C exited {p.returncode}: {' | '.join(said)[-400:]}")
        for path in out.glob("*.mcap"):
            log = read_log(path)
            s.expect(log.outcome == "aborted", "logs readable, outcome true",
                     f"{path.name} says {log.outcome} after Ctrl-C")
            path.unlink()

    # Each step is one of these, drawn among those that apply now (a single rule, so that every
    # example mixes them all: hypothesis' own rule choice leaves some rules out of an example),
    # with its arguments drawn from the lists beside it.
    ACTIONS: ClassVar[dict] = {
        "start": (lambda m: m.idle, {"name": sorted(PROTOCOLS)}),
        "move_back_through_the_daemon": (lambda m: m.idle and m.soak.position_mm() > 0.5, {}),
        "finish": (lambda m: m.running, {}),
        "start_while_busy": (lambda m: m.running, {}),
        "stop": (lambda m: m.running, {"mode": ["abort", "hold", "estop"],
                                       "delay": [0.0, 0.4, 1.0]}),
        "estop_idle": (lambda m: m.idle, {}),
        "fault": (lambda m: m.running, {"kind": ["alarm", "vanish", "disk_full"]}),
        "line_fault": (lambda m: m.running,
                       {"kind": ["drop_replies", "corrupt_replies", "garble_replies"]}),
        "clock_step": (lambda m: m.soak.proc is not None and m.soak.last_start_wall > 0,
                       {}),
        "second_daemon": (lambda m: m.soak.proc is not None, {}),
        "second_cli": (lambda m: m.soak.proc is not None,
                       {"kind": ["position", "move", "run"]}),
        "sigint_daemon": (lambda m: m.soak.proc is not None, {}),
        "sigint_rig_run": (lambda m: True, {}),
        "cell_fault": (lambda m: m.running,
                       {"kind": ["loadcell_frozen", "loadcell_noiseless", "stiffness_jump"]}),
        "start_racing_stop": (lambda m: m.idle and m.soak.position_mm() < 20,
                              {"mode": ["estop", "hold", "abort"], "delay": [0.0, 0.005, 0.03, 0.15, 0.6]}),
        "campaign": (lambda m: m.idle, {"mode": ["estop", "hold", "abort"], "delay": [0.2, 2.0, 6.0]}),
        "repeats": (lambda m: m.idle and m.soak.position_mm() < 30, {}),
        "bad_name": (lambda m: m.idle, {"name": BAD_NAMES}),
    }
    # starts and trial-time events more often than the slow process-level ones
    WEIGHTS: ClassVar[dict] = {"start": 4, "finish": 2, "stop": 3, "fault": 3, "line_fault": 2,
                               "sigint_rig_run": 1, "cell_fault": 3, "start_racing_stop": 2}

    @rule(data=st.data())
    def act(self, data) -> None:
        names = [n for n, (pre, _) in self.ACTIONS.items() if pre(self)]
        pool = [n for n in names for _ in range(self.WEIGHTS.get(n, 1))]
        # hypothesis starts from the simplest draw (0, every step): turned by the step number and
        # the seed, that draw still walks through every action, and it shrinks the same way
        step = len(self.soak.trace)
        idx = data.draw(st.integers(0, len(pool) - 1), label="action")
        name = pool[(idx + 7 * step + self.seed_value) % len(pool)]
        # the same for its arguments: the simplest draw alone would give every stop an abort,
        # every fault an alarm and every start the first protocol
        kwargs = {}
        for k, options in self.ACTIONS[name][1].items():
            i = data.draw(st.integers(0, len(options) - 1), label=k)
            kwargs[k] = options[(i + 3 * step + 5 * self.seed_value) % len(options)]
        try:
            getattr(self, name)(**kwargs)
        except Exception as exc:  # recorded for the report, then raised as it was
            if not self.soak.failures or self.soak.failures[-1] not in str(exc):
                self.soak.failures.append(f"{name}({kwargs}): {type(exc).__name__}: {exc}\n  steps: "
                                          + " -> ".join(self.soak.trace[-12:]))
            raise

    @invariant()
    def invariants(self) -> None:
        if self.soak is not None:
            self.soak.check_all()
