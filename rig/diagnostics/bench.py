"""`rig bench`: the timing and cost figures the rig's targets are stated in.

- loop: a real-clock trial with in-process simulated devices; period error
  |t_k - t_(k-1) - 1/rate| percentiles, late and missed ticks, bus transactions per tick;
- RLS update time; the loop-side cost of recording one sample; replay speed;
- on the simulated wire: the wire's share of a tick (the loop's reads as bytes on the line at
  the simulated drive's baud rate and frame, plus the USB adapter's latency), and with
  `--max-rate` the highest rate without a late tick (status read at about 10 Hz at every rate);
  beside it, the machine's own pseudo-terminal delivery, which the simulated wire rides on.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rig.control.estimator import StiffnessRLS
from rig.diagnostics.stalls import StallProbe, tty_workers
from rig.recording.messages import SAMPLE
from rig.recording.recorder import Recorder
from rig.specs.config import RigConfig
from rig.specs.protocol import parse_protocol


def _bench_protocol(duration_s: float) -> str:
    """Ramp-hold-return cycles of about 10 s (shorter for a short bench) filling the duration."""
    repeats = max(int(duration_s // 10), 1)
    cycle = duration_s / repeats - 0.5 / repeats  # the tare comes once
    depth = min(8.0, max(cycle / 4.0, 0.5))
    hold = max(cycle - depth / 2.0 - depth / 5.0 - 0.3, 0.2)
    return (f"name: bench cycles\nsteps:\n  - ramp: {{to_mm: {depth:.2f}, speed_mm_s: 2}}\n"
            f"  - hold: {{duration_s: {hold:.2f}}}\n  - return: {{to_mm: 0, speed_mm_s: 5}}\n"
            f"repeat: {repeats}\n")


class CpuLoad:
    """N processes that do nothing but burn a CPU each: a busy lab PC, made on purpose."""

    def __init__(self, n: int) -> None:
        # each ends by itself once the bench is gone (killed, not only closed)
        burn = "import os\nparent = os.getppid()\nwhile os.getppid() == parent:\n    pass\n"
        self.procs = [subprocess.Popen([sys.executable, "-c", burn], stdin=subprocess.DEVNULL)
                      for _ in range(n)]

    def __enter__(self) -> CpuLoad:
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait(5)


STATUS_HZ = 10.0  # DESIGN.md: status and alarm read at about 10 Hz, whatever the loop rate


def bench_loop(duration_s: float, rate_Hz: float, progress: bool = True, wire: str = "none",
               load: int = 0, realtime: str = "auto") -> dict:
    from rig.recording.logs import read_log
    from rig.service.run import RunOptions, run_trial

    config = RigConfig()
    config.loop.rate_Hz = rate_Hz
    # the alarm read as often in time at every rate (the default 10 ticks is 10 Hz at 100 Hz)
    config.loop.status_every = max(round(rate_Hz / STATUS_HZ), 1)
    config.loop.realtime = realtime
    config.sim.wire = wire
    proto = parse_protocol(_bench_protocol(duration_s), "<bench>")
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "bench.mcap"
        if progress:
            where = "in-process devices" if wire == "none" else f"simulated devices over Modbus {wire.upper()}"
            busy = f", {load} CPU-bound processes beside it" if load else ""
            print(f"bench: {duration_s:g} s real-clock trial at {rate_Hz:g} Hz, {where}{busy} ...",
                  file=sys.stderr)
        trial = []
        with CpuLoad(load), StallProbe(config.loop.realtime_priority + 1) as probe:
            result = run_trial(proto, config, RunOptions(speed=1.0, progress=False, log_path=log,
                                                         on_start=lambda t, _: trial.append(t)))
        err = result.period_errors_ms
        replay = bench_replay(log)
        meta, health = read_log_meta(log)
        scheduling = meta.get("realtime", "")
        machine = _machine_stalls(probe, read_log(log).samples, trial[0].started_s if trial else None,
                                  config.loop.late_tolerance_ms)
    return {
        "load_processes": load,
        "scheduling": scheduling,
        "devices": "in-process" if wire == "none" else f"modbus-{wire} + serial load cell",
        "rate_Hz": rate_Hz,
        "duration_s": round(result.duration_s, 2),
        "ticks": result.samples,
        "late_ticks": result.late_ticks,
        "missed_ticks": result.missed_ticks,
        "period_err_p50_ms": float(np.percentile(err, 50)),
        "period_err_p99_ms": float(np.percentile(err, 99)),
        "period_err_max_ms": float(err.max()),
        "bus_transactions_per_tick": result.bus_transactions / max(result.samples, 1),
        "outcome": result.outcome,
        "fault": result.fault,
        "bus_errors": int(health.get("bus_errors", 0)),
        "wire": wire_share(config, wire, result.bus_transactions / max(result.samples, 1)),
        "replay": replay,
        "machine": machine,
    }


def _machine_stalls(probe: StallProbe, samples: dict, t0: float | None, late_tolerance_ms: float) -> dict:
    """The probe's stalls over the run, and how many of the run's troubled ticks (late, or after
    skipped ones) came right after one of at least half the late tolerance: the machine's, then,
    not the rig's. `samples`: the log's t_s and late_ms; `t0`: the trial's first slot on the
    monotonic clock."""
    t = np.asarray(samples["t_s"], dtype=float)
    gaps = np.diff(t, prepend=t[0]) if len(t) else t
    period = float(np.median(gaps[1:])) if len(gaps) > 1 else 0.0
    troubled = np.flatnonzero((samples["late_ms"] > late_tolerance_ms) | (gaps > 1.5 * period))
    at_stall = 0
    if t0 is not None:
        at_stall = sum(probe.near(t0 + t[i]) >= late_tolerance_ms / 2.0 for i in troubled)
    out = {"probe_realtime": probe.realtime, "threshold_ms": probe.threshold_ms,
           "troubled_ticks": len(troubled), "troubled_at_stall": int(at_stall), "tty_workers": tty_workers()}
    for kind in ("wake", "pty"):
        ms = [m for _, m, k in probe.stalls if k == kind]
        out[kind] = {"stalls": len(ms), "max_ms": max(ms, default=0.0), "over_5ms": sum(m > 5.0 for m in ms)}
    return out


def wire_share(config: RigConfig, wire: str, transactions_per_tick: float | None = None) -> dict | None:
    """What the simulated wire costs a tick, by its model: the loop reads the position every tick
    and status plus alarm every `status_every`th, each an FC03 (8-byte request, 5 + 2 x registers
    reply) whose bytes cross the line at the drive's baud rate and frame and whose reply waits the
    USB adapter's latency (TCP: its latency only). Moves (FC16) are rare and left out. None for
    in-process devices. The rest of a transaction (the drive's and the driver's own time) is not
    the wire's and shows in the period error."""
    if wire == "none":
        return None
    from rig.drivers.registers import PROFILES
    from rig.sim.line import Framing

    sim = config.sim
    profile = config.slider.profile
    regs = PROFILES.get("oriental_az_sim" if profile == "oriental_az" else profile, PROFILES["oriental_az_sim"])
    reads = [(1.0, 2), (1.0 / config.loop.status_every, regs.status_block[1])]  # (per tick, registers)
    per_tick = sum(n for n, _ in reads)
    if wire == "tcp":
        latency_ms = sim.tcp_latency_ms
        line = f"Modbus TCP, latency {latency_ms:g} ms"
        wire_ms = per_tick * latency_ms
    elif not sim.pace_wire:
        line, wire_ms = "not paced (instant pty)", 0.0
    else:
        d = sim.drive
        framing = Framing(d.baudrate, d.parity, d.stopbits)
        latency_ms = sim.usb_latency_ms
        line = f"{framing.describe()} + {latency_ms:g} ms USB latency"
        wire_ms = sum(n * (framing.bytes_s(8 + 5 + 2 * count) * 1000.0 + latency_ms) for n, count in reads)
    period_ms = 1000.0 / config.loop.rate_Hz
    return {"line": line, "reads_per_tick": per_tick, "transactions_per_tick": transactions_per_tick,
            "wire_ms_per_tick": wire_ms, "period_ms": period_ms, "share": wire_ms / period_ms}


def read_log_meta(path: Path) -> tuple[dict, dict]:
    from rig.recording.logs import read_log

    log = read_log(path)
    return log.trial, (log.health[-1] if log.health else {})


def bench_baseline(duration_s: float, rate_Hz: float) -> dict:
    """A loop that only sleeps to its deadlines: how much jitter the machine itself adds."""
    from rig.clock import RealClock

    clock = RealClock()
    period = 1.0 / rate_Hz
    n = max(int(duration_s * rate_Hz), 2)
    t0 = clock.now()
    late = np.empty(n)
    for k in range(n):
        clock.sleep_until(t0 + k * period)
        late[k] = clock.now() - (t0 + k * period)
    late_ms = late * 1000.0
    return {"duration_s": duration_s, "ticks": n, "lateness_p99_ms": float(np.percentile(late_ms, 99)),
            "lateness_max_ms": float(late_ms.max()), "over_5ms": int(np.sum(late_ms > 5.0))}


def bench_pty(duration_s: float, rate_Hz: float) -> dict:
    """The kernel's own delivery through a pseudo-terminal, no rig code: 17 bytes (a position
    read's request and reply) across a pty and back (two crossings), once a tick, at the loop's
    real-time priority where allowed. Bytes written to a pty reach its other side through a
    kernel worker thread of normal priority: on a busy machine they can wait for it for many
    milliseconds, whatever the priority of the threads at either end, and a simulated-wire
    transaction crosses a pty four times (client to bridge to drive and back). Stalls here make
    late ticks of the simulated-wire loop that are the machine's, not the loop's."""
    import os
    import pty
    import tty

    from rig.realtime import Realtime

    master, slave = pty.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    rt = Realtime("auto", 50)
    rt.enter()
    period = 1.0 / rate_Hz
    n = max(int(duration_s * rate_Hz), 2)
    took = np.full(n, np.nan)
    data = bytes(17)
    try:
        t0 = time.monotonic()
        for k in range(n):
            time.sleep(max(t0 + k * period - time.monotonic(), 0.0))
            start = time.monotonic()
            if _carried(slave, master, data) and _carried(master, slave, data):
                took[k] = time.monotonic() - start
    finally:
        rt.leave()
        for fd in (master, slave):
            os.close(fd)
    took_ms = took * 1000.0
    lost = int(np.sum(np.isnan(took_ms)))
    ok = took_ms[~np.isnan(took_ms)]
    return {"duration_s": duration_s, "round_trips": n, "lost": lost,
            "p50_ms": float(np.percentile(ok, 50)) if len(ok) else float("nan"),
            "p99_ms": float(np.percentile(ok, 99)) if len(ok) else float("nan"),
            "max_ms": float(ok.max()) if len(ok) else float("nan"),
            "over_5ms": int(np.sum(ok > 5.0)) + lost}


def _carried(src: int, dst: int, data: bytes, timeout_s: float = 1.0) -> bool:
    """Write `data` at one end of a pty, read it all at the other; False if it did not come."""
    import os
    import select

    os.write(src, data)
    got = 0
    deadline = time.monotonic() + timeout_s
    while got < len(data):
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([dst], [], [], left)[0]:
            return False
        got += len(os.read(dst, 4096))
    return True


def bench_rls(n: int = 200_000) -> dict:
    rls = StiffnessRLS(rate_Hz=100.0)
    rng = np.random.default_rng(0)
    x = np.linspace(0.001, 0.03, n)
    f = 80.0 * x + rng.normal(0, 0.08, n)
    xs, fs = x.tolist(), f.tolist()
    t0 = time.perf_counter()
    for i in range(n):
        rls.update(xs[i], fs[i])
    dt = time.perf_counter() - t0
    return {"updates": n, "update_us": dt / n * 1e6}


def bench_model(n: int = 200_000) -> dict:
    """One tick of a saved model in the loop (`OnlineModel.step`), for the paper's model and for
    a richer one (a second relaxation branch, offset and drift)."""
    from rig.models.catalogue import build_model
    from rig.models.online import OnlineModel

    values = {"k1_N_per_m3": 5.6e4, "k2_N_per_m2": 550.0, "k3_N_per_m": 14.0, "tau2_N_s_per_m2": 2.3e5,
              "tau1_s": 8.0, "k_m_N_per_m": 60.0, "tau_m_s": 40.0, "offset_N": 0.1, "drift_N_per_s": 0.001}
    x = (np.minimum(np.arange(n) % 10_000, 3000) * 1e-5).tolist()  # ramps to 30 mm and holds
    out = {}
    richer = ["relaxation2", "offset", "drift"]
    for label, extra in (("proposed", []), ("proposed+relaxation2+offset+drift", richer)):
        online = OnlineModel(build_model("proposed", extra), values, 0.01)
        step = online.step
        t0 = time.perf_counter()
        for i in range(n):
            step(i * 0.01, x[i])
        out[label] = (time.perf_counter() - t0) / n * 1e6
    return {"steps": n, "step_us": out}


def bench_record(n: int = 50_000) -> dict:
    """Loop-side cost of one sample: building its dict and queueing it (the writer runs apart)."""
    with tempfile.TemporaryDirectory() as tmp:
        rec = Recorder(Path(tmp) / "r.mcap")
        t0 = time.perf_counter()
        for i in range(n):
            rec.put(SAMPLE.topic, i, SAMPLE.record(
                seq=i, t_s=i * 0.01, position_mm=1.0, position_cmd_mm=1.0, force_N=0.5,
                stiffness_N_per_m=80.0, force_pred_N=0.5, error_N=0.0, forgetting=0.99, contact=True,
                step=0, step_kind="ramp", late_ms=0.0))
        loop_side = time.perf_counter() - t0
        t1 = time.perf_counter()
        rec.close()
        drain = time.perf_counter() - t1
        size = (Path(tmp) / "r.mcap").stat().st_size
    return {"samples": n, "put_us": loop_side / n * 1e6,
            "writer_us_per_sample": (loop_side + drain) / n * 1e6,
            "bytes_per_sample": size / n}


def bench_replay(path: Path, reads: int = 5) -> dict:
    """Reading a trial's log into arrays (`read_log`, as `rig replay` and the analysis read it):
    samples per second, the median of `reads` reads (one read of a minute's log takes tens of
    milliseconds, which one scheduler hiccup can double); the first read is given apart. `columns`:
    whether the samples came from the log's attached columns (a finished log) or its messages."""
    from rig.recording.logs import read_log

    rates = []
    for _ in range(max(reads, 1)):
        t0 = time.perf_counter()
        log = read_log(path)
        dt = time.perf_counter() - t0
        rates.append(log.n / dt if dt > 0 else float("inf"))
    late = log.samples["late_ms"]
    return {"samples": log.n, "reads": len(rates), "samples_per_s": float(np.median(rates)),
            "first_read_samples_per_s": rates[0], "columns": log.from_columns,
            "lateness_p99_ms": float(np.percentile(late, 99)), "lateness_max_ms": float(late.max())}


def max_rate(wire: str, rates=(100, 150, 200, 250, 300, 400, 600, 800, 1000), seconds: float = 5.0,
             progress: bool = True) -> dict:
    """The highest loop rate with no late or missed tick over a short run, per transport (steps
    of 50 Hz up to 300: a paced serial wire ends there), with the wire's share of each tick."""
    tried = []
    best = None
    for rate in rates:
        r = bench_loop(seconds, float(rate), progress, wire)
        ok = r["late_ticks"] == 0 and r["missed_ticks"] == 0 and r["outcome"] == "completed"
        tried.append({"rate_Hz": rate, "ok": ok, "late_ticks": r["late_ticks"],
                      "missed_ticks": r["missed_ticks"], "period_err_p99_ms": r["period_err_p99_ms"],
                      "wire_share": r["wire"]["share"] if r["wire"] else None})
        if not ok:
            break
        best = rate
    return {"wire": wire, "max_rate_Hz": best, "tried": tried}


def run_bench(duration_s: float = 60.0, rate_Hz: float = 100.0, progress: bool = True,
              wire: str = "none", find_max_rate: bool = False, ode_fit: bool = True, load: int = 0,
              realtime: str = "auto") -> dict:
    out = {"loop": bench_loop(duration_s, rate_Hz, progress, wire, load, realtime), "rls": bench_rls(),
           "model": bench_model(),
           "record": bench_record(), "baseline": bench_baseline(min(duration_s, 30.0), rate_Hz)}
    if wire != "none":
        out["pty"] = bench_pty(min(duration_s, 20.0), rate_Hz)
    if progress:
        print("bench: model fit (and the same fit by an ODE solver) ...", file=sys.stderr)
    out["fit"] = bench_fit(ode_fit)
    if find_max_rate:
        out["max_rate"] = max_rate(wire, progress=progress)
    return out


def format_bench(r: dict) -> str:
    lp, rls, rec, base = r["loop"], r["rls"], r["record"], r["baseline"]
    lines = [
        f"loop      {lp['ticks']} ticks at {lp['rate_Hz']:g} Hz over {lp['duration_s']:.1f} s (real clock, "
        f"{lp['devices']} simulated devices)",
        f"          period error p50 {lp['period_err_p50_ms']:.3f} ms  p99 {lp['period_err_p99_ms']:.3f} ms"
        f"  max {lp['period_err_max_ms']:.3f} ms",
        f"          tick start after its slot p99 {lp['replay']['lateness_p99_ms']:.3f} ms  "
        f"max {lp['replay']['lateness_max_ms']:.3f} ms",
        f"          late ticks {lp['late_ticks']}  missed {lp['missed_ticks']}  "
        f"bus transactions/tick {lp['bus_transactions_per_tick']:.3f}  bus errors {lp['bus_errors']}",
        f"          scheduling: {lp['scheduling']}; {lp['load_processes']} CPU-bound processes beside it",
        f"          outcome {lp['outcome']}" + (f": {lp['fault']}" if lp.get("fault") else ""),
    ]
    if lp.get("machine"):
        m = lp["machine"]
        w, p = m["wake"], m["pty"]
        lines.append(f"          beside it, above the loop's priority: {w['stalls']} wake-ups over "
                     f"{m['threshold_ms']:g} ms late (max {w['max_ms']:.2f} ms), {p['stalls']} pty crossings "
                     f"over {m['threshold_ms']:g} ms (max {p['max_ms']:.2f} ms)"
                     + ("" if m["probe_realtime"] else "; the probe was refused real-time priority"))
        if m["troubled_ticks"]:
            lines.append(f"          {m['troubled_at_stall']} of the {m['troubled_ticks']} late or "
                         "skipped-over ticks came right after such a stall of the machine's")
        tw = m.get("tty_workers") or {}
        if p["stalls"] and tw.get("threads") and tw["realtime"] < tw["threads"]:
            slow = tw["threads"] - tw["realtime"]
            lines.append(f"          the kernel's tty workers run at normal priority ({slow} "
                         f"of {tw['threads']} kworker/u threads): bytes on a pty or a USB serial line wait "
                         "behind busy processes (as root, `chrt -f -p 45 PID` raises one; it shortens "
                         "those waits, not the machine's own stalls above)")
    if lp.get("wire"):
        w = lp["wire"]
        lines.append(f"wire      {w['wire_ms_per_tick']:.2f} ms per tick on the wire ({w['line']}; "
                     f"{w['reads_per_tick']:.1f} reads per tick): {w['share']:.0%} of the "
                     f"{w['period_ms']:g} ms period")
    lines += [
        f"rls       {rls['update_us']:.2f} us per update",
        "model     " + "; ".join(f"{k} {v:.2f} us per tick" for k, v in r["model"]["step_us"].items()),
        f"record    {rec['put_us']:.2f} us per sample on the loop side; writer "
        f"{rec['writer_us_per_sample']:.1f} us/sample; {rec['bytes_per_sample']:.1f} bytes/sample on disk",
        f"replay    {lp['replay']['samples_per_s']:,.0f} samples/s reading the log into arrays (median of "
        f"{lp['replay']['reads']} reads of its {lp['replay']['samples']} samples; first read "
        f"{lp['replay']['first_read_samples_per_s']:,.0f}; "
        f"{'from its attached columns' if lp['replay'].get('columns') else 'decoding its messages'})",
        f"machine   a loop that only sleeps, {base['duration_s']:g} s: lateness p99 "
        f"{base['lateness_p99_ms']:.3f} ms, max {base['lateness_max_ms']:.3f} ms, "
        f"{base['over_5ms']} ticks over 5 ms",
    ]
    if "pty" in r:
        p = r["pty"]
        lines.append(f"          a pseudo-terminal there and back (the kernel's delivery, no rig code), "
                     f"{p['duration_s']:g} s: p50 {p['p50_ms']:.3f} ms, p99 {p['p99_ms']:.3f} ms, "
                     f"max {p['max_ms']:.2f} ms, {p['over_5ms']} of {p['round_trips']} over 5 ms")
    if "max_rate" in r:
        m = r["max_rate"]
        lines.append(f"max rate  {m['max_rate_Hz']} Hz without a late tick over {m['wire']} "
                     f"(tried {', '.join(str(t['rate_Hz']) for t in m['tried'])})")
        for t in m["tried"]:
            share = f"  wire {t['wire_share']:.0%} of the tick" if t.get("wire_share") is not None else ""
            lines.append(f"          {t['rate_Hz']:>5} Hz  late {t['late_ticks']}  missed {t['missed_ticks']}  "
                         f"period error p99 {t['period_err_p99_ms']:.3f} ms{share}")
    if "fit" in r:
        f = r["fit"]
        lines.append(f"fit       proposed model, {f['trials']} trials jointly ({f['samples']} samples): "
                     f"{f['fit_s']:.3f} s ({f['evaluations']} model evaluations, "
                     f"{f['eval_ms_per_trial']:.2f} ms per trial each)")
        if f.get("ode"):
            o = f["ode"]
            lines.append(f"          by solve_ivp instead: {o['eval_s']:.2f} s per evaluation of the three "
                         f"trials, so about {o['fit_s_estimated']:.0f} s for the same "
                         f"{o['evaluations']} evaluations")
    return "\n".join(lines)


def bench_fit(ode_fit: bool = True) -> dict:
    """Joint fit of the proposed model to three 100 s simulated trials at 100 Hz; and the same
    fit with the model integrated by scipy's solve_ivp inside least_squares, for comparison."""
    from rig.analysis.fitting.fit import fit
    from rig.analysis.trials.data import load_trial
    from rig.models.catalogue import build_model
    from rig.service.run import RunOptions, run_trial

    trials = []
    with tempfile.TemporaryDirectory() as tmp:
        for v in (0.75, 1.5, 3.0):
            hold = 100.0 - 0.5 - 30.0 / v - 6.3
            text = (f"name: bench {v}\nsteps:\n  - ramp: {{to_mm: 30, speed_mm_s: {v}}}\n"
                    f"  - hold: {{duration_s: {hold:.2f}}}\n  - return: {{to_mm: 0, speed_mm_s: 5}}\n")
            path = Path(tmp) / f"t{v}.mcap"
            run_trial(parse_protocol(text, "<bench>"), RigConfig(), RunOptions(speed=0, progress=False,
                                                                                log_path=path))
            trials.append(load_trial(path))
    model = build_model("proposed")
    calls = [0]
    original = model.predict

    def counted(values, m):
        calls[0] += 1
        return original(values, m)

    model.predict = counted
    res = fit(model, trials)
    model.predict = original
    out = {"trials": len(trials), "samples": int(sum(t.n for t in trials)),
           "fit_s": res.seconds, "evaluations": calls[0] // len(trials), "rmse_N": res.overall.rmse_N}
    t0 = time.perf_counter()
    for _ in range(20):
        model.predict(res.values, trials[0].motion)
    out["eval_ms_per_trial"] = (time.perf_counter() - t0) / 20 * 1000.0
    if ode_fit:
        out["ode"] = _ode_fit(trials, res, calls[0] // len(trials))
    return out


def _ode_fit(trials, res, calls: int) -> dict:
    """The proposed model by a general ODE solver (RK45, inputs interpolated), as it would run
    inside least_squares: the time of one evaluation of all trials, times the evaluations our fit
    needed (each evaluation costs the same whichever optimiser asks for it)."""
    from scipy.integrate import solve_ivp

    v = res.values
    k1, k2, k3, tau2, tau1 = (v["k1_N_per_m3"], v["k2_N_per_m2"], v["k3_N_per_m"], v["tau2_N_s_per_m2"],
                              v["tau1_s"])

    def predict(tr):
        t, x, xd = tr.motion.t_s, tr.motion.x_m, tr.motion.v_m_s

        def rhs(tt, f):
            xi = max(np.interp(tt, t, x), 0.0)
            vi = np.interp(tt, t, xd) if xi > 0 else 0.0
            g = ((k1 * xi + k2) * xi + k3) * xi + tau2 * xi * vi
            return [(g - f[0]) / tau1]

        sol = solve_ivp(rhs, (t[0], t[-1]), [0.0], t_eval=t, max_step=0.02, rtol=1e-6, atol=1e-9)
        return np.maximum(sol.y[0], 0.0)

    t0 = time.perf_counter()
    pred = [predict(tr) for tr in trials]
    eval_s = time.perf_counter() - t0
    resid = np.concatenate([p - tr.force_N for p, tr in zip(pred, trials, strict=True)])
    rmse = float(np.sqrt(np.mean(resid ** 2)))
    return {"eval_s": eval_s, "evaluations": calls, "fit_s_estimated": eval_s * calls, "rmse_N": rmse}
