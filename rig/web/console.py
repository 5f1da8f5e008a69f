"""The console's server side: the protocol library, `rig check` before a start, the devices' state.

A start goes to the daemon, which checks the protocol again from where the slider stands; the
check here is what the technician reads before pressing Start (the same limits, the same plan
as `rig check`), never a substitute for the daemon's.
"""

from __future__ import annotations

import contextlib
import json
import math
from datetime import UTC, datetime
from pathlib import Path

from rig.control.zero import cell_key, zero_path
from rig.errors import RigError
from rig.specs.config import RigConfig
from rig.specs.protocol import check_limits, parse_protocol, plan
from rig.specs.yamlspec import read_text


def protocol_files(folder: Path) -> list[dict]:
    """The library: every YAML file in `folder`, with its name (or why it does not read)."""
    out = []
    for path in sorted([*folder.glob("*.yaml"), *folder.glob("*.yml")]):
        try:
            name = parse_protocol(read_text(path, "protocol file"), str(path)).name
            out.append({"file": path.name, "name": name})
        except (RigError, OSError) as exc:
            out.append({"file": path.name, "name": "", "error": str(exc).splitlines()[0]})
    return out


def library_path(folder: Path, file: str) -> Path:
    """A file of the library by its name, never a path outside it."""
    path = (folder / file).resolve()
    if path.parent != folder.resolve() or path.suffix not in (".yaml", ".yml") or not path.is_file():
        raise RigError(f"no protocol {file!r} in the library ({folder})")
    return path


def limits_of(proto, config: RigConfig) -> dict:
    lim = proto.effective_limits(config.limits)
    return {"max_force_N": lim.max_force_N, "max_speed_mm_s": lim.max_speed_mm_s,
            "travel_mm": list(lim.travel_mm)}


def check(folder: Path, file: str, config: RigConfig, start_mm: float | None) -> dict:
    """`rig check` of a library protocol, from where the slider stands when that is known:
    {"ok": true, "lines": [...], "limits": ...} or {"ok": false, "error": "in words"}."""
    try:
        path = library_path(folder, file)
        proto = parse_protocol(read_text(path, "protocol file"), str(path))
        check_limits(proto, config, start_mm=start_mm)
        p = plan(proto, config)
    except RigError as exc:
        return {"ok": False, "error": str(exc)}
    limits = limits_of(proto, config)
    speeds = [s.speed_mm_s for s in proto.steps if hasattr(s, "speed_mm_s")]
    bound = "up to " if p.upper_bound else ""
    where = "from the slider's position now" if start_mm is not None else "from the start position"
    lines = [f"{path.name}: OK  '{proto.name}'"]
    if proto.description:
        lines.append(f"  {proto.description}")
    repeats = f"  (x{proto.repeat})" if proto.repeat > 1 else ""
    lines += [f"  steps     {' -> '.join(s.kind for s in proto.steps)}{repeats}",
              f"  duration  {bound}{p.duration_s:.1f} s (including {config.loop.tare_s:g} s tare)",
              f"  depths    {', '.join(f'{d:g}' for d in p.depths_mm[:12]) or '-'} mm   speeds "
              f"{', '.join(f'{v:g}' for v in speeds) or '-'} mm/s",
              f"  reach     {p.max_position_mm:g} mm at most, {where}",
              f"  limits    force {limits['max_force_N']:g} N, speed {limits['max_speed_mm_s']:g} mm/s, "
              f"travel [{limits['travel_mm'][0]:g}, {limits['travel_mm'][1]:g}] mm"]
    return {"ok": True, "protocol": proto.name, "file": path.name, "lines": lines, "limits": limits,
            "duration_s": p.duration_s, "text": read_text(path, "protocol file"), "path": str(path)}


def zero_state(config: RigConfig) -> dict:
    """The load cell's free-air zero: where it comes from and how old it is."""
    if config.loadcell.zero_N is not None:
        return {"zero_N": config.loadcell.zero_N, "source": "the config's loadcell.zero_N", "age_s": None}
    path = zero_path(config)
    try:
        entry = json.loads(path.read_text()).get(cell_key(config))
    except (OSError, ValueError, AttributeError):
        entry = None
    if not isinstance(entry, dict):
        return {"zero_N": None, "source": "none measured (`rig tare` with the probe out of contact)",
                "age_s": None}
    age = None
    with contextlib.suppress(TypeError, ValueError):
        age = (datetime.now(UTC) - datetime.fromisoformat(entry.get("measured", ""))).total_seconds()
    value = entry.get("zero_N")
    return {"zero_N": value if isinstance(value, int | float) and math.isfinite(value) else None,
            "source": f"`rig tare` at {entry.get('measured', '?')}", "age_s": age}


JOURNAL_LINES = 200  # the newest journal events shown


def _short(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list | tuple):
        return ", ".join(_short(x) for x in v[:6]) + (" ..." if len(v) > 6 else "")
    return str(v)


def journal_line(e: dict) -> str:
    """One journal event in words, as the campaign wrote it."""
    ev = e.get("event", "?")
    if ev == "start":
        return f"started: specimen {e.get('specimen')}, model {e.get('model')}"
    if ev == "trial":
        return f"trial {e.get('n')}: {e.get('protocol')} ({e.get('why', '')})"
    if ev == "ran":
        return f"trial {e.get('n')} ran: {e.get('outcome')}" + (f" - log {Path(str(e['log'])).name}"
                                                               if e.get("log") else "")
    if ev == "fit":
        ok = "adequate" if e.get("adequate") else "not adequate"
        return f"fitted {e.get('trials')} trials: {e.get('model')} ({ok})"
    if ev == "model":
        return (f"model: added {_short(e.get('added') or '-')}, removed {_short(e.get('removed') or '-')}"
                + (f": {e.get('why')}" if e.get("why") else ""))
    if ev == "decision":
        why = e.get("why") or ""
        return f"decided: {e.get('kind')}" + (f" - {_short(why)}" if why else "")
    if ev == "end":
        return f"ended: {e.get('status')} - {e.get('reason', '')}"
    skip = {"t", "event", "yaml", "considered", "refused", "summary", "sizing"}
    rest = "  ".join(f"{k}={_short(v)}" for k, v in e.items() if k not in skip and not isinstance(v, dict))
    return f"{ev}: {rest}" if rest else ev


def journal(folder: Path, path: str | None) -> dict:
    """A campaign's journal (JSON lines in the log folder), its newest events in words."""
    if not path:
        return {"ok": False, "error": "no campaign journal yet"}
    root = Path(folder).resolve()
    p = Path(path)
    p = (p if p.is_absolute() else root / p).resolve()
    if root not in p.parents or p.suffix != ".jsonl":
        return {"ok": False, "error": f"the journal {path} is not in the log folder {folder}"}
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        return {"ok": False, "error": f"cannot read the journal {path}: {exc.strerror or exc}"}
    events = []
    for line in text.splitlines():
        with contextlib.suppress(ValueError):
            e = json.loads(line)
            if isinstance(e, dict):
                events.append(e)
    lines = [{"t": e.get("t"), "event": e.get("event"), "text": journal_line(e)}
             for e in events[-JOURNAL_LINES:]]
    return {"ok": True, "journal": str(p.relative_to(root)), "events": len(events), "lines": lines,
            "ended": any(e.get("event") == "end" for e in events)}
