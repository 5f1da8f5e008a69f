"""The driver interfaces every backend (real, simulated, mock) implements.

The loop only ever talks to these: a `Slider` that moves, stops and reports its
position and status, and a `LoadCell` that hands over its newest reading and how
old it is. Backends live one per module, like pyserial's platform modules.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar, runtime_checkable

T = TypeVar("T")


@dataclass(frozen=True)
class Reading(Generic[T]):
    """A value with the time it was taken and whether this call took it (ophyd-async style).

    `fresh` is False when the device did not answer and the value is the last good one:
    it may stand in for display, never for a safety decision or a speed estimate.
    """

    value: T
    t_s: float  # driver clock (the loop's clock) when the value was taken
    fresh: bool = True


@dataclass(frozen=True)
class SliderStatus:
    ready: bool
    moving: bool
    in_position: bool
    alarm: bool
    alarm_code: int = 0


@dataclass(frozen=True)
class ForceReading:
    force_N: float  # as converted by the driver, before the loop's tare
    t_s: float  # loop-clock time the reading arrived
    age_s: float  # how old it was when handed over
    # The cell reported a force beyond its range (loadcell.max_abs_N): the value is what it
    # said, and the loop treats it as a force fault at once rather than as a bad line.
    over_range: bool = False


@dataclass
class LinkStats:
    """Counters every driver keeps; the loop logs them in /rig/health."""

    transactions: int = 0
    errors: int = 0
    retries: int = 0
    lines_ok: int = 0
    lines_bad: int = 0
    out_of_range: int = 0


@runtime_checkable
class Slider(Protocol):
    """What the trial needs of a linear slider: readings that carry their freshness, one move
    at a time that the drive executes itself, and a stop. ``stats`` counts the bus's
    transactions and errors. Backends: `drivers.modbus_slider` (Modbus RTU and TCP) and the
    in-process simulator."""

    stats: LinkStats

    def position(self) -> Reading[float]:
        """Feedback position, mm (one bus transaction); stale (`fresh=False`) if it failed."""

    def status(self) -> Reading[SliderStatus]:
        """READY / MOVE / IN-POS / alarm (one bus transaction); stale if it failed."""

    def read_position_mm(self) -> float:
        """`position().value`: for display and set-up, not for safety decisions."""

    def read_status(self) -> SliderStatus:
        """`status().value`."""

    def move_to(self, position_mm: float, speed_mm_s: float, accel_mm_s2: float | None = None) -> None:
        """Start one absolute move the drive executes itself; returns at once."""

    def stop(self) -> bool:
        """Stop motion now (decelerate at the drive's stop rate); False if no write was acknowledged."""

    def reset_alarm(self) -> None:
        """Clear the drive's alarm (after its cause is gone); `DeviceError` if not acknowledged."""

    def close(self) -> None: ...


@runtime_checkable
class LoadCell(Protocol):
    """What the trial needs of a load cell: its newest reading, with a timestamp and whether it
    is valid. ``stats`` counts good and bad lines and readings out of range. Backends:
    `drivers.serial_loadcell` (ASCII over a serial line) and the in-process simulator."""

    stats: LinkStats

    def latest(self) -> ForceReading | None:
        """The newest reading (a polled device is asked for one), or None before the first."""

    def close(self) -> None: ...


@runtime_checkable
class Link(Protocol):
    """How a driver reaches its device: what messages call it, and the per-transaction bound."""

    timeout_s: float

    def describe(self) -> str:
        """The link in words: "Modbus RTU /dev/ttyUSB0 115200 8N1 unit 1"."""


@runtime_checkable
class BusSlider(Slider, Protocol):
    """A slider on a bus (`drivers.modbus_slider`): the trial's contract, and what opening it
    (`rig.control.devices.open_slider`), `rig probe` and `rig move` need beyond it."""

    link: Link
    last_error: str  # the last failed transaction, in words ("" if none yet)

    def prepare(self) -> None:
        """On connect: release a STOP or home level left set, and verify it (`DeviceError`)."""

    def set_comm_timeout(self, timeout_s: float) -> bool:
        """Write the drive's communication timeout and read it back; False if the drive has no
        such register, `DeviceError` if it does not take the value."""

    def home(self) -> None:
        """Start the drive's own return-to-home operation."""
