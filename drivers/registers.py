"""Slider register maps as data: another drive is a new profile, not new code.

Addresses are zero-based PDU addresses; 32-bit values take two registers, upper word
first. `oriental_az` follows the Oriental Motor AZ-series Modbus RTU map (direct-data
operation from 0x0058, feedback position 0x00CC, output status 0x007E-7F, present
alarm 0x0080-81, driver input command 0x007C-7D, alarm reset 0x0180).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace


@dataclass(frozen=True)
class RegisterMap:
    direct_data: int = 0x0058  # 16 registers: data No., type, position, speed, accel, decel, current, trigger
    input_command: int = 0x007C  # 2 registers; the lower word carries the bits
    output_status: int = 0x007E  # 2 registers; the lower word carries the bits
    alarm: int = 0x0080  # 2 registers: present alarm code
    feedback_position: int = 0x00CC  # 2 registers: signed steps
    alarm_reset: int = 0x0180  # maintenance command: write 1, then 0
    # Drive parameter for the communication timeout, in ms (0 = off). Its address on a real
    # AZ drive is in the drive manual (HM-60262E); set it per installation. None = not written.
    comm_timeout_ms: int | None = None
    # output status bits
    bit_ready: int = 5
    bit_alarm: int = 7
    bit_move: int = 13
    bit_in_pos: int = 14
    # input command bits
    bit_zhome: int = 4
    bit_stop: int = 5
    bit_alarm_reset: int = 7
    # direct-data operation type for an absolute move
    type_absolute: int = 1

    def with_overrides(self, values: dict[str, int]) -> RegisterMap:
        known = {f.name for f in fields(self)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown register name(s): {', '.join(unknown)}")
        return replace(self, **values)

    @property
    def status_block(self) -> tuple[int, int]:
        """(address, count) of one read covering status and alarm when they are adjacent."""
        if self.alarm == self.output_status + 2:
            return self.output_status, 4
        return self.output_status, 2


# The simulated drive answers the comm-timeout parameter at this address (a drive-specific
# choice, not an Oriental address): it lets tests show the timeout being set over the wire.
SIM_COMM_TIMEOUT_REGISTER = 0x0300

PROFILES: dict[str, RegisterMap] = {
    "oriental_az": RegisterMap(),
    "oriental_az_sim": RegisterMap(comm_timeout_ms=SIM_COMM_TIMEOUT_REGISTER),
}


def to_words(value: int) -> list[int]:
    """A signed 32-bit integer as two 16-bit registers, upper word first."""
    v = int(value) & 0xFFFFFFFF
    return [v >> 16, v & 0xFFFF]


def from_words(hi: int, lo: int) -> int:
    v = (hi << 16) | lo
    return v - (1 << 32) if v & 0x80000000 else v
