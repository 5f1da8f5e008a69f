"""Long records for the model-lab benchmarks: a staircase with long holds, repeated, on the
simulated rig at 100 Hz (about 20 minutes, 120,000 samples), written as MCAP logs."""

from __future__ import annotations

import sys
from pathlib import Path

from rig.service.run import RunOptions, run_trial
from rig.specs.config import RigConfig
from rig.specs.protocol import parse_protocol

STAIRCASE = """name: long staircase
steps:
  - ramp: {to_mm: 10, speed_mm_s: 1.5}
  - hold: {duration_s: 112}
  - ramp: {to_mm: 20, speed_mm_s: 1.5}
  - hold: {duration_s: 112}
  - ramp: {to_mm: 30, speed_mm_s: 1.5}
  - hold: {duration_s: 112}
  - return: {to_mm: 0, speed_mm_s: 5}
repeat: 3
rest_s: 60
limits: {max_force_N: 15}
"""


def make(out_dir: Path, n: int = 3, drift_N_per_s: float = 0.0) -> list[Path]:
    """`n` long logs of one specimen (noise seeded apart); optionally a hidden load-cell drift."""
    from rig.sim.params import DriftParams

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        cfg = RigConfig()
        cfg.sim.seed = 100 + i
        if drift_N_per_s:
            cfg.sim.effects.drift = DriftParams(rate_N_per_s=drift_N_per_s)
        path = out_dir / f"long{i + 1}{'-drift' if drift_N_per_s else ''}.mcap"
        if not path.exists():
            run_trial(parse_protocol(STAIRCASE, "<bench>"), cfg,
                      RunOptions(speed=0, progress=False, log_path=path))
        paths.append(path)
    return paths


if __name__ == "__main__":
    for p in make(Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/rig-long"), drift_N_per_s=2e-4):
        print(p)
