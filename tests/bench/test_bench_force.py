"""The force loop over Modbus RTU at 100 Hz on the real clock, five seeds on each of three
tissues 100x apart in stiffness (tests/test_force_control.py runs one seed each):

    python -m pytest -p no:cacheprovider tests/bench/test_bench_force.py -s -q

Prints overshoot, settling time, RMS error over the sensor noise, the creep and the late ticks of
every run. The target: every run within the thresholds and without a late tick. A late tick when
the machine's own pseudo-terminal delivery stalls (printed first, `rig bench`'s figure) is the
machine's: the simulated wire rides on pseudo-terminals."""

from __future__ import annotations

import pytest

from rig.diagnostics.bench import bench_pty
from rig.recording.logs import read_log
from rig.service.run import RunOptions, run_trial
from rig.specs.protocol import parse_protocol
from tests.test_force_control import TISSUES, _check, _config, _measure, _protocol


@pytest.mark.parametrize("tissue", TISSUES)
def test_force_holds_over_rtu_five_seeds(tissue, tmp_path):
    target = TISSUES[tissue][2]
    pty = bench_pty(5.0, 100.0)
    print(f"\nmachine: a pseudo-terminal there and back p99 {pty['p99_ms']:.2f} ms, "
          f"max {pty['max_ms']:.1f} ms, {pty['over_5ms']} of {pty['round_trips']} over 5 ms")
    runs = {}
    for seed in range(1, 6):
        cfg = _config(tissue, seed)
        cfg.sim.wire = "rtu"
        result = run_trial(parse_protocol(_protocol(target), "<bench>"), cfg,
                           RunOptions(speed=1.0, progress=False, log_path=tmp_path / f"{seed}.mcap"))
        if result.outcome != "completed":  # said, and the other seeds still run: a bench reports them all
            print(f"{tissue} seed {seed}: {result.outcome}: {result.fault}")
            runs[seed] = (result, None)
            continue
        m = _measure(read_log(result.log_path), target)
        print(f"{tissue} seed {seed}: overshoot {100 * m['overshoot']:.1f} %, "
              f"settled in {m['settle_s']:.2f} s, RMS error {m['rms_over_noise']:.2f}x the noise, "
              f"creep {m['creep_mm']:.2f} mm, late ticks {result.late_ticks}, missed {result.missed_ticks}")
        runs[seed] = (result, m)
    assert all(r.outcome == "completed" for r, _ in runs.values()), \
        {seed: r.fault for seed, (r, _) in runs.items() if r.outcome != "completed"}
    for _, m in runs.values():
        _check(m)
    late = {seed: r.late_ticks + r.missed_ticks for seed, (r, _) in runs.items()}
    assert not any(late.values()), f"late or missed ticks by seed: {late}"
