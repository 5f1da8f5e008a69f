"""`rig spy FILE`: a wire-spy file decoded: function codes, addresses, values, CRCs, lines."""

from __future__ import annotations

import re
import statistics
from dataclasses import dataclass, field, fields
from pathlib import Path

from rig.drivers.registers import PROFILES, RegisterMap
from rig.drivers.spy import SPY_MAGIC
from rig.drivers.wireframes import (
    CHANNELS,
    FROM_DEVICE,
    TO_DEVICE,
    WireRecord,
    describe_pdu,
    request_span,
    rtu_crc_ok,
)
from rig.errors import RigError

_RECORD = re.compile(r"^(?P<t>\d+\.\d+) (?P<ch>\w+) (?P<dir>[<>]) (?P<hex>(?:[0-9A-F]{2}(?: |$))*)"
                     r"(?P<partial>partial)?$")


@dataclass
class SpyFile:
    path: str
    started: str = ""
    channels: dict[str, str] = field(default_factory=dict)
    records: list[WireRecord] = field(default_factory=list)
    dropped: int | None = None  # None: the file was not closed (the program died)


def read_spy(path: str | Path) -> SpyFile:
    """A spy file, checked line by line; `RigError` names the first line that is not one."""
    p = Path(path)
    try:
        text = p.read_bytes().decode("ascii")
    except FileNotFoundError:
        raise RigError(f"spy file not found: {p}") from None
    except OSError as exc:
        raise RigError(f"cannot read the spy file {p}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise RigError(f"{p}: not a rig spy file (it is not text)") from None
    lines = text.splitlines()
    if not lines or lines[0] != SPY_MAGIC:
        raise RigError(f"{p}: not a rig spy file (its first line is not '{SPY_MAGIC}')")
    spy = SpyFile(str(p))
    for n, line in enumerate(lines[1:], start=2):
        if line.startswith("# "):
            key, _, rest = line[2:].partition(" ")
            if key == "started":
                spy.started = rest
            elif key == "channel":
                ch, _, desc = rest.partition(" ")
                spy.channels[ch] = desc
            elif key == "dropped" and rest.isdigit():
                spy.dropped = int(rest)
            continue
        m = _RECORD.match(line)
        if m is None or m["ch"] not in CHANNELS:
            raise RigError(f"{p}:{n}: not a spy record: {line[:60]!r}")
        data = bytes.fromhex(m["hex"])
        spy.records.append(WireRecord(float(m["t"]), m["ch"], m["dir"], data, bool(m["partial"])))
    return spy


def register_names(profile: str) -> dict[int, str]:
    regs = PROFILES.get(profile, RegisterMap())
    names = {}
    for f in fields(regs):
        value = getattr(regs, f.name)
        if isinstance(value, int) and not f.name.startswith(("bit_", "type_")):
            names[value] = f.name
    return names


def _profile(desc: str) -> str:
    m = re.search(r"profile (\S+)", desc)
    return m.group(1) if m else "oriental_az"


@dataclass
class Decoded:
    record: WireRecord
    text: str
    crc_ok: bool | None = None  # RTU only
    round_trip_ms: float | None = None  # replies: time since their request


def decode(spy: SpyFile) -> list[Decoded]:
    out = []
    pending: dict[str, tuple[WireRecord, tuple[int, int] | None] | None] = {}
    for r in spy.records:
        names = register_names(_profile(spy.channels.get(r.channel, "")))
        if r.channel == "cell":
            text = repr(r.data.decode("ascii", "backslashreplace"))
            if r.partial:
                text += "  (no line end)"
            out.append(Decoded(r, text))
            continue
        request = r.direction == TO_DEVICE
        if r.channel == "rtu":
            crc = rtu_crc_ok(r.data)
            unit, pdu = (r.data[0], r.data[1:-2]) if len(r.data) >= 4 else (None, b"")
            prefix = f"unit {unit}" if unit is not None else "?"
        else:
            crc = None
            if len(r.data) >= 8:
                tid, unit, pdu = int.from_bytes(r.data[:2], "big"), r.data[6], r.data[7:]
                prefix = f"tid {tid} unit {unit}"
            else:
                pdu, prefix = b"", "?"
        asked = pending.get(r.channel)
        text = f"{prefix}  " + describe_pdu(pdu, request=request, names=names,
                                          asked=None if request or not asked else asked[1])
        if r.partial:
            text += "  (cut short)"
        rtt = None
        if request:
            pending[r.channel] = (r, request_span(pdu))
        elif asked is not None:
            rtt = (r.t_s - asked[0].t_s) * 1000.0
            pending[r.channel] = None
        else:
            text += "  (no request waiting: a late reply)"
        if crc is not None:
            text += "  CRC ok" if crc else "  CRC BAD"
        out.append(Decoded(r, text, crc, rtt))
    return out


def format_spy(spy: SpyFile, *, show_hex: bool = False, channel: str | None = None) -> str:
    lines = [f"spy file   {spy.path}" + (f"  (started {spy.started})" if spy.started else "")]
    for ch, desc in spy.channels.items():
        lines.append(f"  {ch:<4}     {desc}")
    decoded = decode(spy)
    for d in decoded:
        r = d.record
        if channel and r.channel != channel:
            continue
        way = "->" if r.direction == TO_DEVICE else "<-"
        rtt = f"  {d.round_trip_ms:.1f} ms" if d.round_trip_ms is not None else ""
        lines.append(f"{r.t_s:10.4f}  {r.channel:<4} {way}  {d.text}{rtt}")
        if show_hex:
            lines.append(f"{'':18}{r.data.hex(' ').upper()}")
    lines.append("")
    lines.extend(summarize(decoded))
    if spy.dropped is None:
        lines.append("the file ends without a footer: the program writing it stopped without closing it")
    elif spy.dropped:
        lines.append(f"{spy.dropped} records were dropped (the spy's queue was full)")
    return "\n".join(lines)


def summarize(decoded: list[Decoded]) -> list[str]:
    out = []
    for ch in CHANNELS:
        recs = [d for d in decoded if d.record.channel == ch]
        if not recs:
            continue
        sent = sum(d.record.direction == TO_DEVICE for d in recs)
        got = [d for d in recs if d.record.direction == FROM_DEVICE]
        if ch == "cell":
            partial = sum(d.record.partial for d in got)
            out.append(f"{ch:<4} {len(got)} lines from the device, {sent} requests to it"
                       + (f", {partial} without a line end" if partial else ""))
            continue
        answered = [d.round_trip_ms for d in got if d.round_trip_ms is not None]
        bad = sum(d.crc_ok is False for d in got)
        late = sum("late reply" in d.text for d in got)
        text = (f"{ch:<4} {sent} requests, {len(answered)} answered, {sent - len(answered)} unanswered"
                + (f", {bad} replies with a bad CRC" if bad else "")
                + (f", {late} late replies" if late else ""))
        if answered:
            text += (f"; round trip median {statistics.median(answered):.2f} ms, "
                     f"worst {max(answered):.2f} ms")
        out.append(text)
    if not out:
        out.append("no traffic recorded")
    return out
