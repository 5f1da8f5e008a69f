"""`rig probe`: do the slider and the load cell a config names answer, and how fast?

Nothing moves. The drive is read (position, status and alarm) and its communication
timeout written and read back, as every trial does on connect; the load cell is listened
to (or asked, when polled). Then, for a few seconds, the loop's bus traffic is replayed
at the loop's rate (a position read every tick, status every `loop.status_every`th, the
load cell's request when polled) and each transaction is timed against the period.
Every problem names the config field to look at.
"""

from __future__ import annotations

import contextlib
import copy
import os
import statistics
import time

from rig.clock import slots_behind
from rig.drivers.alarms import alarm_meaning
from rig.drivers.spy import MemoryTap, Tee
from rig.drivers.wireframes import FROM_DEVICE, TO_DEVICE
from rig.errors import DeviceError, RigError
from rig.specs.config import RigConfig
from rig.views.probe_report import ProbeReport, Timing

# The first contact waits this long for a reply, to tell a slow drive from a silent one.
DIAGNOSTIC_TIMEOUT_S = 0.5


def probe(config: RigConfig, *, seconds: float = 2.0, spy_path: str | None = None) -> ProbeReport:
    """Probe the rig `config` names; the built-in simulated rig is started on the wire."""
    from rig.control.devices import open_spy, wire_config

    sb, lb = config.slider.backend, config.loadcell.backend
    if (sb == "sim") != (lb == "sim"):
        raise RigError(f"slider backend '{sb}' and load-cell backend '{lb}': the simulated rig "
                       "provides both devices, so use 'sim' for both or for neither")
    sim = None
    cfg = config
    target = f"{config.name} ({config.source_path})"
    if sb == "sim":
        from rig.sim.process import SimProcess

        if config.sim.wire == "none":
            config = copy.deepcopy(config)
            config.sim.wire = "rtu"  # a probe is of the wire
        sim = SimProcess(config.text())
        cfg = wire_config(config, sim.endpoints)
        target = f"the simulated rig on the wire (a `rig sim` process, Modbus {config.sim.wire.upper()})"
    report = ProbeReport(target, 1000.0 / cfg.loop.rate_Hz, seconds)
    spy = None
    try:
        spy = open_spy(spy_path, cfg) if spy_path else None
        _Probe(cfg, report, spy).run()
    finally:
        if spy is not None:
            spy.close()
        if sim is not None:
            sim.close()
    return report


class _Probe:
    def __init__(self, cfg: RigConfig, report: ProbeReport, spy) -> None:
        self.cfg = cfg
        self.r = report
        self.spy = spy
        self.cell_tap = MemoryTap()
        self.slider = None
        self.cell = None
        self.failed_before = 0  # failed transactions of a link closed before the timing
        self.window = (0.0, 0.0)  # monotonic start and end of the timed traffic
        self.error_before = ""
        self.asked_before = 0

    def run(self) -> None:
        try:
            self._open_slider()
            self._open_loadcell()
            if self.slider is not None or self.cell is not None:
                self._traffic()
            if self.cell is not None:
                self._judge_loadcell()
        finally:
            for dev in (self.slider, self.cell):
                if dev is not None:
                    with contextlib.suppress(Exception):
                        dev.close()

    # ------------------------------------------------------------ slider
    def _slider_fields(self) -> list[str]:
        s = self.cfg.slider
        if s.backend == "modbus-tcp":
            return ["slider.host", "slider.tcp_port", "slider.device_id"]
        return ["slider.port", "slider.baudrate", "slider.parity", "slider.stopbits", "slider.device_id"]

    def _make(self, timeout_s: float | None = None):
        from rig.control.devices import make_slider

        return make_slider(self.cfg, tap=self.spy, timeout_s=timeout_s, max_consecutive_errors=10**9)

    def _open_slider(self) -> None:
        """First contact with a long timeout, so a slow drive is told from a silent one and its
        status is read right; then the configured timeout, for the timing a trial will see."""
        from rig.control.devices import slider_link

        s, r = self.cfg.slider, self.r
        link = slider_link(self.cfg)
        r.slider.update(link=f"{link.describe()}, profile {s.profile}", device_id=s.device_id)
        try:
            slider = self._make(DIAGNOSTIC_TIMEOUT_S)
        except DeviceError as exc:
            r.slider["why"] = "cannot open the port"
            r.problem("slider", str(exc) + _missing(s.port if link.transport == "rtu" else ""),
                      self._slider_fields()[:2])
            return
        first, took_ms = None, 0.0
        for _ in range(4):  # a lost or corrupted reply or two is not silence
            t0 = time.perf_counter()
            with contextlib.suppress(DeviceError):
                reading = slider.position()
                if reading.fresh:
                    first, took_ms = reading, (time.perf_counter() - t0) * 1000
                    break
        if first is None:
            r.slider["why"] = f"no answer within {DIAGNOSTIC_TIMEOUT_S * 1000:g} ms"
            r.problem("slider", f"no answer from unit {s.device_id} ({slider.last_error}), not even within "
                                f"{DIAGNOSTIC_TIMEOUT_S * 1000:g} ms",
                      self._slider_fields(), "check the cable (A/B may be swapped), the drive's power, its "
                                             "baud-rate and ID switches, and the RS-485 termination")
            slider.close()
            return
        # a slow drive is slow every time; a machine busy with other work, now and then
        for _ in range(2):
            if took_ms <= s.timeout_s * 1000:
                break
            t0 = time.perf_counter()
            with contextlib.suppress(DeviceError):
                if slider.position().fresh:
                    took_ms = min(took_ms, (time.perf_counter() - t0) * 1000)
        # a drive that answers only after its timeout does not answer a trial
        r.slider_answers = took_ms <= s.timeout_s * 1000
        if not r.slider_answers:
            r.slider["why"] = f"answers only after {took_ms:.1f} ms"
            r.problem("slider", f"the drive answers, but after {took_ms:.1f} ms: later than slider.timeout_s "
                                f"({s.timeout_s * 1000:g} ms), so every read times out, and on RTU a late "
                                "reply can be taken for the next request's",
                      ["slider.timeout_s", "slider.baudrate", "loop.rate_Hz"],
                      "a USB-serial adapter's latency timer adds up to 16 ms: see `rig ports`")
        steps = round(first.value * s.steps_per_mm)
        r.slider.update(position_mm=first.value, position_steps=steps, steps_per_mm=s.steps_per_mm,
                        first_reply_ms=round(took_ms, 3))
        self.slider = slider
        self._status()
        self._comm_timeout()
        self.failed_before, self.asked_before = slider.stats.errors, slider.stats.transactions
        self.error_before = slider.last_error
        slider.close()
        self.slider = None
        try:
            self.slider = self._make()
        except DeviceError as exc:
            r.problem("slider", f"cannot reopen the port: {exc}", self._slider_fields()[:1])

    def _status(self) -> None:
        r, s = self.r, self.cfg.slider
        reading = self.slider.status()
        if not reading.fresh:
            r.slider["status"] = f"not read ({self.slider.last_error})"
            r.problem("slider", f"the status read failed: {self.slider.last_error}",
                      ["slider.profile", "slider.registers.output_status", "slider.registers.alarm"])
            return
        st = reading.value
        words = [("ready" if st.ready else "NOT READY"), ("moving" if st.moving else "standing still"),
                 ("in position" if st.in_position else "not in position")]
        if st.alarm:
            meaning = alarm_meaning(s.profile, st.alarm_code)
            words.append(f"ALARM 0x{st.alarm_code:02X}: {meaning}")
            fields = ["slider.comm_timeout_s"] if st.alarm_code == 0x85 else []
            r.problem("slider", f"the drive reports alarm 0x{st.alarm_code:02X}: {meaning}; it will not move",
                      fields, "clear its cause, then `rig reset-alarm`; no trial starts until it is gone")
        else:
            words.append("no alarm")
            if not st.ready:
                r.problem("slider", "the drive is not READY (no alarm): is the motor excited, is STOP or "
                                    "FREE set by another master?",
                          ["slider.registers.bit_ready"], "check the drive's inputs and its display")
        r.slider["status"] = ", ".join(words)
        r.slider["alarm_code"] = st.alarm_code

    def _comm_timeout(self) -> None:
        r, s = self.r, self.cfg.slider
        fields = ["slider.registers.comm_timeout_ms", "slider.allow_no_comm_timeout"]
        if s.comm_timeout_s <= 0:
            r.slider["comm_timeout"] = "off (slider.comm_timeout_s is 0)"
            if not s.allow_no_comm_timeout:
                r.problem("slider", "slider.comm_timeout_s is 0: if the controller dies mid-move, nothing "
                                    "stops the drive, and `rig run` refuses to start",
                          ["slider.comm_timeout_s", "slider.allow_no_comm_timeout"])
            return
        try:
            written = self.slider.set_comm_timeout(s.comm_timeout_s)
        except DeviceError as exc:
            r.slider["comm_timeout"] = "NOT taken by the drive"
            r.problem("slider", f"the communication timeout was not taken: {exc}",
                      ["slider.registers.comm_timeout_ms"])
            return
        if written:
            r.slider["comm_timeout"] = (f"{s.comm_timeout_s:g} s written and read back (register "
                                        f"0x{self.slider.regs.comm_timeout_ms:04X})")
        elif s.allow_no_comm_timeout:
            r.slider["comm_timeout"] = (f"not set: profile '{s.profile}' has no register for it (allowed by "
                                        "slider.allow_no_comm_timeout)")
        else:
            r.slider["comm_timeout"] = f"cannot be set: profile '{s.profile}' has no register for it"
            r.problem("slider", f"profile '{s.profile}' does not know the drive's communication-timeout "
                                "register: `rig run` refuses to start until it is set (or explicitly waived)",
                      fields, "the parameter's address is in the drive manual (AZ: HM-60262E)")

    # ------------------------------------------------------------ load cell
    def _open_loadcell(self) -> None:
        from rig.control.devices import open_loadcell

        lc, r = self.cfg.loadcell, self.r
        r.loadcell["link"] = f"{lc.port} {lc.baudrate} baud, {lc.mode}" + (
            f" (request {lc.request!r})" if lc.mode == "poll" else "")
        try:
            self.cell = open_loadcell(self.cfg, None, tap=Tee(self.cell_tap, self.spy))
        except DeviceError as exc:
            r.loadcell["summary"] = "cannot open the port"
            r.problem("loadcell", str(exc) + _missing(lc.port), ["loadcell.port"])
            return
        if lc.mode == "poll":
            # a polled cell says nothing until asked: lines now mean it streams
            time.sleep(0.3)
            unasked = [x for x in self.cell_tap.records("cell") if x.direction == FROM_DEVICE]
            if len(unasked) >= 3:
                r.problem("loadcell", f"{len(unasked)} lines came in 0.3 s before any request: the cell "
                                      "streams on its own", ["loadcell.mode"], "set loadcell.mode: stream")
            self.cell_tap.chunks.clear()

    def _judge_loadcell(self) -> None:
        from rig.drivers.serial_loadcell import LineRejected, parse_line

        r, lc, cell = self.r, self.cfg.loadcell, self.cell
        recs = self.cell_tap.records("cell")
        rx = [x for x in recs if x.direction == FROM_DEVICE and x.data.strip()]
        tx = [x for x in recs if x.direction == TO_DEVICE]
        t0, t1 = self.window
        duration = max(t1 - t0, 1e-3)
        examples = []
        for x in rx[:3]:
            raw = repr(x.data.decode("ascii", "backslashreplace"))
            line = x.data.rstrip(b"\r\n")
            try:
                parsed = f"{parse_line(line, cell.fmt):.4f} N"
            except LineRejected as exc:
                parsed = f"rejected: {exc}"
            examples.append((raw, parsed))
        r.loadcell["examples"] = examples
        ok, bad = cell.stats.lines_ok, cell.stats.lines_bad + cell.stats.out_of_range
        r.loadcell.update(lines_ok=ok, lines_bad=bad, requests=len(tx))
        if not rx:
            if lc.mode == "stream":
                self._silent_stream()
            else:
                r.loadcell["summary"] = f"no answer to {len(tx)} requests {lc.request!r}"
                r.problem("loadcell", f"no answer to {len(tx)} requests {lc.request!r} in {duration:.1f} s",
                          ["loadcell.request", "loadcell.port", "loadcell.baudrate", "loadcell.mode"])
            return
        r.loadcell_answers = ok > 0
        rate = sum(t0 <= x.t_s <= t1 for x in rx) / duration
        text = f"{len(rx)} lines ({rate:.0f} lines/s while timed), {ok} parsed, {bad} bad"
        if lc.mode == "poll":
            rtts = _round_trips_ms(recs)
            if rtts:
                text += (f"; reply to a request: median {statistics.median(rtts):.2f} ms, "
                         f"worst {max(rtts):.2f} ms")
                r.loadcell.update(reply_median_ms=statistics.median(rtts), reply_worst_ms=max(rtts))
                if statistics.median(rtts) > r.period_ms:
                    r.problem("loadcell", f"a polled reading takes {statistics.median(rtts):.1f} ms "
                                          f"(median), longer than the {r.period_ms:g} ms loop period: every "
                                          "tick uses the reading of the tick before",
                              ["loadcell.baudrate", "loop.rate_Hz", "loadcell.mode"])
            missing = len(tx) - len(rx)
            if missing > max(2, 0.02 * len(tx)):
                r.problem("loadcell", f"{missing} of {len(tx)} requests got no reply",
                          ["loadcell.request", "loadcell.baudrate"])
        elif rate < 0.9 * 1000.0 / r.period_ms:
            r.problem("loadcell", f"{rate:.0f} lines/s is slower than the {1000 / r.period_ms:g} Hz loop: "
                                  "some ticks reuse the last reading",
                      ["loop.rate_Hz", "loadcell.mode"], "or raise the cell's own output rate")
        r.loadcell["summary"] = text
        r.loadcell["lines_per_s"] = round(rate, 1)
        if bad:
            why = cell.last_rejected or "?"
            if ok == 0:
                r.problem("loadcell", f"lines arrive but not one parses ({bad} bad; last: {why})",
                          ["loadcell.pattern", "loadcell.unit", "loadcell.baudrate"],
                          "garbage characters usually mean a wrong baud rate")
            else:
                r.problem("loadcell", f"{bad} of {ok + bad} lines did not parse (last: {why})",
                          ["loadcell.pattern", "loadcell.unit", "loadcell.max_abs_N", "loadcell.baudrate"],
                          "a few garbled lines are skipped and counted; many mean noise on the line")

    def _silent_stream(self) -> None:
        """A streaming cell that says nothing: does it answer when asked?"""
        r, lc, cell = self.r, self.cfg.loadcell, self.cell
        cell.mode = "poll"
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            cell.latest()
            time.sleep(0.01)
        answered = [x for x in self.cell_tap.records("cell") if x.direction == FROM_DEVICE and x.data.strip()]
        if answered:
            r.loadcell_answers = True
            r.loadcell["summary"] = f"silent until asked; answers {lc.request!r}"
            r.problem("loadcell", f"no line in {r.seconds:g} s of listening, but it answers the request "
                                  f"{lc.request!r}: it is a polled cell", ["loadcell.mode"],
                      "set loadcell.mode: poll")
            return
        r.loadcell["summary"] = f"no line in {r.seconds:g} s, nor when asked with {lc.request!r}"
        r.problem("loadcell", f"no line from the load cell in {r.seconds:g} s of listening, nor an answer to "
                              f"{lc.request!r}",
                  ["loadcell.port", "loadcell.baudrate", "loadcell.mode", "loadcell.request"],
                  "is the cell powered, its output switched on, the cable the right one?")

    # ------------------------------------------------------------ the loop's traffic, timed
    def _traffic(self) -> None:
        r, cfg = self.r, self.cfg
        period_s = r.period_ms / 1000.0
        pos, stat = Timing("position read"), Timing("status read")
        ticks_ms: list[float] = []
        n_ticks = max(1, round(r.seconds / period_s))
        t_next = time.perf_counter()
        self.window = (time.monotonic(), time.monotonic() + r.seconds)
        for k in range(n_ticks):
            tick_ms = 0.0
            if self.slider is not None:
                tick_ms += _timed(pos, self.slider.position)
                if k % cfg.loop.status_every == 0:
                    tick_ms += _timed(stat, self.slider.status)
                ticks_ms.append(tick_ms)
            if self.cell is not None:
                self.cell.latest()  # a polled cell is asked here, once a tick, as in a trial
            t_next += period_s
            delay = t_next - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            else:
                t_next = time.perf_counter()
        self.window = (self.window[0], time.monotonic())
        if self.slider is None:
            return
        r.timing = [pos, stat]
        r.worst_tick_ms = round(max(ticks_ms), 3)
        self._judge_timing(pos, ticks_ms)

    def _judge_timing(self, pos: Timing, ticks_ms: list[float]) -> None:
        r, s = self.r, self.cfg.slider
        # every transaction of the probe counts, the first contact's too
        failed = self.failed_before + self.slider.stats.errors
        total = self.asked_before + self.slider.stats.transactions
        # a trial rides through a single lost reply; a busy machine loses one now and then
        if failed > 0.01 * total:
            r.problem("slider", f"{failed} of {total} transactions got no valid answer within "
                                f"{self.slider.link.timeout_s * 1000:g} ms (last: "
                                f"{self.slider.last_error or self.error_before}); "
                                f"{s.max_consecutive_errors} in a row stop a trial",
                      ["slider.timeout_s", "slider.retries", "slider.baudrate"],
                      "lost or corrupted replies: check the cable, its shield and the RS-485 termination")
        if not pos.times_ms:
            return
        median = statistics.median(pos.times_ms)
        if median > 0.5 * r.period_ms:
            r.problem("timing", f"a position read takes {median:.1f} ms (median), more than half the "
                                f"{r.period_ms:g} ms loop period",
                      ["loop.rate_Hz", "slider.baudrate"],
                      "a USB-serial adapter's latency timer adds up to 16 ms: see `rig ports`")
            return
        # one slow tick is the machine, not the link: the loop rides it out (late_tolerance_ms),
        # so the ticks are judged by the loop's own rule, not by the period alone
        tol_ms = self.cfg.loop.late_tolerance_ms
        late, missed = loop_lateness(ticks_ms, r.period_ms, tol_ms)
        if late + missed > max(1, 0.02 * len(ticks_ms)):
            over = sum(t > r.period_ms for t in ticks_ms)
            r.problem("timing", f"{late} of {len(ticks_ms)} ticks would start more than {tol_ms:g} ms late "
                                f"(loop.late_tolerance_ms) and {missed} be skipped: {over} spent longer "
                                f"than the {r.period_ms:g} ms period on the bus "
                                f"(worst {r.worst_tick_ms:.1f} ms)",
                      ["loop.rate_Hz", "loop.status_every", "slider.baudrate"])


def loop_lateness(ticks_ms: list[float], period_ms: float, tolerance_ms: float) -> tuple[int, int]:
    """(late, skipped) ticks of a loop whose ticks take `ticks_ms` each, by the trial loop's rule
    (rig.control.trial): a tick starts at its slot or when the one before ends, whichever is
    later; whole periods behind are skipped (`slots_behind`), and one starting more than
    `tolerance_ms` after its slot is late. A single long tick is ridden out by the slack of the
    ticks after it."""
    end = 0.0
    slot = late = skipped = 0
    for took in ticks_ms:
        start = max(end, slot * period_ms)
        behind = slots_behind(start - slot * period_ms, period_ms)
        skipped += behind
        slot += behind
        late += start - slot * period_ms > tolerance_ms
        slot += 1
        end = start + took
    return late, skipped


def _missing(port: str) -> str:
    if port.startswith("/dev/") and not os.path.exists(port):
        return f" ({port} does not exist: `rig ports` lists the serial ports)"
    return ""


def _timed(timing: Timing, call) -> float:
    t0 = time.perf_counter()
    try:
        reading = call()
    except DeviceError:
        reading = None
    ms = (time.perf_counter() - t0) * 1000.0
    if reading is None or not reading.fresh:
        timing.failed += 1
    else:
        timing.times_ms.append(ms)
    return ms


def _round_trips_ms(recs) -> list[float]:
    """Each request to the first line after it."""
    out, asked = [], None
    for x in recs:
        if x.direction == TO_DEVICE:
            asked = x.t_s
        elif asked is not None and x.data.strip():
            out.append((x.t_s - asked) * 1000.0)
            asked = None
    return out
