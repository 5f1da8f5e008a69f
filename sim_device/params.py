"""Parameters of the simulated rig: tissue, slider mechanics, load cell and hidden effects.

Plain dataclasses so the rig config binds them from YAML with units checked by name.
Every hidden effect is off (None) by default.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

STANDARD_GRAVITY = 9.80665  # m/s^2: a mass's weight on the cell (the conventional value, CGPM 1901)


def _pos(**kw: float) -> dict:
    return {"metadata": kw}


@dataclass
class TissueParams:
    """The paper's proposed model: f + tau1 df/dt = k1 x^3 + k2 x^2 + k3 x + tau2 x dx/dt (SI units)."""

    k1_N_per_m3: float = field(default=5.6e4, **_pos(ge=0))
    k2_N_per_m2: float = field(default=5.5e2, **_pos(ge=0))
    k3_N_per_m: float = field(default=14.0, **_pos(ge=0))
    tau1_s: float = field(default=8.0, **_pos(gt=0))
    tau2_N_s_per_m2: float = field(default=2.3e5, **_pos(ge=0))
    surface_mm: float = 0.0  # where the tissue surface sits in slider coordinates
    # a material under an indenter in place of the lumped model above (sim_device.material)
    material: MaterialParams | None = None


@dataclass
class MaterialParams:
    """A relaxation modulus under an indenter's geometry (sim_device.material): the standard
    linear solid E(t) = E_inf + (E0 - E_inf) exp(-t/tau), or with `beta` > 0 the power law
    E(t) = E0 (t/t0)^-beta. `indenter`: paraboloid:R=..., cone:half_angle=...deg or
    cylinder:R=... (a flat punch)."""

    indenter: str = "paraboloid:R=5mm"
    poisson: float = field(default=0.5, **_pos(ge=0, le=0.5))
    E0_Pa: float = field(default=20e3, **_pos(gt=0))
    E_inf_Pa: float = field(default=8e3, **_pos(ge=0))
    tau_s: float = field(default=5.0, **_pos(gt=0))
    beta: float = field(default=0.0, **_pos(ge=0, le=0.99))
    t0_s: float = field(default=1.0, **_pos(gt=0))


@dataclass
class SliderParams:
    """Stepper slider with a trapezoidal velocity profile."""

    steps_per_mm: float = field(default=100.0, **_pos(gt=0))
    accel_mm_s2: float = field(default=50.0, **_pos(gt=0))
    stop_decel_mm_s2: float = field(default=2000.0, **_pos(gt=0))
    start_mm: float = 0.0


@dataclass
class LoadCellParams:
    noise_N: float = field(default=0.08, **_pos(ge=0))
    resolution_N: float = field(default=0.001, **_pos(ge=0))
    # The indicator's own low-pass filter (first order), applied to the signal and its noise
    # alike, as a real indicator does; 0 = off.
    lowpass_Hz: float = field(default=0.0, **_pos(ge=0))
    # On the wire: streamed lines at rate_Hz, or one line per request ("poll").
    mode: str = field(default="stream", metadata={"choices": ["stream", "poll"]})
    rate_Hz: float = field(default=200.0, **_pos(gt=0, le=2000))
    line_format: str = "{force_N:+.4f} N"
    # poll mode: the reply leaves this long after the request (conversion time; the bytes'
    # own time on the line comes on top when the wire is paced)
    reply_ms: float = field(default=0.0, **_pos(ge=0, le=1000))
    # Its serial line (RS-232, full duplex): each direction paced at this rate and frame.
    baudrate: int = field(default=115200, **_pos(gt=0))
    parity: str = field(default="N", metadata={"choices": ["N", "E", "O"]})
    stopbits: int = field(default=1, **_pos(ge=1, le=2))
    # The cell's sensitivity: what it reads per newton on it (1: a perfectly calibrated cell);
    # `rig calibrate` measures it with known masses.
    gain: float = field(default=1.0, **_pos(gt=0, le=10))
    # A calibration mass resting on the probe (g, weighing on the cell as a pressing force);
    # switchable at run time (`rig sim`'s {"loadcell": {"mass_g": 500}}): the simulated
    # technician's hand at `rig calibrate`.
    mass_g: float = field(default=0.0, **_pos(ge=0))


@dataclass
class DriveParams:
    """The simulated drive on the wire."""

    comm_timeout_s: float = field(default=0.5, **_pos(ge=0))  # 0 = off; alarm 0x85 when exceeded
    home_speed_mm_s: float = field(default=5.0, **_pos(gt=0))
    device_id: int = field(default=1, **_pos(ge=1, le=247))
    # Its RS-485 line (half duplex: a request and its reply take turns): the BAUD switch and
    # the frame, which set how long each byte takes (11 bits in 8E1, 10 in 8N1). The pseudo-
    # terminal itself is opened 8N1 whatever these say: ptys do not emulate parity.
    baudrate: int = field(default=115200, **_pos(gt=0))
    parity: str = field(default="N", metadata={"choices": ["N", "E", "O"]})
    stopbits: int = field(default=1, **_pos(ge=1, le=2))


@dataclass
class FaultParams:
    """Faults of the simulated devices on the wire; also switchable at run time."""

    drop_replies: int = field(default=0, **_pos(ge=0))  # the next N Modbus replies are lost
    corrupt_replies: int = field(default=0, **_pos(ge=0))  # the next N RTU replies have a bad CRC
    garble_replies: int = field(default=0, **_pos(ge=0))  # the next N replies are replaced by line noise
    reply_delay_ms: float = field(default=0.0, **_pos(ge=0))  # every reply is this late
    alarm_code: int = field(default=0, **_pos(ge=0))  # raise this drive alarm now
    loadcell_silent: bool = False  # the load cell stops sending
    garbage_lines: int = field(default=0, **_pos(ge=0))  # the next N load-cell lines are garbage
    loadcell_disconnect: bool = False  # the load cell's port goes away
    # the cell keeps sending its last value on fresh lines (an indicator stuck on HOLD, a relay
    # repeating its last line): every reading looks fresh and none moves
    loadcell_frozen: bool = False
    # the cell's noise vanishes: it reports a smooth value, the tissue's force at the moment of the
    # fault (a saturated or disconnected bridge amplifier reads steady and plausible)
    loadcell_noiseless: bool = False
    # the specimen's elastic stiffness scaled from now on (it tears, or the probe reaches bone)
    stiffness_scale: float = field(default=1.0, **_pos(gt=0))
    ignore_moves: bool = False  # moves are acknowledged but never start (motor not excited)
    ignore_stops: int = field(default=0, **_pos(ge=0))  # the next N STOPs are acknowledged, not acted on


@dataclass
class Relaxation2Params:
    """A second Maxwell branch (spring k_m in series with a dashpot, time constant tau_m) in
    parallel: the catalogue's relaxation2, its parameters under the names a fit gives them."""

    # the names before the catalogue's, still read from a config (with a DeprecatedKey warning)
    RENAMED_KEYS: ClassVar[dict[str, str]] = {"k_N_per_m": "k_m_N_per_m", "tau_s": "tau_m_s"}

    k_m_N_per_m: float = field(default=60.0, **_pos(ge=0))
    tau_m_s: float = field(default=40.0, **_pos(gt=0))


@dataclass
class DriftParams:
    rate_N_per_s: float = 0.004


@dataclass
class OffsetParams:
    """A cable pulling on the probe once it has left its start position: a tare error."""

    force_N: float = 0.3
    after_mm: float = field(default=0.05, **_pos(ge=0))


@dataclass
class ContactOffsetParams:
    x0_mm: float = field(default=1.5, **_pos(ge=0))


@dataclass
class DelayParams:
    delay_s: float = field(default=0.08, **_pos(ge=0, le=5))


@dataclass
class ComplianceParams:
    k_frame_N_per_m: float = field(default=2000.0, **_pos(gt=0))


@dataclass
class FrictionParams:
    """Coulomb friction in the probe guide; `v_smooth_mm_s` rounds the sign near zero speed."""

    force_N: float = field(default=0.15, **_pos(ge=0))
    v_smooth_mm_s: float = field(default=0.02, **_pos(gt=0))


@dataclass
class SpeedRelaxationParams:
    """Relaxation faster after a faster loading, as the paper observed: the proposed model's tau1
    becomes tau1 * (ref_speed / v)^exponent, v the fastest indentation speed of the current
    contact (tau1 itself holds at the reference speed)."""

    ref_speed_mm_s: float = field(default=1.5, **_pos(gt=0))
    exponent: float = field(default=1.0, **_pos(ge=0, le=3))


@dataclass
class FractionalParams:
    """A power-law (fractional) relaxation branch in parallel: a spring k in series with a
    springpot, the fractional Maxwell element RHEOS fits to AFM data. Its relaxation modulus is
    k E_alpha(-(t/tau)^alpha): a power law t^-alpha after tau, a Maxwell branch when alpha = 1."""

    k_N_per_m: float = field(default=60.0, **_pos(ge=0))
    tau_s: float = field(default=1.0, **_pos(gt=0))
    alpha: float = field(default=0.4, **_pos(gt=0, le=0.95))


@dataclass
class PreconditioningParams:
    """The specimen softens over its first loadings (Mullins-like): the elastic drive is scaled
    by 1 - softening (1 - exp(-n / trials)), n the loadings it has had; `done` counts those
    before this run (a series of runs on one specimen)."""

    softening: float = field(default=0.2, **_pos(ge=0, le=0.9))
    trials: float = field(default=1.5, **_pos(gt=0))
    done: int = field(default=0, **_pos(ge=0))


@dataclass
class HiddenEffects:
    relaxation2: Relaxation2Params | None = None
    drift: DriftParams | None = None
    offset: OffsetParams | None = None
    contact_offset: ContactOffsetParams | None = None
    delay: DelayParams | None = None
    compliance: ComplianceParams | None = None
    friction: FrictionParams | None = None
    # tissue physics the catalogue does not mirror term for term
    speed_relaxation: SpeedRelaxationParams | None = None
    fractional: FractionalParams | None = None
    preconditioning: PreconditioningParams | None = None

    def active(self) -> list[str]:
        return [name for name in self.__dataclass_fields__ if getattr(self, name) is not None]


@dataclass
class SimParams:
    seed: int = 1
    substep_ms: float = field(default=0.5, **_pos(gt=0, le=1))
    # How `rig run` reaches the simulated rig at --speed 1: Modbus RTU on a pseudo-terminal,
    # Modbus TCP on loopback, or "none" for the in-process devices.
    wire: str = field(default="rtu", metadata={"choices": ["rtu", "tcp", "none"]})
    # `rig sim` stands in for hardware with CPUs of its own: it asks for real-time scheduling
    # (below the loop's priority) so a busy machine does not make the simulated drive late.
    realtime: str = field(default="auto", metadata={"choices": ["auto", "off"]})
    # The wire as slow as a lab's: the drive's and the load cell's serial bytes take their time
    # on the line (baud rate and frame, `drive.baudrate`, `loadcell.baudrate`), and every byte
    # from a device waits `usb_latency_ms` in the USB-serial adapter (an FTDI's latency timer:
    # 16 ms out of the box, 1 ms tuned). false: a pseudo-terminal's instant bytes.
    pace_wire: bool = True
    usb_latency_ms: float = field(default=1.0, **_pos(ge=0, le=100))
    # Modbus TCP is not paced by baud; a reply can be made this late (a gateway, a network).
    tcp_latency_ms: float = field(default=0.0, **_pos(ge=0, le=1000))
    tissue: TissueParams = field(default_factory=TissueParams)
    slider: SliderParams = field(default_factory=SliderParams)
    loadcell: LoadCellParams = field(default_factory=LoadCellParams)
    effects: HiddenEffects = field(default_factory=HiddenEffects)
    drive: DriveParams = field(default_factory=DriveParams)
    faults: FaultParams = field(default_factory=FaultParams)
