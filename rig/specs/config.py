"""Rig configuration: YAML bound to dataclasses. The defaults are the simulated rig.

`config/sim-rig.yaml` spells the defaults out; any field left out of a file keeps its
default, so a config names only what differs from the simulated rig.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import yaml

from rig.errors import SpecError
from rig.sim.params import SimParams
from rig.specs.yamlspec import bind, load_marked, read_text


@dataclass
class LoopConfig:
    rate_Hz: float = field(default=100.0, metadata={"gt": 0, "le": 1000})
    # A tick is late when it starts more than this after its slot (default: half a period at
    # 100 Hz, i.e. its sample sits nearer the next slot than its own). Lateness of every tick
    # is logged (`late_ms`), so nothing hides below the threshold.
    late_tolerance_ms: float = field(default=5.0, metadata={"gt": 0})
    status_every: int = field(default=10, metadata={"ge": 1})  # read status/alarm every N ticks
    tare_s: float = field(default=0.5, metadata={"ge": 0})
    spin_ms: float = field(default=0.3, metadata={"ge": 0})  # busy-wait before each deadline
    health_every_s: float = field(default=1.0, metadata={"gt": 0})
    # Real-time scheduling of the loop thread (SCHED_FIFO) and locked memory: "auto" asks and
    # carries on without it (the log records which), "required" refuses to run without it.
    realtime: str = field(default="auto", metadata={"choices": ["auto", "required", "off"]})
    realtime_priority: int = field(default=50, metadata={"ge": 1, "le": 99})


# Bounds on the limits that are checks: a value past them would switch the check off without a
# word (a stale limit of an hour never fires). Each is well beyond any rig's need.
MAX_STALE_MS = 1000.0
MAX_TRAVEL_MM = 10_000.0
MAX_SPEED_MM_S = 1000.0
MAX_PROTOCOL_STEPS_CEILING = 1_000_000


@dataclass
class LimitsConfig:
    # At most the load cell's range (loadcell.max_abs_N), checked when the config is read: a
    # limit the cell cannot read limits nothing.
    max_force_N: float = field(default=20.0, metadata={"gt": 0})
    # Slider coordinates, within +-10 m: a window wider than any slider's stroke limits nothing.
    travel_mm: tuple[float, float] = field(default=(-5.0, 45.0), metadata={
        "ge": -MAX_TRAVEL_MM, "le": MAX_TRAVEL_MM, "why": "a travel window wider than any slider's stroke"})
    # At most 1 m/s: faster than any indentation slider.
    max_speed_mm_s: float = field(default=10.0, metadata={
        "gt": 0, "le": MAX_SPEED_MM_S, "why": "a speed limit beyond any indentation slider limits nothing"})
    # No new load-cell reading for this long is a fault; at most a second, so that no config
    # switches the check off.
    loadcell_stale_ms: float = field(default=100.0, metadata={
        "gt": 0, "le": MAX_STALE_MS,
        "why": f"the load cell's stale check cannot be switched off ({MAX_STALE_MS:g} ms at most)"})
    # Measured speed above max_speed_mm_s * overspeed_factor is a fault (runaway drive).
    overspeed_factor: float = field(default=1.5, metadata={
        "ge": 1, "le": 4, "why": "the overspeed check cannot be switched off"})
    # Every move has a deadline: planned time x factor + slack. It must show motion within
    # move_start_s and may not run past its target by more than overshoot_mm.
    move_deadline_factor: float = field(default=1.25, metadata={
        "ge": 1, "le": 10, "why": "a move's deadline cannot be switched off"})
    move_deadline_slack_s: float = field(default=0.5, metadata={
        "gt": 0, "le": 60, "why": "a move's deadline cannot be switched off"})
    move_start_s: float = field(default=0.3, metadata={
        "gt": 0, "le": 5, "why": "a drive that takes a move and does not move must be caught"})
    overshoot_mm: float = field(default=0.1, metadata={
        "gt": 0, "le": 5, "why": "a drive that runs past its target must be caught"})
    # After a STOP, the drive must report standing still within this; STOP is re-sent meanwhile.
    stop_confirm_s: float = field(default=2.0, metadata={
        "gt": 0, "le": 10, "why": "an unconfirmed STOP must be reported"})
    # Without a load cell the force limit applies to the model's estimate times (1 + margin).
    model_force_margin: float = field(default=0.25, metadata={"ge": 0})
    # A trial tared in contact starts with a preload (its tare minus the load cell's free-air
    # zero); the limit counts it. A preload above this share of max_force_N is refused before
    # anything moves: the probe is pressed in, retract it first.
    max_preload_share: float = field(default=0.5, metadata={"ge": 0, "le": 1})
    # The most steps a protocol may execute: len(steps) x repeat, plus a rest between repeats.
    # The loop, its status and the checks before a trial walk them; a protocol beyond this is
    # refused before anything moves (`repeat: 100000000` would take minutes and gigabytes).
    max_protocol_steps: int = field(default=10_000, metadata={"ge": 1, "le": MAX_PROTOCOL_STEPS_CEILING})

    def __post_init__(self) -> None:
        lo, hi = self.travel_mm
        if not lo < hi:
            raise ValueError(f"travel_mm must be [min, max] with min < max, got [{lo}, {hi}]")


@dataclass
class EstimatorConfig:
    law: str = field(default="constant_information",
                     metadata={"choices": ["constant_information", "fixed"]})
    memory_s: float = field(default=0.3, metadata={"gt": 0})
    smoothing_s: float = field(default=0.1, metadata={"gt": 0})
    lambda_min: float = field(default=0.8, metadata={"gt": 0, "le": 1})
    lambda_max: float = field(default=0.9999, metadata={"gt": 0, "le": 1})
    noise_N: float = field(default=0.08, metadata={"gt": 0})
    initial_stiffness_N_per_m: float = 0.0
    initial_std_N_per_m: float = field(default=1000.0, metadata={"gt": 0})
    contact_mm: float = field(default=0.2, metadata={"ge": 0})
    contact_N: float = field(default=0.05, metadata={"ge": 0})

    def __post_init__(self) -> None:
        if self.lambda_min > self.lambda_max:
            raise ValueError("lambda_min must not exceed lambda_max")


@dataclass
class ForceControlConfig:
    """Force-controlled steps (`ramp_force`, `hold_force`): how far the force loop trusts its
    load cell, and what it reports of each step (`rig.control.sensorwatch`, `rig.control.force`)."""

    # Out of contact a force step seeks the surface at this share of the speed limit (an
    # approach's pace); the loop takes over once the force shows contact.
    seek_speed_share: float = field(default=0.05, metadata={"gt": 0, "le": 0.5})
    # In contact, the slider may travel at most this far with the force unchanged (the default
    # is five times the travel that should change it by four sigma at the measured stiffness,
    # capped here): further is a frozen or disconnected load cell, a fault.
    answer_mm: float = field(default=5.0, metadata={"gt": 0, "le": 10})
    # A force step that overshoots its setpoint by more than this share, or whose hold's RMS
    # error (past its first second) is above this many sigma of the load cell's noise, is said:
    # an event in the log and a notice for the operator.
    overshoot_warn_share: float = field(default=0.05, metadata={"gt": 0, "le": 1})
    rms_warn_sigma: float = field(default=2.0, metadata={"gt": 0})


@dataclass
class SliderConfig:
    # sim: the simulated rig (on the wire at --speed 1 unless sim.wire is none);
    # modbus-rtu / modbus-tcp: a real drive.
    backend: str = field(default="sim", metadata={"choices": ["sim", "modbus-rtu", "modbus-tcp"]})
    accel_mm_s2: float = field(default=50.0, metadata={"gt": 0})
    position_tolerance_mm: float = field(default=0.02, metadata={"gt": 0})
    port: str = ""  # modbus-rtu: serial device (or pyserial URL)
    baudrate: int = field(default=115200, metadata={"gt": 0})
    parity: str = field(default="N", metadata={"choices": ["N", "E", "O"]})
    stopbits: int = field(default=1, metadata={"ge": 1, "le": 2})
    host: str = "127.0.0.1"  # modbus-tcp
    tcp_port: int = field(default=502, metadata={"ge": 1, "le": 65535})
    device_id: int = field(default=1, metadata={"ge": 0, "le": 247})
    timeout_s: float = field(default=0.02, metadata={"gt": 0})  # per transaction
    retries: int = field(default=0, metadata={"ge": 0, "le": 3})
    max_consecutive_errors: int = field(default=5, metadata={"ge": 1})
    steps_per_mm: float = field(default=100.0, metadata={"gt": 0})
    profile: str = "oriental_az"  # register map (drivers/registers.py)
    registers: dict[str, int] = field(default_factory=dict)  # overrides of the profile
    current_percent: float = field(default=100.0, metadata={"gt": 0, "le": 100})
    # Written to the drive on connect (profiles that know the register): the drive stops by
    # itself when the controller falls silent this long.
    comm_timeout_s: float = field(default=0.5, metadata={"ge": 0})
    # A profile that cannot set the communication timeout leaves the drive running if the
    # controller dies: refused unless this says the rig runs without that backstop.
    allow_no_comm_timeout: bool = False
    # The drive's own return-to-home speed (a drive parameter): checked against the limits.
    home_speed_mm_s: float = field(default=5.0, metadata={"gt": 0})


@dataclass
class LoadCellConfig:
    # none: no load cell; the force is the model's estimate (`model:` must name one)
    backend: str = field(default="sim", metadata={"choices": ["sim", "serial", "none"]})
    port: str = ""  # serial device or pyserial URL (e.g. loop://)
    baudrate: int = field(default=115200, metadata={"gt": 0})
    mode: str = field(default="stream", metadata={"choices": ["stream", "poll"]})
    request: str = "?\r\n"  # poll mode: sent once per tick
    pattern: str = ""  # regular expression with a group 'value' (and optional 'unit'); "" = default
    unit: str = "N"  # when lines carry no unit: N, kN, mN, lbf, kgf, g
    counts: bool = False  # raw counts: force = gain_N_per_count * (value - offset_counts)
    gain_N_per_count: float = 1.0
    offset_counts: float = 0.0
    max_abs_N: float = field(default=500.0, metadata={"gt": 0})
    # What the cell reads with nothing touching the probe (N, as converted). Unset: the zero
    # `rig tare` measured and saved for this cell, else the tare of the daemon's earlier trial,
    # else each trial's own tare is assumed to be taken out of contact (and the log says so).
    zero_N: float | None = None

    def __post_init__(self) -> None:
        if self.zero_N is not None and not abs(self.zero_N) <= self.max_abs_N:
            raise ValueError(f"zero_N must be a finite force within max_abs_N ({self.max_abs_N:g} N), "
                             f"got {self.zero_N}")


@dataclass
class CalibrationConfig:
    """The load cell's calibration with known masses, as `rig calibrate` saves it (its date, and
    each figure with its standard uncertainty): the cell reads `sensitivity` per newton on it,
    plus `offset_N`; `linearity_N` is the largest deviation of a mass's reading from that line
    (in N of force; `linearity_pct` of the calibrated range `range_N`). Every log's header
    carries it; one older than `max_age_days`, or a force beyond `range_N`, is warned about at
    `rig check` and in the log."""

    date: str = ""  # ISO 8601, UTC
    cell: str = ""  # the load cell it was measured on (backend:port)
    sensitivity: float = field(default=1.0, metadata={"gt": 0})
    sensitivity_u: float = field(default=0.0, metadata={"ge": 0})
    offset_N: float = 0.0
    offset_u_N: float = field(default=0.0, metadata={"ge": 0})
    linearity_N: float = field(default=0.0, metadata={"ge": 0})
    linearity_u_N: float = field(default=0.0, metadata={"ge": 0})
    linearity_pct: float = field(default=0.0, metadata={"ge": 0})
    range_N: tuple[float, float] = (0.0, 0.0)
    masses_g: list[float] = field(default_factory=list)
    readings_N: list[float] = field(default_factory=list)
    # older than this, `rig check` and every trial's log warn that the cell is due a calibration
    max_age_days: float = field(default=365.0, metadata={"gt": 0})


@dataclass
class RecorderConfig:
    out_dir: str = "trials"
    flush_s: float = field(default=1.0, metadata={"gt": 0})
    compression: str = field(default="zstd", metadata={"choices": ["zstd", "lz4", "none"]})
    # Messages waiting for the writer; more means the disk cannot keep up: a recording fault.
    max_queue: int = field(default=20000, metadata={"ge": 100})


@dataclass
class LiveConfig:
    """The live view (Foxglove WebSocket protocol; needs the extra `rig[live]`)."""

    host: str = "127.0.0.1"  # loopback only unless you mean otherwise
    port: int = field(default=8765, metadata={"ge": 0, "le": 65535})
    max_queue: int = field(default=2000, metadata={"ge": 10})  # beyond it, the oldest are dropped


@dataclass
class DaemonConfig:
    socket: str = ""  # "" = /run/rig/rigd.sock as root, else $XDG_RUNTIME_DIR/rig/rigd.sock
    group: str = ""  # group allowed to use the socket besides the owner ("" = owner only)
    max_request_bytes: int = field(default=65536, metadata={"ge": 1024})
    watch_rate_Hz: float = field(default=10.0, metadata={"gt": 0, "le": 100})
    stall_s: float = field(default=1.0, metadata={"gt": 0})  # no tick this long: withhold watchdog pings
    live: LiveConfig | None = None  # e.g. {port: 8765}: publish every trial live


@dataclass
class RigConfig:
    """A rig as its YAML config describes it: the loop's rate, the safety limits, the estimator,
    force control, the slider's and load cell's backends and links, the recorder, the daemon,
    the simulator's parameters, and optionally a saved model run in the loop, the probe's
    indenter and the load cell's calibration. The defaults are the built-in simulated rig;
    `load_config` reads and checks a file, and ``text()`` is the config exactly as run (logged
    with every trial)."""

    name: str = "simulated rig"
    loop: LoopConfig = field(default_factory=LoopConfig)
    limits: LimitsConfig = field(default_factory=LimitsConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    force: ForceControlConfig = field(default_factory=ForceControlConfig)
    slider: SliderConfig = field(default_factory=SliderConfig)
    loadcell: LoadCellConfig = field(default_factory=LoadCellConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
    daemon: DaemonConfig = field(default_factory=DaemonConfig)
    sim: SimParams = field(default_factory=SimParams)
    # A saved model (`rig analyze ... --save`) run in the loop from the measured position:
    # force_model_N and model_error_N in every sample.
    model: str = ""
    # The probe's geometry as an indenter (e.g. cylinder:R=2mm, sphere:R=5mm): `rig analyze` reads
    # it from each log and fits moduli in Pa (the hertz model); "" leaves the models lumped.
    probe: str = ""
    # The load cell's calibration (`rig calibrate` writes it here); none: never calibrated.
    calibration: CalibrationConfig | None = None
    source_text: str = field(default="", repr=False, compare=False)
    source_path: str = field(default="<built-in simulated rig>", repr=False, compare=False)

    def to_yaml(self) -> str:
        data = asdict(self)
        data.pop("source_text")
        data.pop("source_path")
        return yaml.safe_dump(_plain(data), sort_keys=False)

    def text(self) -> str:
        """The config exactly as run: the file's text, or the built-in defaults spelled out."""
        return self.source_text or self.to_yaml()

    def digest(self) -> str:
        return hashlib.sha256(self.text().encode()).hexdigest()[:16]


def _plain(obj: object) -> object:
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    return obj


def load_config(path: str | Path | None) -> RigConfig:
    """Load and validate a rig config; None gives the built-in simulated rig."""
    if path is None:
        return RigConfig()
    return parse_config(read_text(path, "config file"), str(path))


def parse_config(text: str, path: str = "<config>") -> RigConfig:
    """The config in `text` (YAML), checked: an unknown key, a wrong type or a value out of its
    range raises `RigError` naming the file, the line and the key."""
    node = load_marked(path, text)
    _refuse_keys(node, ("source_text", "source_path"), path)
    cfg = bind(RigConfig, node, path)
    _check_material(cfg, node, path)
    _check_force_limit(cfg, node, path)
    if cfg.probe:
        from rig.models.contact import parse_indenter

        try:
            parse_indenter(cfg.probe)
        except SpecError as exc:
            child = node.value["probe"]
            raise SpecError(exc.message, path=path, line=child.line, column=child.column,
                            field="probe") from None
    cfg.source_text = text
    cfg.source_path = path
    return cfg


def _check_force_limit(cfg: RigConfig, node, path: str) -> None:
    """A force limit beyond the load cell's range: the cell reads over range first, and the
    limit never acts (with `.inf` a protocol drove the probe until the cell read 500 N)."""
    if cfg.loadcell.backend == "none" or cfg.limits.max_force_N <= cfg.loadcell.max_abs_N:
        return
    key = "limits.max_force_N"
    child = _child(node, "limits", "max_force_N")
    if child is None:  # the default limit, the cell's range set below it
        key, child = "loadcell.max_abs_N", _child(node, "loadcell", "max_abs_N") or node
    raise SpecError(f"a force limit of {cfg.limits.max_force_N:g} N is beyond the load cell's range "
                    f"(loadcell.max_abs_N {cfg.loadcell.max_abs_N:g} N): the cell cannot read the limit",
                    path=path, line=child.line, column=child.column, field=key)


def _child(node, *keys: str):
    """The node at `keys` in a mapping, or None."""
    for key in keys:
        if not isinstance(node.value, dict) or key not in node.value:
            return None
        node = node.value[key]
    return node


def _check_material(cfg: RigConfig, node, path: str) -> None:
    """The simulated material's indenter and moduli, where the file gives them."""
    mat = cfg.sim.tissue.material
    if mat is None:
        return
    from rig.sim.material import parse_geometry

    where = node
    for key in ("sim", "tissue", "material"):
        where = where.value[key] if isinstance(where.value, dict) and key in where.value else where
    problem = ""
    try:
        parse_geometry(mat.indenter)
    except ValueError as exc:
        problem, key = str(exc), "indenter"
    if not problem and mat.beta == 0 and mat.E_inf_Pa > mat.E0_Pa:
        problem, key = (f"E_inf_Pa ({mat.E_inf_Pa:g}) is above E0_Pa ({mat.E0_Pa:g}): a relaxation modulus "
                        "falls from E0 to E_inf"), "E_inf_Pa"
    if problem:
        child = where.value.get(key, where) if isinstance(where.value, dict) else where
        raise SpecError(problem, path=path, line=child.line, column=child.column,
                        field=f"sim.tissue.material.{key}")


def _refuse_keys(node, keys: tuple[str, ...], path: str) -> None:
    if isinstance(node.value, dict):
        for k in keys:
            if k in node.value:
                child = node.value[k]
                raise SpecError(f"unknown key '{k}'", path=path, line=child.key_line,
                                column=child.key_column)
