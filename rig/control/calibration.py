"""`rig calibrate`: the load cell calibrated with known masses.

The technician empties the probe, then places each mass in turn and confirms; the cell's
readings are averaged over `seconds` each, through the same driver and serial line protocol a
trial reads (as `rig tare` does). On the simulated rig the simulator places each mass itself
once it is confirmed (`rig sim`'s {"loadcell": {"mass_g": ...}}). `--readings FILE` scripts a
run: one mass a line (g), measured without asking; or a mass and its reading (N, with its
standard deviation and count if known), taken elsewhere, fitted without the cell.

The readings r against the masses' weights F = m g are fitted with a straight line
r = sensitivity F + offset, each point weighted by its mean's standard error (the readings'
standard deviation over the square root of their count); the standard uncertainties come from
that fit's covariance, scaled by the reduced chi-square where it exceeds 1 (the scatter about
the line beyond the noise counts). The linearity is the largest deviation of a point from the
line, in newtons of force (deviation / sensitivity) and in % of the calibrated range; its
uncertainty is that point's own and the line's there, combined. The masses are taken as exact:
a class M1 mass's tolerance (5e-5 of it) is far below these figures.

The result is saved with its date into the rig config (the `calibration:` section, written
whole; the rest of the file is kept as it is) and written into every log's header (the
"calibration" metadata record, rig.control.trial). Readings are not corrected with it: the
indicator's span is where a cell's sensitivity is set; the calibration says how far it is off.
"""

from __future__ import annotations

import math
import os
import re
import time
from collections.abc import Callable
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from rig.errors import RigError
from rig.specs.config import CalibrationConfig, RigConfig, parse_config

STANDARD_GRAVITY = 9.80665  # m/s^2
SETTLE_S = 0.3  # after a mass is placed, before its readings count


def fit_calibration(masses_g: list[float], readings_N: list[float], std_N: list[float],
                    counts: list[int], resolution_N: float = 0.0) -> dict:
    """The line through the points and its figures, each with its standard uncertainty."""
    F = np.asarray(masses_g, float) * 1e-3 * STANDARD_GRAVITY
    r = np.asarray(readings_N, float)
    if len(F) < 2 or np.ptp(F) <= 0:
        raise RigError("a calibration needs readings at two different masses at least")
    # a mean's standard error, never below what the indicator's last digit allows
    floor = resolution_N / math.sqrt(12.0)
    se = np.array([max(s, floor, 1e-12) / math.sqrt(max(n, 1)) for s, n in zip(std_N, counts, strict=True)])
    w = 1.0 / se ** 2
    X = np.column_stack([F, np.ones_like(F)])
    cov = np.linalg.inv(X.T @ (X * w[:, None]))
    sens, off = cov @ (X.T @ (w * r))
    resid = r - (sens * F + off)
    dof = len(F) - 2
    chi2 = float(np.sum(w * resid ** 2))
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
    cov = cov * scale
    worst = int(np.argmax(np.abs(resid)))
    line_var = float(X[worst] @ cov @ X[worst])
    lin_N = abs(float(resid[worst])) / sens
    span = float(np.ptp(F))
    return {"sensitivity": float(sens), "sensitivity_u": math.sqrt(cov[0, 0]),
            "offset_N": float(off), "offset_u_N": math.sqrt(cov[1, 1]),
            "linearity_N": lin_N, "linearity_u_N": math.sqrt(se[worst] ** 2 * scale + line_var) / sens,
            "linearity_pct": 100.0 * lin_N / span, "range_N": (float(F.min()), float(F.max())),
            "forces_N": F.tolist(), "deviations_N": (resid / sens).tolist(), "chi2_per_dof": chi2 / dof if dof
            else None}


def read_readings_file(path: str | Path) -> list[tuple[float, float | None, float | None, int | None]]:
    """The lines of a `--readings` file: mass (g), then optionally the reading (N), its standard
    deviation (N) and count; blank lines and # comments skipped."""
    out = []
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise RigError(f"--readings {path}: {exc.strerror}") from None
    for i, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = re.split(r"[,\s]+", line)
        try:
            nums = [float(p) for p in parts]
        except ValueError:
            raise RigError(f"{path}:{i}: expected a mass in g, then optionally its reading in N, the "
                           f"readings' standard deviation and their count; got '{line}'") from None
        if len(nums) > 4 or nums[0] < 0 or not all(math.isfinite(v) for v in nums):
            raise RigError(f"{path}:{i}: expected a mass >= 0 g and at most three figures after it; "
                           f"got '{line}'")
        out.append((nums[0], *(nums[1:3] + [None] * (2 - len(nums[1:3]))),
                    int(nums[3]) if len(nums) > 3 else None))
    if not out:
        raise RigError(f"--readings {path}: no masses in it")
    return out


def measure(config: RigConfig, masses_g: list[float], seconds: float,
            confirm: Callable[[float], None], say: Callable[[str], None] = lambda s: None) -> list[tuple]:
    """Each mass's readings over `seconds` from the load cell, after `confirm(mass_g)` returns
    (the technician placed it): (mass, mean, std, count)."""
    from rig.clock import RealClock
    from rig.control.devices import open_devices
    from rig.control.zero import measure_zero

    if config.loadcell.backend == "none":
        raise RigError("rig calibrate: loadcell.backend is none: there is no load cell to calibrate")
    if not seconds > 0:
        raise RigError(f"rig calibrate: --seconds must be positive, got {seconds:g}")
    points = []
    with open_devices(config, RealClock(), speed=1.0) as dev:
        try:
            for m in masses_g:
                confirm(m)
                if _place(dev, m):
                    say(f"(simulated rig: the simulator placed {m:g} g)")
                time.sleep(SETTLE_S)
                mean, n, std = measure_zero(dev.loadcell, seconds)
                if mean > config.loadcell.max_abs_N * 0.999:
                    raise RigError(f"{m:g} g reads {mean:g} N, at the cell's range: use lighter masses")
                points.append((m, mean, std, n))
                say(f"{m:>10g} g  {mean:+.5f} N  (std {std:.5f} N, {n} readings)")
        finally:
            _place(dev, 0.0)
    return points


def _place(dev, mass_g: float) -> bool:
    """On the simulated rig, put `mass_g` on the simulated cell; False on a real one."""
    sim = dev.sim
    if sim is None:
        return False
    if hasattr(sim, "send"):  # the simulator on the wire, in its own process
        sim.send({"loadcell": {"mass_g": mass_g}})
    else:  # in-process
        sim.params.loadcell.mass_g = mass_g
    return True


def calibration(config: RigConfig, points: list[tuple],
                keep: CalibrationConfig | None = None) -> CalibrationConfig:
    """The calibration of `points` (mass, mean, std, count), dated now."""
    from rig.control.zero import cell_key

    fit = fit_calibration([p[0] for p in points], [p[1] for p in points], [p[2] for p in points],
                          [p[3] for p in points], config.sim.loadcell.resolution_N
                          if config.loadcell.backend == "sim" else 0.0)
    return CalibrationConfig(
        date=datetime.now(UTC).isoformat(timespec="seconds"), cell=cell_key(config),
        **{k: fit[k] for k in ("sensitivity", "sensitivity_u", "offset_N", "offset_u_N", "linearity_N",
                               "linearity_u_N", "linearity_pct", "range_N")},
        masses_g=[float(p[0]) for p in points], readings_N=[float(p[1]) for p in points],
        max_age_days=keep.max_age_days if keep is not None else CalibrationConfig.max_age_days)


def calibration_yaml(cal: CalibrationConfig) -> str:
    """The calibration as the config's `calibration:` block, numbers to eight figures."""
    d = asdict(cal)

    def num(v: float) -> str:
        return f"{v:.8g}"

    lines = ["calibration:  # the load cell's, by `rig calibrate`"]
    for k, v in d.items():
        if isinstance(v, str):
            lines.append(f"  {k}: \"{v}\"")
        elif isinstance(v, list | tuple):
            lines.append(f"  {k}: [{', '.join(num(x) for x in v)}]")
        else:
            lines.append(f"  {k}: {num(v)}")
    return "\n".join(lines) + "\n"


def save_calibration(path: str | Path, cal: CalibrationConfig) -> Path:
    """`cal` as the `calibration:` section of the config file at `path` (created if absent): an
    earlier section replaced, the rest of the file kept; checked by reading it back, then
    written whole and renamed into place."""
    p = Path(path)
    old = p.read_text() if p.exists() else ""
    kept, skipping = [], False
    for line in old.splitlines(keepends=True):
        if re.match(r"calibration\s*:", line):
            skipping = True
            continue
        if skipping and (not line.strip() or line[0] in " \t#"):
            continue
        skipping = False
        kept.append(line)
    body = "".join(kept)
    if body and not body.endswith("\n"):
        body += "\n"
    text = body + calibration_yaml(cal)
    parse_config(text, str(p))  # what is written reads back
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, p)
    return p


def age_days(cal: CalibrationConfig, now: datetime | None = None) -> float | None:
    """Days since the calibration (None if its date does not parse)."""
    try:
        when = datetime.fromisoformat(cal.date)
    except ValueError:
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return ((now or datetime.now(UTC)) - when).total_seconds() / 86400.0


def calibration_warnings(config: RigConfig, max_force_N: float | None = None) -> list[str]:
    """What is wrong with the config's calibration for a trial up to `max_force_N`: too old, or
    a force limit beyond the calibrated range; [] without a calibration."""
    cal = config.calibration
    if cal is None:
        return []
    out = []
    age = age_days(cal)
    if age is None:
        out.append(f"the load cell's calibration has no readable date ('{cal.date}'): run `rig calibrate`")
    elif age > cal.max_age_days:
        out.append(f"the load cell's calibration is {age:.0f} days old ({cal.date[:10]}), beyond "
                   f"calibration.max_age_days ({cal.max_age_days:g}): run `rig calibrate`")
    if max_force_N is not None and max_force_N > cal.range_N[1]:
        out.append(f"the force limit {max_force_N:g} N is beyond the calibrated range "
                   f"({cal.range_N[0]:g}-{cal.range_N[1]:.4g} N): forces above {cal.range_N[1]:.4g} N are "
                   "read uncalibrated (calibrate with heavier masses)")
    return out


def header(cal: CalibrationConfig) -> dict[str, str]:
    """The log's "calibration" metadata record."""
    age = age_days(cal)
    return {"date": cal.date, "cell": cal.cell, "sensitivity": f"{cal.sensitivity:.8g}",
            "sensitivity_u": f"{cal.sensitivity_u:.3g}", "offset_N": f"{cal.offset_N:.6g}",
            "offset_u_N": f"{cal.offset_u_N:.3g}", "linearity_N": f"{cal.linearity_N:.4g}",
            "linearity_u_N": f"{cal.linearity_u_N:.3g}", "linearity_pct": f"{cal.linearity_pct:.4g}",
            "range_N": f"{cal.range_N[0]:g} {cal.range_N[1]:.6g}",
            "masses_g": " ".join(f"{m:g}" for m in cal.masses_g),
            "age_days": "" if age is None else f"{age:.1f}", "max_age_days": f"{cal.max_age_days:g}"}


def format_calibration(cal: CalibrationConfig, fit: dict, saved: Path | None) -> str:
    """The calibration in words: each mass's force and reading with its deviation from the line, the
    sensitivity and offset with their errors, and where it was saved."""
    lines = [f"load cell {cal.cell}: calibrated with {len(cal.masses_g)} masses",
             f"  {'mass g':>9}  {'force N':>10}  {'reading N':>10}  {'deviation N':>11}"]
    for m, F, r, d in zip(cal.masses_g, fit["forces_N"], cal.readings_N, fit["deviations_N"], strict=True):
        lines.append(f"  {m:>9g}  {F:>10.5f}  {r:>+10.5f}  {d:>+11.5f}")
    lines += [f"sensitivity  {cal.sensitivity:.6f} +/- {cal.sensitivity_u:.2g} (reading per applied N)",
              f"offset       {cal.offset_N:+.5f} +/- {cal.offset_u_N:.2g} N",
              f"linearity    {cal.linearity_N:.5f} +/- {cal.linearity_u_N:.2g} N, {cal.linearity_pct:.3f} % of "
              f"the calibrated range {cal.range_N[0]:g}-{cal.range_N[1]:.5g} N",
              f"date         {cal.date}"]
    if saved is not None:
        lines.append(f"saved in     {saved} (calibration:); every log's header carries it")
    return "\n".join(lines)
