"""Force-controlled steps (`ramp_force`, `hold_force`): the force loop on three simulated tissues
100x apart in stiffness, in virtual time and over Modbus RTU at 100 Hz, and every way a force
step can be stopped.

Tissues: the paper's specimen with its stiffness terms scaled by 0.1, 1 and 10, each read by a
load cell suited to it (noise 4, 40, 80 mN) and driven to a force 30-190x its noise (0.15,
1.5, 15 N: the force near 25 mm of indentation). The overshoot and the settling are read on the
force averaged over 0.1 s (its noise there is a few tenths of a per cent of the target); the
RMS error over the hold past its first second, against the noise the tare measured."""

from __future__ import annotations

import json
import math
import threading

import numpy as np
import pytest

from rig.clock import VirtualClock
from rig.control.devices import open_devices
from rig.control.states import StopMode
from rig.control.trial import Trial
from rig.errors import LimitError, SpecError
from rig.recording.logs import read_log
from rig.service.run import RunOptions, run_trial
from rig.specs.config import RigConfig
from rig.specs.protocol import check_limits, parse_protocol

TISSUES = {"gel": (0.1, 0.004, 0.15), "tissue": (1.0, 0.04, 1.5), "tendon": (10.0, 0.08, 15.0)}
HOLD_S = 3.0


def _protocol(target_N: float, hold_s: float = HOLD_S) -> str:
    return (f"name: force step to {target_N:g} N\nsteps:\n"
            "  - ramp: {to_mm: 5, speed_mm_s: 5}\n"
            f"  - ramp_force: {{to_N: {target_N}, rate_N_s: {target_N}, max_mm: 35}}\n"
            f"  - hold_force: {{force_N: {target_N}, duration_s: {hold_s}, max_mm: 35}}\n"
            "  - return: {speed_mm_s: 10}\n")


def _config(tissue: str, seed: int) -> RigConfig:
    scale, noise, _ = TISSUES[tissue]
    cfg = RigConfig()
    t = cfg.sim.tissue
    for k in ("k1_N_per_m3", "k2_N_per_m2", "k3_N_per_m", "tau2_N_s_per_m2"):
        setattr(t, k, getattr(t, k) * scale)
    cfg.sim.loadcell.noise_N = noise
    # the rig set up for its specimen: the estimator's noise and contact threshold follow the load cell
    cfg.estimator.noise_N = noise
    cfg.estimator.contact_N = 0.05 * scale
    cfg.sim.seed = seed
    cfg.loop.tare_s = 2.0  # 200 readings: the noise the error is judged against known to 5 %
    return cfg


def _measure(log, target_N: float) -> dict:
    """Overshoot (share of the target), settling time from the hold's start (s), RMS error over
    the hold past its first second in units of the tare's noise."""
    s = log.samples
    kind = np.asarray(log.step_kind)
    t, f = np.asarray(s["t_s"]), np.asarray(s["force_N"])
    noise = float(np.std(f[kind == "tare"]))
    smooth = np.convolve(f, np.ones(10) / 10, mode="same")
    hold = kind == "hold_force"
    th, sh = t[hold], smooth[hold]
    outside = np.flatnonzero(np.abs(sh - target_N) > 0.05 * target_N)
    settle = float(th[outside[-1]] - th[0]) if len(outside) else 0.0
    late = hold & (t >= th[0] + 1.0)
    rms = float(np.sqrt(np.mean((f[late] - target_N) ** 2)))
    ramp_and_hold = (kind == "ramp_force") | hold
    return {"overshoot": float((smooth[ramp_and_hold].max() - target_N) / target_N), "settle_s": settle,
            "rms_over_noise": rms / noise, "creep_mm": float(np.ptp(np.asarray(s["position_mm"])[hold]))}


def _check(m: dict) -> None:
    assert m["overshoot"] <= 0.05, m
    assert m["settle_s"] <= 1.0, m
    assert m["rms_over_noise"] <= 1.5, m


@pytest.mark.parametrize("tissue", TISSUES)
def test_force_holds_on_tissues_100x_apart(tissue, tmp_path):
    """Five seeds each, in virtual time."""
    target = TISSUES[tissue][2]
    for seed in range(1, 6):
        result = run_trial(parse_protocol(_protocol(target), "<test>"), _config(tissue, seed),
                           RunOptions(speed=0, progress=False, log_path=tmp_path / f"{seed}.mcap"))
        assert result.outcome == "completed", result.fault
        m = _measure(read_log(result.log_path), target)
        _check(m)
        assert m["creep_mm"] > 0.05, m  # the tissue relaxes: held at a force, it creeps


@pytest.mark.parametrize("tissue", ["tissue"])  # all three, five seeds each: tests/bench/test_bench_force.py
def test_force_holds_over_modbus_rtu_at_100_hz(tissue, tmp_path):
    """The same loop on the simulated devices over Modbus RTU (bytes paced at the baud rate) and
    a serial load cell, on the real clock, one seed each: it holds the force. How well (the 5 %,
    1 s and 1.5x targets) is timing, measured where the machine is not shared with the rest of
    the suite: tests/bench/test_bench_force.py, five seeds."""
    target = TISSUES[tissue][2]
    cfg = _config(tissue, 7)
    cfg.sim.wire = "rtu"
    result = run_trial(parse_protocol(_protocol(target), "<test>"), cfg,
                       RunOptions(speed=1.0, progress=False, log_path=tmp_path / "rtu.mcap"))
    assert result.outcome == "completed", result.fault
    log = read_log(result.log_path)
    assert "Modbus RTU" in log.trial["devices"]
    m = _measure(log, target)
    assert m["overshoot"] <= 0.10 and m["settle_s"] <= 2.0 and m["rms_over_noise"] <= 3.0, m
    assert m["creep_mm"] > 0.05, m


def _stopped(tmp_path, mode: StopMode, into_hold_s: float = 1.0):
    """A trial stopped by `mode` during its hold at 1.5 N, `into_hold_s` after the hold began."""
    cfg = _config("tissue", 3)
    proto = parse_protocol(_protocol(1.5, hold_s=5.0), "<test>")
    clock = VirtualClock(0)
    dev = open_devices(cfg, clock)
    trial = Trial(proto, cfg, dev.slider, dev.loadcell, clock, tmp_path / "stop.mcap")
    fired = threading.Event()
    seen = {}

    def stopper(snap):
        seen.setdefault(snap.step_kind, snap.t_s)
        if snap.t_s >= seen.get("hold_force", float("inf")) + into_hold_s and not fired.is_set():
            fired.set()
            seen["kind_at_stop"] = snap.step_kind
            trial.request_stop(mode, user="tester")

    trial.on_tick = stopper
    return trial.run(), read_log(trial.log_path), seen


def test_abort_during_a_force_hold_stops_then_returns(tmp_path):
    result, log, seen = _stopped(tmp_path, StopMode.ABORT)
    assert seen["kind_at_stop"] == "hold_force"
    assert result.outcome == "aborted"
    assert abs(log.samples["position_mm"][-1]) <= 0.02  # back at the start
    assert "hold_force" not in log.step_kind[-50:]


def test_hold_during_a_force_hold_stays_put(tmp_path):
    result, log, seen = _stopped(tmp_path, StopMode.HOLD)
    assert seen["kind_at_stop"] == "hold_force" and result.outcome == "stopped"
    pos = np.asarray(log.samples["position_mm"])
    assert pos[-1] > 5.0 and np.ptp(pos[-30:]) <= 0.01  # where the force loop had it, not moving


def test_estop_during_a_force_hold_stops_the_motor(tmp_path):
    result, log, seen = _stopped(tmp_path, StopMode.ESTOP)
    assert seen["kind_at_stop"] == "hold_force" and result.outcome == "estopped"
    pos = np.asarray(log.samples["position_mm"])
    assert np.ptp(pos[-30:]) <= 0.01
    stop = next(e for e in log.events if e["kind"] == "stop_requested")
    assert stop["data"]["mode"] == "estop" and stop["data"]["acknowledged"]


def test_a_force_setpoint_past_the_limit_is_refused_before_anything_moves():
    cfg = RigConfig()
    with pytest.raises(LimitError, match=r"is above 0\.9 of the force limit 20 N"):
        check_limits(parse_protocol(_protocol(19.0), "<test>"), cfg)
    # a hold asked above the protocol's limit (the ramp below it) is refused before anything moves
    with pytest.raises(LimitError, match=r"hold_force to 3 N is above 0\.9 of the force limit 2 N"):
        check_limits(parse_protocol(_protocol(1.5).replace("steps:", "limits: {max_force_N: 2}\nsteps:")
                                    .replace("force_N: 1.5", "force_N: 3"), "<test>"), cfg)
    with pytest.raises(LimitError, match="outside the travel window"):
        check_limits(parse_protocol(_protocol(1.5).replace("max_mm: 35", "max_mm: 80"), "<test>"), cfg)


def test_bad_force_steps_name_the_field():
    cases = [("  - ramp_force: {to_N: 1, max_mm: 9}\n", "rate_N_s"),
             ("  - ramp_force: {to_N: 1, rate_N_s: -2, max_mm: 9}\n", "rate_N_s"),
             ("  - ramp_force: {to_N: 1, rate_N_s: 2}\n", "max_mm"),  # required, as an approach's
             ("  - ramp_force: {to_N: -0.5, rate_N_s: 2, max_mm: 9}\n", "to_N"),  # compression only
             ("  - hold_force: {force_N: 1, max_mm: 9}\n", "duration_s"),
             ("  - hold_force: {force_N: 0, duration_s: 2, max_mm: 9}\n", "force_N"),
             ("  - hold_force: {force_N: 1, duration_s: 2, max_mm: 9, speed_mm_s: 3}\n", "speed_mm_s")]
    for step, field in cases:
        with pytest.raises(SpecError) as err:
            parse_protocol(f"name: bad\nsteps:\n{step}", "bad.yaml")
        assert field in str(err.value) and "bad.yaml" in str(err.value), str(err.value)


def test_the_log_records_the_setpoint_and_the_error(tmp_path):
    import json

    from mcap.reader import make_reader

    result = run_trial(parse_protocol(_protocol(1.5), "<test>"), _config("tissue", 2),
                       RunOptions(speed=0, progress=False, log_path=tmp_path / "f.mcap"))
    rows = []
    with open(result.log_path, "rb") as fh:
        for _schema, _channel, message in make_reader(fh).iter_messages(topics=["/rig/sample"]):
            rows.append(json.loads(message.data))
    tracked = [r for r in rows if r.get("step_kind") in ("ramp_force", "hold_force")]
    assert tracked and all("force_cmd_N" in r and "force_error_N" in r for r in tracked)
    assert all(math.isclose(r["force_error_N"], r["force_cmd_N"] - r["force_N"], abs_tol=1e-9) for r in tracked)
    assert not any("force_cmd_N" in r for r in rows if r.get("step_kind") in ("ramp", "return", "tare"))
    # read back: the setpoint and the error as columns, NaN off the force steps, the same whether
    # read from the log's attached columns or message by message
    fast, slow = read_log(result.log_path), read_log(result.log_path, keep_raw=True)
    kind = np.asarray(fast.step_kind)
    for name in ("force_cmd_N", "force_error_N"):
        assert np.array_equal(fast.samples[name], slow.samples[name], equal_nan=True)
        on = np.isin(kind, ("ramp_force", "hold_force"))
        assert np.all(np.isfinite(fast.samples[name][on])) and np.all(np.isnan(fast.samples[name][~on]))


def _run(tmp_path, text: str, tissue: str = "tissue", seed: int = 4, **faults):
    cfg = _config(tissue, seed)
    for k, v in faults.items():
        setattr(cfg.sim.faults, k, v)
    result = run_trial(parse_protocol(text, "<test>"), cfg,
                       RunOptions(speed=0, progress=False, log_path=tmp_path / "t.mcap"))
    return result, read_log(result.log_path)


def test_out_of_contact_a_force_step_seeks_the_surface_slowly(tmp_path):
    """Started 3 mm before the surface, the force loop may only seek it at an approach's pace
    (5 % of the speed limit), not at the speed limit."""
    text = _protocol(1.5).replace("ramp: {to_mm: 5, speed_mm_s: 5}", "ramp: {to_mm: -3, speed_mm_s: 5}")
    result, log = _run(tmp_path, text)
    s = log.samples
    kind = np.asarray(log.step_kind)
    t, x = np.asarray(s["t_s"]), np.asarray(s["position_mm"])
    out = (kind == "ramp_force") & (x < -0.5)  # well before the surface (at 0)
    assert out.sum() > 10
    tt, xx = t[out], x[out]
    speed = (xx[-1] - xx[0]) / (tt[-1] - tt[0])  # over the stretch: the encoder's 0.01 mm steps
    assert 0.3 <= speed <= 0.05 * 10 + 0.02, speed  # 0.5 mm/s at a 10 mm/s limit
    assert result.outcome == "completed"


def test_a_force_step_stopped_by_its_max_mm_says_so(tmp_path):
    text = _protocol(1.5).replace("max_mm: 35", "max_mm: 7")
    result, log = _run(tmp_path, text)
    assert result.outcome == "completed"
    assert any("reached the step's max_mm (7 mm)" in n for n in result.notices), result.notices
    assert any("ended at" in n and "against its setpoint 1.5 N" in n for n in result.notices), result.notices
    kinds = [e["kind"] for e in log.events]
    assert "force_limit_depth" in kinds and "setpoint_missed" in kinds
    x = np.asarray(log.samples["position_mm"])[np.asarray(log.step_kind) == "hold_force"]
    assert x.max() <= 7.0 + 0.011  # never deeper than max_mm (one encoder step)


def test_a_hold_after_a_force_step_holds_where_the_slider_is(tmp_path):
    text = _protocol(1.5).replace("  - return: {speed_mm_s: 10}\n", "  - hold: {duration_s: 2}\n"
                                  "  - return: {speed_mm_s: 10}\n")
    result, log = _run(tmp_path, text)
    assert result.outcome == "completed" and not result.notices
    kind = np.asarray(log.step_kind)
    x = np.asarray(log.samples["position_mm"])
    hold = np.flatnonzero(kind == "hold")
    last_force = np.flatnonzero(kind == "hold_force")[-1]
    assert np.ptp(x[hold[10:]]) <= 0.011  # standing (one encoder step), once the stop took
    assert abs(x[hold[-1]] - x[last_force]) <= 0.05  # where the force step left it


def _poked(tmp_path, poke):
    """The tissue's force hold, with `poke(dev, snap)` called every tick."""
    cfg = _config("tissue", 6)
    proto = parse_protocol(_protocol(1.5), "<test>")
    clock = VirtualClock(0)
    dev = open_devices(cfg, clock)
    trial = Trial(proto, cfg, dev.slider, dev.loadcell, clock, tmp_path / "p.mcap")
    trial.on_tick = lambda snap: poke(dev, snap)
    return trial.run()


def test_after_a_fault_in_a_force_step_no_setpoint_is_logged(tmp_path):
    """A drive alarm during the hold: the slider is stopped, and the samples after the fault carry
    no setpoint or error (the force loop no longer commands anything)."""
    from mcap.reader import make_reader

    def alarm(dev, snap):
        if snap.step_kind == "hold_force" and snap.t_s > 5.0:
            dev.slider.alarm_code = 0x10

    result = _poked(tmp_path, alarm)
    assert result.outcome == "fault" and "0x10" in result.fault
    rows = []
    with open(result.log_path, "rb") as fh:
        for _s, _c, message in make_reader(fh).iter_messages(topics=["/rig/sample"]):
            rows.append(json.loads(message.data))
    after = [r for r in rows if r.get("step_kind") == "fault"]
    assert len(after) > 10 and not any("force_cmd_N" in r or "force_error_N" in r for r in after)


def test_a_drive_that_stops_following_the_force_loop_is_a_fault(tmp_path):
    """Moves acknowledged but never started (the motor not excited) during a force ramp: the
    loop's speed stays at its cap and the slider does not move; after a second, a fault."""

    def stuck(dev, snap):
        if snap.step_kind == "ramp_force":
            dev.slider.ignore_moves = True

    result = _poked(tmp_path, stuck)
    assert result.outcome == "fault"
    assert "the drive did not follow the force loop" in result.fault, result.fault


class _BusLog:
    """The slider's bus calls in order: 'p' position (one a tick, first thing), 's' status, 'm' move."""

    def __init__(self, slider) -> None:
        self._slider = slider
        self.calls: list[str] = []

    def position(self):
        self.calls.append("p")
        return self._slider.position()

    def status(self):
        self.calls.append("s")
        return self._slider.status()

    def move_to(self, *args, **kwargs):
        self.calls.append("m")
        return self._slider.move_to(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._slider, name)

    def ticks(self) -> list[str]:
        """One string per tick (the first is the position read before the loop)."""
        return "".join(self.calls).split("p")[2:]


@pytest.mark.parametrize("seed", [1, 4])
def test_no_tick_carries_a_status_read_and_a_force_move(seed, tmp_path):
    """Over RTU at 115200 baud a position read, a status read and a move together take 13 ms of a
    10 ms tick: on a tick the force loop's move is due, status waits one tick (never more), so
    the alarm is still read at least every status_every + 1 ticks."""
    cfg = _config("tissue", seed)
    clock = VirtualClock(0)
    dev = open_devices(cfg, clock)
    bus = _BusLog(dev.slider)
    trial = Trial(parse_protocol(_protocol(1.5), "<test>"), cfg, bus, dev.loadcell, clock,
                  tmp_path / "bus.mcap")
    result = trial.run()
    dev.close()
    assert result.outcome == "completed", result.fault
    log = read_log(result.log_path)
    ticks = bus.ticks()
    assert len(ticks) == result.samples
    kinds = np.asarray(log.step_kind)
    force = np.flatnonzero(np.isin(kinds, ["ramp_force", "hold_force"]))
    moves = [i for i in force if "m" in ticks[i]]
    assert len(moves) >= 0.3 * len(force)  # the force loop streams its moves (every 2nd tick at most)
    assert not any("s" in ticks[i] and "m" in ticks[i] for i in force)
    reads = [i for i, t in enumerate(ticks) if "s" in t]
    assert reads[0] == 0 and max(np.diff(reads)) <= cfg.loop.status_every + 1
    # and a deferral is one tick, not a new rhythm: about one status read every status_every ticks
    assert len(reads) >= len(ticks) / (cfg.loop.status_every + 1)
