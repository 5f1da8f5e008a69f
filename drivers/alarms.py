"""What a drive's alarm codes mean, per register profile (data, like the register maps).

`oriental_az`: the AZ-series alarm list (drive manual HM-60262E, "Alarm" chapter); the
codes below are the ones a slider on a test bench meets. The simulated drive raises the
same codes.
"""

from __future__ import annotations

ORIENTAL_AZ = {
    0x10: "excessive position deviation (the load stalled the motor, or it moved against an obstacle)",
    0x20: "overcurrent",
    0x21: "main circuit overheat",
    0x22: "overvoltage",
    0x23: "main power supply off",
    0x25: "undervoltage",
    0x26: "motor overheat",
    0x28: "sensor error (motor cable)",
    0x30: "overload (more than the rated torque for too long)",
    0x31: "overspeed",
    0x41: "EEPROM error",
    0x42: "sensor error at power on",
    0x4A: "return-to-home incomplete",
    0x60: "both limit sensors (+LS and -LS) active",
    0x66: "hardware overtravel (a limit sensor is active)",
    0x67: "software overtravel",
    0x68: "emergency stop input (HWTO)",
    0x70: "operation data error (a move the drive cannot run)",
    0x84: "RS-485 communication error (too many bad frames in a row)",
    0x85: "RS-485 communication timeout (the master fell silent longer than the drive's timeout)",
    0xF0: "CPU error",
}

ALARMS: dict[str, dict[int, str]] = {"oriental_az": ORIENTAL_AZ, "oriental_az_sim": ORIENTAL_AZ}


def alarm_meaning(profile: str, code: int) -> str:
    table = ALARMS.get(profile, {})
    return table.get(code, "not in the profile's alarm list: see the drive manual")
