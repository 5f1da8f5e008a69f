"""Trials for analysis: from MCAP logs or CSV files, on a uniform time grid, with phases.

Phases: `ramp`, `hold_early` (first 10 s of a hold), `hold_late`, `return`, and
`baseline` (before contact). From a log they come from the protocol steps; from a CSV
they are found in the motion itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.signal import savgol_filter

from rig.errors import RigError, SpecError
from rig.models.core import Motion

PHASES = ("ramp", "hold_early", "hold_late", "return")
HOLD_EARLY_S = 10.0


@dataclass
class TrialData:
    name: str
    motion: Motion
    force_N: np.ndarray
    phase: np.ndarray  # phase name per sample ("" = outside every phase)
    baseline_noise_N: float | None  # std of the force before contact, if there is enough of it
    source: str  # "mcap" or "csv"
    baseline_n: int = 0

    @property
    def n(self) -> int:
        return len(self.force_N)

    def mask(self, phase: str) -> np.ndarray:
        return self.phase == phase


def load_trial(path: str | Path) -> TrialData:
    path = Path(path)
    if path.suffix.lower() == ".csv":
        from rig.logs import read_csv_trial

        d = read_csv_trial(path)
        t, x_mm, f = d["t_s"], d["position_mm"], d["force_N"]
        kinds = None
    else:
        from rig.logs import read_log

        log = read_log(path)
        if log.n < 10:
            raise RigError(f"{path}: the log holds {log.n} samples: too few to analyse")
        s = log.samples
        keep = np.array([k not in ("tare", "fault", "done") for k in log.step_kind])
        pre = ~keep & (np.array(log.step_kind) == "tare")
        t, x_mm, f = s["t_s"], s["position_mm"], s["force_N"]
        kinds = np.array(log.step_kind)
        baseline = f[pre]
        t, x_mm, f, kinds = t[keep], x_mm[keep], f[keep], kinds[keep]
    t, x_mm, f, kinds = _uniform(t, x_mm, f, kinds)
    dt = float(np.median(np.diff(t)))
    x = x_mm / 1000.0
    if np.max(x) <= 0.0005:
        raise SpecError("no contact: the position never goes past 0.5 mm", path=str(path))
    v = _velocity(x, dt)
    if kinds is not None:
        phase = _phases_from_steps(t, kinds)
    else:
        phase = _phases_from_motion(t, x, v)
        baseline = f[(x <= 0) & (np.arange(len(x)) < np.argmax(x > 0))]
    noise = float(np.std(baseline)) if len(baseline) >= 20 else None
    return TrialData(path.name, Motion(t, x, v, dt), f, phase, noise,
                     "csv" if kinds is None else "mcap", len(baseline))


def _uniform(t, x, f, kinds):
    """Resample to a uniform grid when the sampling jitters by more than 1 % of a period."""
    d = np.diff(t)
    dt = float(np.median(d))
    if dt <= 0:
        raise RigError("time does not advance")
    if np.max(np.abs(d - dt)) <= 0.01 * dt:
        return t, x, f, kinds
    tu = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    idx = np.clip(np.searchsorted(t, tu), 0, len(t) - 1)
    return tu, np.interp(tu, t, x), np.interp(tu, t, f), (kinds[idx] if kinds is not None else None)


def _velocity(x: np.ndarray, dt: float) -> np.ndarray:
    """dx/dt over about 0.15 s (the encoder's steps make a raw difference noisy)."""
    win = max(5, round(0.15 / dt) | 1)
    if len(x) <= win:
        return np.gradient(x, dt)
    return savgol_filter(x, win, 2, deriv=1, delta=dt)


def _split_holds(t: np.ndarray, hold: np.ndarray, phase: np.ndarray) -> None:
    start = None
    for i in range(len(t) + 1):
        inside = i < len(t) and hold[i]
        if inside and start is None:
            start = i
        elif not inside and start is not None:
            seg = np.arange(start, i)
            early = t[seg] - t[start] < HOLD_EARLY_S
            phase[seg[early]] = "hold_early"
            phase[seg[~early]] = "hold_late"
            start = None


def _phases_from_steps(t: np.ndarray, kinds: np.ndarray) -> np.ndarray:
    phase = np.full(len(t), "", dtype=object)
    phase[kinds == "ramp"] = "ramp"
    phase[kinds == "return"] = "return"
    _split_holds(t, kinds == "hold", phase)
    return phase


def _phases_from_motion(t: np.ndarray, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    vmax = np.max(np.abs(v))
    moving = np.abs(v) > 0.1 * vmax
    phase = np.full(len(t), "", dtype=object)
    phase[moving & (v > 0) & (x > 0)] = "ramp"
    phase[moving & (v < 0) & (x > 0)] = "return"
    _split_holds(t, ~moving & (x > 0.5 * np.max(x)), phase)
    return phase
