"""The machine's own stalls beside a bench run (rig.diagnostics.stalls) and how `rig bench`
lays the loop's late ticks against them."""

from __future__ import annotations

import time

import numpy as np

from rig.diagnostics.bench import _machine_stalls, format_bench
from rig.diagnostics.stalls import StallProbe


def test_the_probe_runs_beside_and_reports_its_stalls():
    with StallProbe(threshold_ms=0.0) as probe:  # every wake-up and crossing counts
        time.sleep(0.3)
    kinds = {k for _, _, k in probe.stalls}
    assert kinds == {"wake", "pty"}
    starts = [t for t, _, _ in probe.stalls]
    assert all(0 < ms <= 1000 for _, ms, _ in probe.stalls)  # a crossing is reported up to 1 s
    assert time.monotonic() - 5 < min(starts) <= max(starts) < time.monotonic()


def test_near_finds_a_stall_that_ended_just_before():
    probe = StallProbe()
    probe.stalls = [(100.0, 12.0, "wake"), (200.0, 3.0, "pty")]
    assert probe.near(100.02) == 12.0  # ended at 100.012, 8 ms before
    assert probe.near(100.2) == 0.0  # long over
    assert probe.near(99.99) == 0.0  # not yet begun
    assert probe.near(200.004) == 3.0


def test_late_and_skipped_over_ticks_are_laid_against_the_stalls():
    t = np.arange(200) * 0.01
    t[120:] += 0.03  # three ticks skipped before tick 120
    late = np.zeros(200)
    late[50] = 7.0
    late[150] = 6.0
    t0 = 1000.0
    probe = StallProbe()
    probe.stalls = [(t0 + t[50] - 0.02, 15.0, "wake"), (t0 + t[120] - 0.012, 10.0, "pty"),
                    (t0 + 0.5, 1.0, "pty")]
    m = _machine_stalls(probe, {"t_s": t, "late_ms": late}, t0, late_tolerance_ms=5.0)
    assert m["troubled_ticks"] == 3  # ticks 50, 120 and 150
    assert m["troubled_at_stall"] == 2  # 150 came with no stall of the machine's
    assert m["wake"] == {"stalls": 1, "max_ms": 15.0, "over_5ms": 1}
    assert m["pty"] == {"stalls": 2, "max_ms": 10.0, "over_5ms": 1}
    # a stall under half the tolerance does not excuse a late tick
    probe.stalls = [(t0 + t[50] - 0.004, 2.0, "wake")]
    assert _machine_stalls(probe, {"t_s": t, "late_ms": late}, t0, 5.0)["troubled_at_stall"] == 0


def _report(machine: dict) -> dict:
    loop = {"ticks": 100, "rate_Hz": 100.0, "duration_s": 1.0, "devices": "in-process",
            "period_err_p50_ms": 0.0, "period_err_p99_ms": 0.1, "period_err_max_ms": 9.0,
            "late_ticks": 2, "missed_ticks": 0,
            "bus_transactions_per_tick": 1.1, "bus_errors": 0, "scheduling": "SCHED_FIFO 50",
            "load_processes": 0, "outcome": "completed", "wire": None,
            "replay": {"lateness_p99_ms": 0.1, "lateness_max_ms": 9.0, "samples_per_s": 1e6, "reads": 5,
                       "samples": 100, "first_read_samples_per_s": 1e6, "columns": True},
            "machine": machine}
    return {"loop": loop, "rls": {"update_us": 1.0}, "model": {"step_us": {"proposed": 1.0}},
            "record": {"put_us": 1.0, "writer_us_per_sample": 2.0, "bytes_per_sample": 30.0},
            "baseline": {"duration_s": 1.0, "lateness_p99_ms": 0.1, "lateness_max_ms": 0.2, "over_5ms": 0}}


def test_the_report_says_which_late_ticks_the_machine_caused():
    r = _report({"probe_realtime": True, "threshold_ms": 2.0, "troubled_ticks": 2, "troubled_at_stall": 1,
                 "wake": {"stalls": 3, "max_ms": 11.5, "over_5ms": 1},
                 "pty": {"stalls": 0, "max_ms": 0.0, "over_5ms": 0}})
    text = format_bench(r)
    assert "3 wake-ups over 2 ms late (max 11.50 ms)" in text
    assert "1 of the 2 late or skipped-over ticks came right after such a stall" in text


def test_the_report_names_the_tty_workers_when_bytes_waited():
    from rig.diagnostics.stalls import tty_workers

    tw = tty_workers()
    assert 0 <= tw["realtime"] <= tw["threads"]
    machine = {"probe_realtime": True, "threshold_ms": 2.0, "troubled_ticks": 0, "troubled_at_stall": 0,
               "wake": {"stalls": 0, "max_ms": 0.0, "over_5ms": 0},
               "pty": {"stalls": 12, "max_ms": 21.0, "over_5ms": 4},
               "tty_workers": {"threads": 7, "realtime": 0}}
    r = _report(machine)
    assert "12 pty crossings over 2 ms (max 21.00 ms)" in format_bench(r)
    assert "tty workers run at normal priority (7 of 7 kworker/u threads)" in format_bench(r)
    machine["tty_workers"] = {"threads": 7, "realtime": 7}
    assert "tty workers" not in format_bench(_report(machine))
