"""Run one trial from the command line: config, protocol, devices, clock, progress, Ctrl-C."""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from rig.clock import RealClock, VirtualClock
from rig.control.devices import Devices, open_devices
from rig.control.states import Lifecycle, StopMode
from rig.control.trial import Snapshot, Trial, TrialResult, default_log_path
from rig.errors import RigError
from rig.recording.recorder import TrialInfo
from rig.specs.config import RigConfig
from rig.specs.protocol import Protocol, plan
from rig.views.progress import ProgressBar


@dataclass
class RunOptions:
    """How `run_trial` runs one trial beyond its protocol and config: who and what for the log's
    header (specimen, operator, notes, dimensions), where the log goes, the clock's speed,
    the progress line, what to publish live or spy on, a saved model for the loop, and the
    callbacks a caller (the daemon, a test) hooks into the loop."""

    specimen: str = "specimen"
    operator: str = ""
    notes: str = ""
    out_dir: str | None = None
    speed: float = 1.0  # 1 = real time on the real clock; 0 = as fast as possible
    progress: bool = True
    log_path: Path | None = None
    # Called every tick on the loop thread: must not block (no terminal, socket or disk).
    on_tick: Callable[[Snapshot], None] | None = None
    on_start: Callable[[Trial, Devices], None] | None = None  # after the devices open
    live_port: int | None = None  # publish live on this port (Foxglove WebSocket), None = off
    model_path: str | None = None  # a saved model to run in the loop (default: the config's `model:`)
    spy_path: str | None = None  # write every frame and line on the wire here (`rig spy` reads it)
    # the specimen's thickness and area for the log's header (rig.specs.specimen.dimensions)
    dimensions: dict[str, str] = field(default_factory=dict)


def run_trial(proto: Protocol, config: RigConfig, opts: RunOptions, *, warn=None) -> TrialResult:
    """Open the devices, run the protocol, close the devices; Ctrl-C aborts safely.

    The protocol's limits are checked again from where the slider actually is before
    anything moves (`LimitError`). `warn` gets each warning about the rig (stderr by default).
    """
    from rig.models.saved import model_for_run

    model = model_for_run(config, opts.model_path)
    clock = RealClock(config.loop.spin_ms / 1000.0) if opts.speed == 1.0 else VirtualClock(opts.speed)
    if opts.speed != 1.0 and config.slider.backend != "sim":
        raise RigError("--speed other than 1 needs the simulated rig (slider.backend: sim)")
    with open_devices(config, clock, speed=opts.speed, spy_path=opts.spy_path) as devices:
        return _run_on(devices, proto, config, clock, opts, warn, model)


def _run_on(devices: Devices, proto: Protocol, config: RigConfig, clock, opts: RunOptions, warn,
            model) -> TrialResult:
    """`run_trial` once its devices are open (they are closed by the caller, however this ends)."""
    for w in devices.warnings:
        (warn or _stderr)(w)
    log_path = opts.log_path or default_log_path(opts.out_dir or config.recorder.out_dir, proto,
                                                 opts.specimen)
    clock_name = "real" if opts.speed == 1.0 else f"virtual x{opts.speed:g}" if opts.speed else "virtual"
    info = TrialInfo(specimen=opts.specimen, operator=opts.operator, notes=opts.notes,
                     clock=clock_name, extra={"devices": devices.description, "backstop": devices.backstop,
                                              "warnings": " | ".join(devices.warnings), **opts.dimensions})
    trial = Trial(proto, config, devices.slider, devices.loadcell, clock, log_path, info, model=model)
    bar = ProgressBar(plan(proto, config).duration_s, lambda: trial.snapshot) if opts.progress else None
    trial.on_tick = opts.on_tick
    live = None
    if opts.live_port is not None:
        from rig.service.live import LiveView

        host = config.daemon.live.host if config.daemon.live is not None else "127.0.0.1"
        live = LiveView(host, opts.live_port)
        trial.live = live
        (warn or _stderr)(f"live view: {live.url} (Foxglove: open connection, Foxglove WebSocket)")
    for w in trial.warnings:
        (warn or _stderr)(w)
    if opts.on_start is not None:
        opts.on_start(trial, devices)
    notices = CtrlCNotices(trial, warn or _stderr)
    old = signal.signal(signal.SIGINT, sigint_handler(trial)) if _main_thread() else None
    old_switch = sys.getswitchinterval()
    # The writer thread must not hold the GIL for the default 5 ms while a tick waits.
    sys.setswitchinterval(0.0005)
    try:
        if bar:
            bar.start()
        notices.start()
        return trial.run()
    finally:
        sys.setswitchinterval(old_switch)
        if old is not None:
            signal.signal(signal.SIGINT, old)
        notices.stop()
        if bar:
            bar.close()
        if live is not None:
            live.close()


def sigint_handler(trial: Trial) -> Callable:
    """First Ctrl-C: abort and retract; second: stop the motor now.

    The handler runs on the main thread between two bytecodes, possibly while the loop (the
    same thread) holds a lock or a stream's buffer: it only assigns an attribute, which the
    loop reads on its next tick. No lock, no Event, no print.
    """
    def on_sigint(signum, frame) -> None:
        trial.signal_stop = StopMode.ABORT if trial.signal_stop is None else StopMode.ESTOP

    return on_sigint


class CtrlCNotices:
    """Tells the operator what a Ctrl-C does, from a thread of its own (the handler must not
    print). While the loop ticks, it carries the Ctrl-C out; while the trial starts or closes
    its log, this thread sends the stop at once; after the trial, the slider gets a STOP."""

    def __init__(self, trial: Trial, say: Callable[[str], None]) -> None:
        self.trial = trial
        self.say = say
        self._told: StopMode | None = None
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ctrl-c notices", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._done.wait(0.02):
            self._tell()

    def _tell(self) -> None:
        mode = self.trial.signal_stop
        if mode is self._told:
            return
        self._told = mode
        self.say("\nabort: stopping, then returning to the start position (Ctrl-C again stops the "
                 "motor at once)" if mode is StopMode.ABORT else "\nemergency stop")
        if self.trial.lifecycle is not Lifecycle.RUNNING:  # no tick to read the flag: stop from here
            ticket = self.trial.request_stop(mode, user="console")
            if ticket.trial_over:
                try:
                    self.trial.slider.stop()
                except RigError as exc:  # the drive's communication timeout is the backstop
                    self.say(f"STOP not sent: {exc}")

    def stop(self) -> None:
        self._done.set()
        if self._thread.is_alive():
            self._thread.join(1.0)
        self._tell()


def _stderr(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()
