"""`rig bench`: the timing and cost figures the rig's targets are stated in.

- loop: a real-clock trial with in-process simulated devices; period error
  |t_k - t_(k-1) - 1/rate| percentiles, late and missed ticks, bus transactions per tick;
- RLS update time; the loop-side cost of recording one sample; replay speed.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rig.config import RigConfig
from rig.estimator import StiffnessRLS
from rig.protocol import parse_protocol
from rig.recorder import SAMPLE_TOPIC, Recorder


def _bench_protocol(duration_s: float) -> str:
    """Ramp-hold-return cycles of about 10 s (shorter for a short bench) filling the duration."""
    repeats = max(int(duration_s // 10), 1)
    cycle = duration_s / repeats - 0.5 / repeats  # the tare comes once
    depth = min(8.0, max(cycle / 4.0, 0.5))
    hold = max(cycle - depth / 2.0 - depth / 5.0 - 0.3, 0.2)
    return (f"name: bench cycles\nsteps:\n  - ramp: {{to_mm: {depth:.2f}, speed_mm_s: 2}}\n"
            f"  - hold: {{duration_s: {hold:.2f}}}\n  - return: {{to_mm: 0, speed_mm_s: 5}}\n"
            f"repeat: {repeats}\n")


def bench_loop(duration_s: float, rate_Hz: float, progress: bool = True, wire: str = "none") -> dict:
    from rig.trialrun import RunOptions, run_trial

    config = RigConfig()
    config.loop.rate_Hz = rate_Hz
    config.sim.wire = wire
    proto = parse_protocol(_bench_protocol(duration_s), "<bench>")
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "bench.mcap"
        if progress:
            where = "in-process devices" if wire == "none" else f"simulated devices over Modbus {wire.upper()}"
            print(f"bench: {duration_s:g} s real-clock trial at {rate_Hz:g} Hz, {where} ...", file=sys.stderr)
        result = run_trial(proto, config, RunOptions(speed=1.0, progress=False, log_path=log))
        err = result.period_errors_ms
        replay = bench_replay(log)
    return {
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
        "replay": replay,
    }


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


def bench_record(n: int = 50_000) -> dict:
    """Loop-side cost of one sample: building its dict and queueing it (the writer runs apart)."""
    with tempfile.TemporaryDirectory() as tmp:
        rec = Recorder(Path(tmp) / "r.mcap")
        t0 = time.perf_counter()
        for i in range(n):
            rec.put(SAMPLE_TOPIC, i, {
                "seq": i, "t_s": i * 0.01, "position_mm": 1.0, "position_cmd_mm": 1.0,
                "force_N": 0.5, "stiffness_N_per_m": 80.0, "force_pred_N": 0.5, "error_N": 0.0,
                "forgetting": 0.99, "contact": True, "step": 0, "step_kind": "ramp", "late_ms": 0.0})
        loop_side = time.perf_counter() - t0
        t1 = time.perf_counter()
        rec.close()
        drain = time.perf_counter() - t1
        size = (Path(tmp) / "r.mcap").stat().st_size
    return {"samples": n, "put_us": loop_side / n * 1e6,
            "writer_us_per_sample": (loop_side + drain) / n * 1e6,
            "bytes_per_sample": size / n}


def bench_replay(path: Path) -> dict:
    from rig.logs import read_log

    t0 = time.perf_counter()
    log = read_log(path)
    dt = time.perf_counter() - t0
    late = log.samples["late_ms"]
    return {"samples": log.n, "samples_per_s": log.n / dt if dt > 0 else float("inf"),
            "lateness_p99_ms": float(np.percentile(late, 99)), "lateness_max_ms": float(late.max())}


def max_rate(wire: str, rates=(100, 200, 400, 600, 800, 1000), seconds: float = 5.0,
             progress: bool = True) -> dict:
    """The highest loop rate with no late or missed tick over a short run, per transport."""
    tried = []
    best = None
    for rate in rates:
        r = bench_loop(seconds, float(rate), progress, wire)
        ok = r["late_ticks"] == 0 and r["missed_ticks"] == 0 and r["outcome"] == "completed"
        tried.append({"rate_Hz": rate, "ok": ok, "late_ticks": r["late_ticks"],
                      "missed_ticks": r["missed_ticks"], "period_err_p99_ms": r["period_err_p99_ms"]})
        if not ok:
            break
        best = rate
    return {"wire": wire, "max_rate_Hz": best, "tried": tried}


def run_bench(duration_s: float = 60.0, rate_Hz: float = 100.0, progress: bool = True,
              wire: str = "none", find_max_rate: bool = False) -> dict:
    out = {"loop": bench_loop(duration_s, rate_Hz, progress, wire), "rls": bench_rls(),
           "record": bench_record(), "baseline": bench_baseline(min(duration_s, 30.0), rate_Hz)}
    if find_max_rate:
        out["max_rate"] = max_rate(wire, progress=progress)
    return out


def format_bench(r: dict) -> str:
    lp, rls, rec = r["loop"], r["rls"], r["record"]
    return "\n".join([
        f"loop      {lp['ticks']} ticks at {lp['rate_Hz']:g} Hz over {lp['duration_s']:.1f} s (real clock, "
        f"{lp['devices']} simulated devices)",
        f"          period error p50 {lp['period_err_p50_ms']:.3f} ms  p99 {lp['period_err_p99_ms']:.3f} ms"
        f"  max {lp['period_err_max_ms']:.3f} ms",
        f"          tick start after its slot p99 {lp['replay']['lateness_p99_ms']:.3f} ms  "
        f"max {lp['replay']['lateness_max_ms']:.3f} ms",
        f"          late ticks {lp['late_ticks']}  missed {lp['missed_ticks']}  "
        f"bus transactions/tick {lp['bus_transactions_per_tick']:.3f}",
        f"rls       {rls['update_us']:.2f} us per update",
        f"record    {rec['put_us']:.2f} us per sample on the loop side; writer "
        f"{rec['writer_us_per_sample']:.1f} us/sample; {rec['bytes_per_sample']:.1f} bytes/sample on disk",
        f"replay    {lp['replay']['samples_per_s']:,.0f} samples/s",
        f"machine   a loop that only sleeps, {r['baseline']['duration_s']:g} s: lateness p99 "
        f"{r['baseline']['lateness_p99_ms']:.3f} ms, max {r['baseline']['lateness_max_ms']:.3f} ms, "
        f"{r['baseline']['over_5ms']} ticks over 5 ms",
    ] + ([f"max rate  {r['max_rate']['max_rate_Hz']} Hz without a late tick over "
          f"{r['max_rate']['wire']} (tried {', '.join(str(t['rate_Hz']) for t in r['max_rate']['tried'])})"]
         if "max_rate" in r else []))
