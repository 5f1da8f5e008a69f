"""The fault-injection soak, short (about a minute): a daemon on the simulated rig over Modbus RTU
through random sequences of starts, stops, holds, estops, moves, a second daemon and CLI, SIGINT,
disk full, a drive alarm, lost and garbled replies, a vanished port and a clock step; every
invariant checked after every step (tests/soak_harness.py). The long run is
tests/bench/test_bench_soak.py."""

from __future__ import annotations

from hypothesis import HealthCheck, Phase, seed, settings

from tests.soak_harness import REPORT, SoakMachine


def run_soak(seed_value: int, examples: int, steps: int) -> list:
    """Run the machine; the soaks it ran (their steps, checks and pending-feature failures)."""
    REPORT.clear()
    machine = type(f"Soak{seed_value}", (SoakMachine,), {"seed_value": seed_value})
    # generate only: a shrink would replay sequences of real processes for many minutes; the
    # failing steps are printed as they ran
    machine.TestCase.settings = settings(max_examples=examples, stateful_step_count=steps, deadline=None,
                                         database=None, phases=[Phase.generate],
                                         suppress_health_check=list(HealthCheck))
    seed(seed_value)(machine.TestCase)("runTest").runTest()
    return list(REPORT)


def test_soak_short():
    soaks = run_soak(seed_value=20, examples=4, steps=14)
    steps = sum(len(s.trace) for s in soaks)
    assert steps >= 10, f"only {steps} steps ran"
    for soak in soaks:
        print(" -> ".join(soak.trace))
        for line in soak.pending:
            print("pending:", line)
