"""The load cell's free-air zero: what it reads with nothing touching the probe.

A trial tares on the mean of its first `loop.tare_s`; if the probe already presses on the
tissue then, that tare holds a preload (tare - zero), and the force limit must count it: the
limit applies to the force the tissue carries, raw - zero. Where the zero comes from, first
found wins:

1. `loadcell.zero_N` in the config (a cell zeroed in its indicator: 0);
2. the zero `rig tare` measured out of contact and saved for this load cell;
3. the zero an earlier trial of the same daemon used (a `stop --hold` then `start` counts
   the preload held);
4. none: the trial's own tare is taken as the zero (preload 0). That assumes the trial
   starts out of contact; the log's tare event and the warning say so.

The saved zeros live in `<recorder.out_dir>/.loadcell-zero.json`, keyed by the load cell
(backend and port): the trials' folder is the one place the daemon and every `rig run` with
the same config share and may write (a per-user state directory would differ between the
daemon's user and an operator's), and the zero belongs to the rig, like its logs.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from rig.drivers.base import LoadCell
from rig.errors import DeviceError, RigError
from rig.specs.config import RigConfig

ZERO_FILE = ".loadcell-zero.json"


@dataclass(frozen=True)
class Zero:
    """The load cell's free-air zero a trial measures force from: its value, where it came from,
    and whether it is only assumed (a trial's own tare, not a reading out of contact)."""

    value_N: float
    source: str  # said in the log and in messages
    assumed: bool = False  # a trial's tare taken as the zero, not a measurement out of contact


def cell_key(config: RigConfig) -> str:
    """Which load cell a saved zero belongs to: its backend and port."""
    lc = config.loadcell
    return f"{lc.backend}:{lc.port}" if lc.port else lc.backend


def zero_path(config: RigConfig) -> Path:
    """Where the free-air zeros are saved: beside the logs."""
    return Path(config.recorder.out_dir) / ZERO_FILE


def _read_all(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        raise RigError(f"{path}: cannot read the saved load-cell zeros ({exc}); run `rig tare` "
                       "out of contact to write it again") from None
    if not isinstance(data, dict):
        raise RigError(f"{path}: the saved load-cell zeros are not a mapping; run `rig tare` again")
    return data


def saved_zero(config: RigConfig) -> Zero | None:
    """The zero `rig tare` saved for this config's load cell, or None."""
    path = zero_path(config)
    entry = _read_all(path).get(cell_key(config))
    if entry is None:
        return None
    value = entry.get("zero_N") if isinstance(entry, dict) else None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise RigError(f"{path}: the zero saved for load cell {cell_key(config)} is not a finite "
                       f"number ({value!r}); run `rig tare` again")
    return Zero(float(value), f"`rig tare` at {entry.get('measured', '?')} ({path})")


def known_zero(config: RigConfig) -> Zero | None:
    """The configured or saved zero (sources 1 and 2), or None."""
    if config.loadcell.zero_N is not None:
        return Zero(config.loadcell.zero_N, "the config's loadcell.zero_N")
    return saved_zero(config)


def save_zero(config: RigConfig, zero_N: float, readings: int, std_N: float) -> Path:
    """Remember a zero measured out of contact; written whole, then renamed (never half a file)."""
    path = zero_path(config)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = _read_all(path)
    data[cell_key(config)] = {"zero_N": zero_N, "readings": readings, "std_N": std_N,
                              "measured": datetime.now(UTC).isoformat(timespec="seconds")}
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)
    return path


def measure_zero(loadcell: LoadCell, duration_s: float) -> tuple[float, int, float]:
    """Mean, count and standard deviation of the distinct readings over `duration_s` (real
    time); an over-range or missing reading is an error, not a zero."""
    values: list[float] = []
    last_t = None
    deadline = time.monotonic() + duration_s
    while time.monotonic() < deadline:
        r = loadcell.latest()
        if r is not None and r.t_s != last_t:
            if r.over_range:
                raise DeviceError(f"load cell over range ({r.force_N:g} N) while taring: not a zero")
            values.append(r.force_N)
            last_t = r.t_s
        time.sleep(0.002)
    if len(values) < 2:
        raise DeviceError(f"load cell: {len(values)} readings in {duration_s:g} s; cannot measure its zero")
    mean = sum(values) / len(values)
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1))
    return mean, len(values), std


def tare(config: RigConfig, seconds: float = 1.0) -> dict:
    """`rig tare`: measure the load cell with the probe out of contact and save it as its zero.

    The probe must not touch anything: this is what every later trial counts a preload from.
    """
    from rig.clock import RealClock
    from rig.control.devices import open_devices

    if config.loadcell.backend == "none":
        raise RigError("rig tare: loadcell.backend is none: there is no load cell to zero")
    if not seconds > 0:
        raise RigError(f"rig tare: --seconds must be positive, got {seconds:g}")
    with open_devices(config, RealClock(), speed=1.0) as dev:
        mean, n, std = measure_zero(dev.loadcell, seconds)
        before = saved_zero(config)
    path = save_zero(config, mean, n, std)
    return {"zero_N": mean, "readings": n, "std_N": std, "path": str(path), "cell": cell_key(config),
            "previous_N": before.value_N if before else None,
            "config_zero_N": config.loadcell.zero_N}
