"""Bytes on the wire into frames and lines, and frames into words a rig builder reads.

A spy sees bytes in the pieces the port hands them over: a Modbus reply may come in two
reads, a load-cell line in three. `Assembler` cuts each channel's bytes into whole
Modbus RTU frames (by the length the function code implies), Modbus TCP frames (by the
MBAP length) and load-cell lines (at the line end). `describe_modbus` decodes one frame.
"""

from __future__ import annotations

from dataclasses import dataclass

TO_DEVICE = ">"
FROM_DEVICE = "<"
CHANNELS = ("rtu", "tcp", "cell")

EXCEPTIONS = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
              4: "device failure", 5: "acknowledge", 6: "device busy", 10: "gateway path unavailable",
              11: "gateway target did not respond"}
FUNCTIONS = {1: "read coils", 2: "read discrete inputs", 3: "read holding registers",
             4: "read input registers", 5: "write coil", 6: "write register", 15: "write coils",
             16: "write registers", 23: "read/write registers"}


def crc16(data: bytes) -> int:
    """Modbus RTU CRC (poly 0xA001, init 0xFFFF); sent low byte first."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def rtu_crc_ok(frame: bytes) -> bool:
    return len(frame) >= 4 and crc16(frame[:-2]) == int.from_bytes(frame[-2:], "little")


def _reply_pdu_length(pdu: bytes) -> int | None:
    """Length of a reply PDU (function code first), or None until enough of it is there."""
    if not pdu:
        return None
    fc = pdu[0]
    if fc & 0x80:
        return 2
    if fc in (1, 2, 3, 4, 23):
        return 2 + pdu[1] if len(pdu) >= 2 else None
    if fc in (5, 6, 15, 16):
        return 5
    return len(pdu)  # unknown function: take what came


def rtu_reply_length(buf: bytes) -> int | None:
    n = _reply_pdu_length(buf[1:])
    return None if n is None else 1 + n + 2


def tcp_frame_length(buf: bytes) -> int | None:
    return 6 + int.from_bytes(buf[4:6], "big") if len(buf) >= 6 else None


@dataclass(frozen=True)
class WireRecord:
    t_s: float
    channel: str  # rtu, tcp or cell
    direction: str  # ">" to the device, "<" from it
    data: bytes
    partial: bool = False  # cut short: the rest never came before the next request or the end


class Assembler:
    """One channel's pieces of bytes into whole frames or lines, each with the time it completed."""

    MAX_LINE = 256

    def __init__(self, channel: str) -> None:
        if channel not in CHANNELS:
            raise ValueError(f"unknown channel {channel!r}")
        self.channel = channel
        self._buf = bytearray()
        self._t_s = 0.0

    def feed(self, t_s: float, direction: str, data: bytes) -> list[WireRecord]:
        if direction == TO_DEVICE:
            out = [] if self.channel == "cell" else self.flush()
            return [*out, WireRecord(t_s, self.channel, direction, bytes(data))]
        self._buf += data
        self._t_s = t_s
        return self._cut()

    def _cut(self) -> list[WireRecord]:
        out = []
        while self._buf:
            n = self._next_length()
            if n is None or n > len(self._buf):
                break
            out.append(WireRecord(self._t_s, self.channel, FROM_DEVICE, bytes(self._buf[:n])))
            del self._buf[:n]
        return out

    def _next_length(self) -> int | None:
        buf = bytes(self._buf)
        if self.channel == "rtu":
            return rtu_reply_length(buf)
        if self.channel == "tcp":
            return tcp_frame_length(buf)
        i = buf.find(b"\n")
        if i >= 0:
            return i + 1
        j = buf.find(b"\r")
        if 0 <= j < len(buf) - 1:  # a lone CR ends a line too (a CR at the end may be half a CRLF)
            return j + 1
        return len(buf) if len(buf) > self.MAX_LINE else None

    def flush(self) -> list[WireRecord]:
        """What is left: a line that ended with CR, or a frame cut short."""
        if not self._buf:
            return []
        data = bytes(self._buf)
        self._buf.clear()
        partial = not (self.channel == "cell" and data.endswith(b"\r"))
        return [WireRecord(self._t_s, self.channel, FROM_DEVICE, data, partial)]


# ------------------------------------------------------------------ decoding

def _words(data: bytes) -> list[int]:
    return [int.from_bytes(data[i:i + 2], "big") for i in range(0, len(data) - 1, 2)]


def _int32s(words: list[int]) -> list[int]:
    out = []
    for hi, lo in zip(words[::2], words[1::2], strict=False):
        v = (hi << 16) | lo
        out.append(v - (1 << 32) if v & 0x80000000 else v)
    return out


def _values(words: list[int]) -> str:
    text = " ".join(f"{w:04X}" for w in words)
    if words and len(words) % 2 == 0:
        text += f"  (int32 {', '.join(str(v) for v in _int32s(words))})"
    return text


def describe_pdu(pdu: bytes, *, request: bool, names: dict[int, str] | None = None,
                 asked: tuple[int, int] | None = None) -> str:
    """One PDU in words. `asked` is (address, count) of the request a read reply answers."""
    names = names or {}

    def where(address: int) -> str:
        name = names.get(address)
        return f"0x{address:04X}" + (f" {name}" if name else "")

    if not pdu:
        return "empty"
    fc = pdu[0]
    if fc & 0x80:
        code = pdu[1] if len(pdu) > 1 else -1
        return (f"FC{fc & 0x7F:02d} exception {code}: {EXCEPTIONS.get(code, 'unknown code')}")
    name = FUNCTIONS.get(fc, "unknown function")
    body = pdu[1:]
    try:
        if request:
            if fc in (1, 2, 3, 4):
                return f"FC{fc:02d} {name} {where(_words(body)[0])} x{_words(body)[1]}"
            if fc in (5, 6):
                address, value = _words(body)[:2]
                return f"FC{fc:02d} {name} {where(address)} = {value:04X}"
            if fc in (15, 16):
                address, count = _words(body)[:2]
                return f"FC{fc:02d} {name} {where(address)} x{count}: {_values(_words(body[5:]))}"
        else:
            if fc in (1, 2, 3, 4, 23):
                words = _words(body[1:1 + body[0]])
                at = f" from {where(asked[0])}" if asked else ""
                return f"FC{fc:02d} reply{at}: {_values(words)}"
            if fc in (5, 6, 15, 16):
                address, value = _words(body)[:2]
                what = "=" if fc in (5, 6) else "x"
                return f"FC{fc:02d} acknowledged {where(address)} {what}{value}"
    except (IndexError, ValueError):
        return f"FC{fc:02d} {name}, cut short"
    return f"FC{fc:02d} {name}: {body.hex(' ').upper()}"


def request_span(pdu: bytes) -> tuple[int, int] | None:
    """(address, count) a read request asks for, to label its reply."""
    if len(pdu) >= 5 and pdu[0] in (1, 2, 3, 4):
        words = _words(pdu[1:5])
        return words[0], words[1]
    return None
