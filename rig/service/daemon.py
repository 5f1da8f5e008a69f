"""`rig daemon`: owns the slider and load cell and runs one trial at a time for its clients.

Control is a Unix-domain socket (`control_socket.py`: mode 0660, the peer checked by
`peers.py`), no network listener. The protocol is JSON lines: one request, one reply; `watch`
streams status lines until the trial ends. The peer user is recorded with the starts and
stops it makes.

Requests: {"cmd": "ping"}, {"cmd": "status"}, {"cmd": "logs"},
{"cmd": "start", "protocol_text": ..., "protocol_path": ..., "specimen": ..., "operator": ..., "notes": ...},
{"cmd": "stop", "mode": "abort" | "hold"}, {"cmd": "estop"}, {"cmd": "reset_alarm"},
{"cmd": "return"}, {"cmd": "watch", "rate_Hz": 10}.
Replies carry "ok": true, or "ok": false with "error". Every field is checked before it is
used: a field of the wrong type (a `rate_Hz` that is not a number > 0, a `mode` or a
`specimen` that is not a string) is refused with an error naming it and what is expected.
`rate_Hz` is clamped to 0.5-100 updates per second. Specimen and operator names are text
without control characters; where a name becomes part of a file name (a campaign's folder, a
trial's log) it is reduced to letters, digits, `-` and `_` (`rig.recording.names`), so every
file the daemon writes lies inside its log folder.

Stops latch. `stop` and `estop` take the state lock, count one more stop (a generation
number), set the running campaign's stop, and note what they cut: the trial that owns the
devices, the starts being set up, a campaign between trials. A start, and each trial of a
campaign, notes the generation when it begins (a campaign: when it was started) and checks it
again under the state lock right before it hands the devices to its trial: if a stop came in
between, or one is still being carried out, it is cancelled before anything moves, and its
reply (or the campaign's journal) says which stop cancelled it. A trial handed its devices
before the stop gets the stop itself (before its first tick it sends the STOP at once and ends
on that tick without moving). So no trial starts after a stop that was acknowledged, whatever
it met. The latch cancels only what was under way when it came: a start that arrives after the
stop is answered starts normally (the latch never has to be cleared).

A trial cut short by an estop or a fault leaves the probe where it stopped, which may be in the
specimen. The daemon keeps where (the depth below the surface the trial's contact watch saw, the
force, the trial that left it), and the next start, or campaign, is refused while the probe is
still below that surface: its reply says so and offers the two ways on, `{"cmd": "return"}`
(`rig return`: back to where that trial started, watched as any move) or the start again with
`"from_contact": true` (`rig start --from-contact`: run from here, the operator's confirmation).
`status` carries it as "probe_in_contact" until the probe is out.

A start may give the specimen's dimensions, `"thickness_mm"` and `"area_mm2"` (positive numbers;
`rig start --thickness-mm --area-mm2`): the log's header keeps them (rig.specs.specimen).

A stop or estop is answered once the STOP has gone out on the bus and the drive acknowledged
it; "ok": false says it did not. With a trial running, the trial sends it (from its loop's next
tick, or at once while it starts or closes); otherwise the daemon sends it itself on the idle
devices (a stop with nothing to stop is refused: "no trial is running"). The state lock is
only ever held for bookkeeping, never across a bus transaction, a protocol's parsing or a
trial's set-up, so a stop never waits behind a slow start. The reply says whether a trial was
running, which starts being set up were cancelled, whether the campaign ends, and whether the
drive acknowledged the STOP: "message" in words (what `rig stop` and `rig estop` print), and
"trial_running", "cancelled" (what was being set up), "campaign_ends" and "acknowledged".
"""

from __future__ import annotations

import contextlib
import grp
import itertools
import json
import math
import os
import signal
import socket
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from rig import __version__
from rig.clock import RealClock
from rig.control.devices import Devices, open_devices
from rig.control.manual import move_on
from rig.control.states import Lifecycle, StopMode
from rig.control.trial import EndPlace, Snapshot, Trial, TrialResult, default_log_path
from rig.errors import RigError
from rig.recording.names import file_part, inside
from rig.recording.recorder import TrialInfo
from rig.recording.recovery import end_journal, find_open_journals, find_unfinished, list_trials, recover
from rig.service.control_socket import ControlSocket, private_dir, send
from rig.service.sdnotify import Watchdog, healthy, notify, watchdog_interval_s
from rig.specs.config import RigConfig
from rig.specs.protocol import check_limits, parse_protocol

RETURN_SPEED_MM_S = 5.0  # `rig return`, as a stopped trial's return (under the rig's speed limit)
LOG_NAMED_S = 5.0  # a start waits this long at most for its log to be named
HAND_OVER_S = 2.0  # a start waits this long at most for the devices (a status read holds them briefly)
STOP_SENT_S = 1.0  # a stop waits this long at most for the STOP to go out
MAX_NAME_CHARS = 200  # a specimen or operator name; the log's file name keeps fewer of them


def default_socket_path(config: RigConfig | None = None) -> Path:
    """The daemon's socket: the config's daemon.socket, $RIG_SOCKET, /run/rig/rigd.sock as root,
    $XDG_RUNTIME_DIR/rig/rigd.sock, else a private folder of the user's in the temporary directory."""
    if config is not None and config.daemon.socket:
        return Path(config.daemon.socket)
    if env := os.environ.get("RIG_SOCKET"):
        return Path(env)
    if os.geteuid() == 0:
        return Path("/run/rig/rigd.sock")
    if runtime := os.environ.get("XDG_RUNTIME_DIR"):
        return Path(runtime) / "rig" / "rigd.sock"
    # A shared temporary directory: whoever made rig-UID first owns it, so it must be ours and
    # closed to others, or another user could serve a socket of their own in its place.
    fallback = private_dir(Path(tempfile.gettempdir()) / f"rig-{os.geteuid()}")
    return fallback / "rig" / "rigd.sock"


class RequestError(Exception):
    """A request the daemon refuses; the message goes back to the client."""


# ---------------------------------------------------------------------- request fields
def _shown(value: object) -> str:
    """A value as the client sent it (JSON), cut short."""
    text = json.dumps(value, default=str)
    return text if len(text) <= 60 else text[:57] + "..."


def _text(req: dict, key: str, default: str) -> str:
    """A text field: absent, null or empty gives `default`; anything but a string is refused."""
    value = req.get(key)
    if value is None:
        return default
    if not isinstance(value, str):
        raise RequestError(f'"{key}" must be a string, not {_shown(value)}')
    return value or default


def _name(req: dict, key: str, default: str) -> str:
    """A specimen's or an operator's name: text of at most MAX_NAME_CHARS, without control
    characters (a NUL or a newline would garble the log list, and has no place in a name)."""
    value = _text(req, key, default)
    if any(ord(c) < 0x20 or 0x7F <= ord(c) < 0xA0 for c in value):
        raise RequestError(f'"{key}" must be printable text (no NUL, newline or other control '
                           f"character), not {_shown(value)}")
    if len(value) > MAX_NAME_CHARS:
        raise RequestError(f'"{key}" must be at most {MAX_NAME_CHARS} characters, not {len(value)}')
    return value


def _flag(req: dict, key: str) -> bool:
    """A yes-or-no field: absent or null is no; anything but true or false is refused."""
    value = req.get(key)
    if value is None:
        return False
    if not isinstance(value, bool):
        raise RequestError(f'"{key}" must be true or false, not {_shown(value)}')
    return value


# ---------------------------------------------------------------------- the probe left in contact
CUT_SHORT = {"estopped": "the estop", "fault": "the fault"}  # outcomes that leave the probe where it stopped


def _left_in_contact(trial: Trial, result: TrialResult, tolerance_mm: float) -> dict | None:
    """Where a trial cut short left the probe, when that is in the specimen: below the surface its
    contact watch last saw, and pressing on it. None otherwise (a trial that completed, or was
    stopped and returned, or held at the operator's word: `rig stop --hold`)."""
    end: EndPlace | None = trial.end_place
    if result.outcome not in CUT_SHORT or end is None or not end.in_contact or end.depth_mm <= tolerance_mm:
        return None
    # back to where the trial started, or to the surface if it started below it (a preload)
    start = trial._start_mm if trial._start_mm is not None else end.surface_mm
    return {"depth_mm": round(end.depth_mm, 4), "position_mm": round(end.position_mm, 4),
            "surface_mm": round(end.surface_mm, 4), "force_N": round(end.force_N, 4),
            "return_to_mm": round(min(start, end.surface_mm), 4), "protocol": trial.proto.name,
            "by": f"{CUT_SHORT[result.outcome]} of trial '{trial.proto.name}' at {time.strftime('%H:%M:%S')}",
            "log": str(result.log_path)}


def _where(left: dict) -> str:
    return (f"{left['depth_mm']:.2f} mm into the specimen (the slider at {left['position_mm']:.3f} mm, the "
            f"surface at {left['surface_mm']:.3f} mm, {left['force_N']:.3g} N), where {left['by']} left it")


def _dimensions(req: dict) -> dict[str, str]:
    """The specimen's thickness and area of a start request ("thickness_mm", "area_mm2": positive
    numbers, or absent), as the log's header keeps them."""
    from rig.specs.specimen import KEYS, dimensions

    values = {}
    for key in KEYS:
        value = req.get(key)
        if value is not None and (_number(value) is None or value <= 0):
            raise RequestError(f'"{key}" must be a positive number, not {_shown(value)}')
        values[key] = value
    return dimensions(values["thickness_mm"], values["area_mm2"])


def _number(value: object) -> float | None:
    """A JSON number as a float (a finite one), else None; true and false are not numbers."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


# ---------------------------------------------------------------------- the stop latch
@dataclass
class _SetUp:
    """A start, or a campaign's trial, between its request and the moment its trial is handed
    the devices: checked, its Trial built, nothing moved yet."""

    id: int
    what: str  # as a reply names it: "the start of 'demo' (specimen pig-07, by ann)"
    gen: int  # the stop generation when it began: any later stop cancels it
    moves: bool = False  # it moves the slider itself (`rig return`): a stop stops it where it is


@dataclass
class _Cut:
    """What a stop or estop found when it latched (under the state lock)."""

    trial: Trial | None  # the trial that owns the devices, if one had not ended
    protocol: str
    cancelled: list[str] = field(default_factory=list)  # starts being set up: now cancelled
    campaign: bool = False  # a campaign was running: it starts no further trial
    moves_stopped: list[str] = field(default_factory=list)  # the daemon's own moves (a return): stopped

    def notes(self, trial_running: bool) -> list[str]:
        out = [f"{what} was cancelled: nothing moved" for what in self.cancelled]
        out += [f"{what} was stopped where it stood" for what in self.moves_stopped]
        if self.campaign:
            out.append("the campaign ends with this trial" if trial_running else
                       "the campaign ends before its next trial (the probe stays where it is)")
        return out


def _joined(head: str, notes: list[str]) -> str:
    return "; ".join([head, *notes])


class Daemon:
    """The rig's controller as a service: it owns the devices, takes start, stop and status
    requests on a Unix socket (`rig start`, `rig stop`, `rig status`), runs one trial at a time
    on its own thread, and keeps what the next trial needs (the load cell's free-air zero). A
    stop never waits for a lock held across a bus transaction."""

    def __init__(self, config: RigConfig, socket_path: Path | None = None, *, log=sys.stderr,
                 spy_path: str | None = None) -> None:
        self.config = config
        self.spy_path = spy_path  # every frame and line on the wire, for as long as the daemon runs
        self.socket_path = Path(socket_path or default_socket_path(config))
        self.out_dir = Path(config.recorder.out_dir).resolve()
        self.log = log
        self.group_gid = grp.getgrnam(config.daemon.group).gr_gid if config.daemon.group else None
        self.devices: Devices | None = None
        self.dev_lock = threading.Lock()  # held by the trial thread for a whole trial
        # Bookkeeping only (who runs, what is set up, the stop latch): never held across a bus
        # transaction or a slow check, so a stop always gets it at once.
        self.state_lock = threading.Lock()
        self.trial: Trial | None = None
        self.trial_thread: threading.Thread | None = None
        self.trial_meta: dict = {}
        self.zero = None  # the load cell's free-air zero the last trial used: the next one counts from it
        self.left_in: dict | None = None  # where a trial cut short left the probe in contact (docstring)
        self.last: dict | None = None
        self.beat: float | None = None
        self.recovered: list[str] = []
        self._stop = threading.Event()
        self.server = ControlSocket(self.socket_path, self._dispatch, group_gid=self.group_gid,
                                    max_request_bytes=config.daemon.max_request_bytes, say=self.say)
        self.watchdog: Watchdog | None = None
        self.live = None  # rig.service.live.LiveView when daemon.live is configured
        self.campaign: dict = {}  # the campaign running (rig start --characterize), its last word
        self.campaign_thread: threading.Thread | None = None
        self.campaign_stop: threading.Event | None = None
        # The stop latch (module docstring), under state_lock.
        self.stop_gen = 0  # stops and estops so far
        self.stops_in_progress = 0  # latched and not yet answered: no trial is handed the devices
        self.last_stop = ""  # "an estop from ann at 14:02:11": what a cancelled start is told
        self.campaign_gen = 0  # the generation when the campaign started
        self.setting_up: dict[int, _SetUp] = {}
        self._setup_ids = itertools.count(1)

    def say(self, msg: str) -> None:
        print(f"rigd: {msg}", file=self.log, flush=True)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Listen, open the devices, then recover crashed logs; READY=1 for systemd.

        In this order: a second daemon finds the socket (or the devices) taken before it
        touches a log, and the logs left unfinished are recovered only by the owner of both."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.server.listen()
        try:
            self.devices = open_devices(self.config, RealClock(self.config.loop.spin_ms / 1000.0), speed=1.0,
                                        spy_path=self.spy_path,
                                        holder_note=f"a rig daemon serving {self.socket_path}")
        except BaseException:
            self.server.close()
            raise
        self._recover_logs()
        self.say(f"devices: {self.devices.description}")
        if self.config.daemon.live is not None:
            from rig.service.live import LiveView

            lv = self.config.daemon.live
            try:
                self.live = LiveView(lv.host, lv.port, max_queue=lv.max_queue)
            except BaseException:
                self.devices.close()
                self.server.close()
                raise
            self.say(f"live view: {self.live.url} (Foxglove: open connection, Foxglove WebSocket)")
        self.say(f"listening on {self.socket_path}")
        interval = watchdog_interval_s()
        if interval:
            self.watchdog = Watchdog(interval, self._healthy).start()
        notify(f"READY=1\nSTATUS=idle; socket {self.socket_path}")

    def _recover_logs(self) -> None:
        """The logs a crash left unfinished (in the log folder and its campaigns' folders), then
        the campaigns it left without an end: their journals get one saying they were
        interrupted, and status reports the newest (`campaign`, and `recovered`)."""
        in_use: list[Path] = []
        for path in find_unfinished(self.out_dir, in_use=in_use):
            try:
                recover(path)
                self.recovered.append(str(path))
                self.say(f"recovered interrupted trial log {path}")
            except RigError as exc:
                self.say(f"could not recover {path}: {exc}")
        for path in find_open_journals(self.out_dir, in_use=in_use):
            try:
                ended = end_journal(path)
            except (RigError, OSError) as exc:
                self.say(f"could not end the campaign journal {path}: {exc}")
                continue
            self.recovered.append(str(path))
            self.say(f"campaign of specimen {ended.specimen} {ended.reason}; its journal {path} now ends so")
            started = time.strftime("%H:%M:%S", time.localtime(ended.started_t)) if ended.started_t else "?"
            by = next((e.requested_by for e in list_trials(path.parent) if e.requested_by), "?")
            self.campaign = {"specimen": ended.specimen, "user": by, "started": started,
                             "phase": "ended: interrupted (found at the daemon's start)",
                             "trials": ended.trials, "status": "interrupted", "reason": ended.reason,
                             "journal": str(path)}
        for path in in_use:
            self.say(f"left {path} alone: another process is writing it")

    def _busy(self) -> bool:
        return self._trial_running() or self._campaign_running()

    def _trial_running(self) -> bool:
        return self.trial is not None and self.trial_thread is not None and self.trial_thread.is_alive()

    def _campaign_running(self) -> bool:
        return self.campaign_thread is not None and self.campaign_thread.is_alive()

    def _healthy(self) -> bool:
        t = self.trial
        running = t is not None and t.snapshot.state.active
        return healthy(time.monotonic(), self.beat, running, self.config.daemon.stall_s)

    def serve_forever(self) -> None:
        try:
            self.server.serve(self._stop)
        finally:
            self.shutdown()

    def request_shutdown(self) -> None:
        self._stop.set()

    def shutdown(self) -> None:
        notify("STOPPING=1")
        with self.state_lock:  # nothing being set up starts now
            self.stop_gen += 1
            self.last_stop = "the daemon's shutdown"
            if self.campaign_stop is not None:
                self.campaign_stop.set()
            t = self.trial
        if self._trial_running():
            self.say("stopping the running trial before shutting down")
            t.request_stop(StopMode.ABORT, user="rigd shutdown")
            self.trial_thread.join(120.0)
        if self._campaign_running():
            self.campaign_thread.join(120.0)
        if self.watchdog:
            self.watchdog.stop()
        self.server.close()
        if self.devices:
            self.devices.close()
            self.devices = None
        if self.live is not None:
            self.live.close()
            self.live = None

    # ------------------------------------------------------------------ dispatch
    def _dispatch(self, conn: socket.socket, req: dict, user: str, received: float) -> bool:
        cmd = req["cmd"]
        handler = getattr(self, f"cmd_{cmd}", None)
        if handler is None:
            known = sorted(n[4:] for n in dir(self) if n.startswith("cmd_"))
            return send(conn, {"ok": False, "error": f"unknown command '{cmd}' (known: {', '.join(known)})"})
        if cmd == "watch":
            return self.cmd_watch(conn, req)
        try:
            reply = handler(req, user, received)
        except (RequestError, RigError) as exc:
            reply = {"ok": False, "error": str(exc)}
        return send(conn, reply)

    # ------------------------------------------------------------------ commands
    def cmd_ping(self, req: dict, user: str, received: float) -> dict:
        return {"ok": True, "version": __version__, "user": user}

    def cmd_status(self, req: dict, user: str, received: float) -> dict:
        t = self.trial
        running = self._trial_running()
        out: dict = {"ok": True, "state": "running" if running else "idle", "last": self.last,
                     "recovered": self.recovered}
        if self.campaign:
            out["campaign"] = dict(self.campaign)
            if self._campaign_running() and not running:
                out["state"] = "characterizing"
        if running:
            snap = t.snapshot
            # the log's name as the recorder took it (another run may have had the one planned)
            out.update(snapshot=asdict(snap), trial={**self.trial_meta, "log": str(t.log_path)})
            if snap.fault:
                out["state"] = "fault"
        else:
            out["snapshot"] = self._idle_snapshot()
        if self.left_in is not None:
            out["probe_in_contact"] = dict(self.left_in)
        return out

    def _idle_snapshot(self) -> dict | None:
        """Position and force read directly while no trial owns the devices."""
        if not self.dev_lock.acquire(timeout=0.2):
            return None
        try:
            pos = self.devices.slider.read_position_mm()
            status = self.devices.slider.read_status()
            cell = self.devices.loadcell
            r = cell.latest() if cell is not None else None
            return {"position_mm": pos, "force_N": r.force_N if r else None,
                    "alarm_code": status.alarm_code, "moving": status.moving}
        except RigError as exc:
            return {"error": str(exc)}
        finally:
            self.dev_lock.release()

    def cmd_logs(self, req: dict, user: str, received: float) -> dict:
        return {"ok": True, "trials": [e.as_dict() for e in list_trials(self.out_dir)]}

    def _refuse_if_busy(self) -> None:
        """The caller holds state_lock."""
        if self._campaign_running():
            c = self.campaign
            raise RequestError(f"busy: characterizing specimen {c['specimen']} (started by {c['user']} at "
                               f"{c['started']}; {c['phase']}); `rig stop` ends it")
        if self._trial_running():
            m = self.trial_meta
            raise RequestError(f"busy: trial '{m['protocol']}' (specimen {m['specimen']}, started "
                               f"by {m['user']} at {m['started']}) is running; log {m['log']}")
        if self.setting_up:
            what = next(iter(self.setting_up.values())).what
            raise RequestError(f"busy: {what} is being set up")

    # ------------------------------------------------------------------ set-up and hand-over
    def _begin_setup(self, what: str, gen: int | None = None, moves: bool = False) -> _SetUp:
        """The caller holds state_lock. `gen`: the generation the set-up answers to (a campaign's
        trial: the campaign's), else now's."""
        setup = _SetUp(next(self._setup_ids), what, self.stop_gen if gen is None else gen, moves)
        self.setting_up[setup.id] = setup
        return setup

    def _end_setup(self, setup: _SetUp) -> None:
        with self.state_lock:
            self.setting_up.pop(setup.id, None)

    def _hand_over(self, setup: _SetUp, trial: Trial, meta: dict,
                   thread: threading.Thread | None = None) -> str | None:
        """Give the devices to `trial`, unless a stop came since `setup` began (or one is being
        carried out): then nothing is handed over and the reason is returned. With `thread`, it
        is started to run the trial; without, the calling thread runs it (a campaign's)."""
        if not self.dev_lock.acquire(timeout=HAND_OVER_S):
            raise RequestError(f"the devices stayed busy for {HAND_OVER_S:g} s (a status read or a stop); "
                               "not starting; try again")
        with self.state_lock:
            self.setting_up.pop(setup.id, None)
            if self.stop_gen == setup.gen and not self.stops_in_progress:
                self.trial = trial
                self.trial_meta = meta
                self.trial_thread = thread or threading.current_thread()
                self.beat = time.monotonic()
                if thread is not None:
                    thread.start()
                return None
            why = self.last_stop
        self.dev_lock.release()
        return why

    def cmd_start(self, req: dict, user: str, received: float) -> dict:
        if req.get("characterize") is not None:
            return self._start_campaign(req, user)
        text = req.get("protocol_text")
        if not isinstance(text, str) or not text.strip():
            raise RequestError('start needs "protocol_text" (the protocol file\'s contents)')
        path = _text(req, "protocol_path", "<protocol>")
        specimen = _name(req, "specimen", "specimen")
        operator = _name(req, "operator", user)
        notes = _text(req, "notes", "")
        size = _dimensions(req)
        from_contact = _flag(req, "from_contact")
        with self.state_lock:
            self._refuse_if_busy()
            setup = self._begin_setup(f"the start of a trial (specimen {specimen}, by {user})")
        try:
            proto = parse_protocol(text, path)  # SpecError -> error reply
            setup.what = f"the start of '{proto.name}' (specimen {specimen}, by {user})"
            # From where the slider is now: the trial's zero is there, not at 0.
            here = self._read_position()
            in_contact = self._in_contact(here, from_contact)  # RequestError while it is, unconfirmed
            check_limits(proto, self.config, start_mm=here)  # LimitError -> error reply
            log_path = inside(self.out_dir, default_log_path(self.out_dir, proto, specimen))
            trial = self._new_trial(proto, specimen, operator, notes, user, log_path, self._model(req), size)
            warnings = [*in_contact, *self.devices.warnings, *trial.warnings]
            meta = {"protocol": proto.name, "specimen": specimen, "user": user, "operator": operator,
                    "log": str(log_path), "started": time.strftime("%H:%M:%S")}
            thread = threading.Thread(target=self._run_trial, args=(trial,), name="trial", daemon=True)
            why = self._hand_over(setup, trial, meta, thread)
        finally:
            self._end_setup(setup)
        if why is not None:
            self.say(f"{user}'s start of '{proto.name}' cancelled: {why} arrived while it was set up")
            raise RequestError(f"not started: {why} arrived while the trial was being set up; "
                               "it was cancelled before anything moved")
        # the recorder may take the next free name (a log of the same second exists): the reply
        # names the file this trial writes, never an earlier one
        trial.log_named.wait(LOG_NAMED_S)
        log_path = trial.log_path
        if trial.recorder is None and trial.log_named.is_set():
            # it ended before opening its log (a limit from where the slider stands, the first
            # position read, the log's folder): the truth is that it did not start
            thread.join(LOG_NAMED_S)
            why = (self.last or {}).get("error", "it ended at once")
            raise RequestError(f"the trial did not start: {why}")
        with self.state_lock:
            if self.trial is trial:
                self.trial_meta["log"] = str(log_path)
            if self.stop_gen != setup.gen:  # handed over, then stopped: the trial carries it out
                warnings.append(f"{self.last_stop} came as the trial started: the trial carries it out")
        self.say(f"{user} started '{proto.name}' (specimen {specimen}) -> {log_path}")
        for w in warnings:
            self.say(w)
        notify(f"STATUS=running '{proto.name}'")
        return {"ok": True, "log": str(log_path), "protocol": proto.name, "warnings": warnings}

    # ------------------------------------------------------------------ campaigns
    def _start_campaign(self, req: dict, user: str) -> dict:
        """`rig start --characterize`: the campaign in a thread of its own; each of its trials runs
        on the daemon's devices like a started one (status, watch, stop and estop reach it)."""
        from rig.service.characterize import Request

        opts = req.get("characterize")
        if not isinstance(opts, dict):
            raise RequestError('"characterize" must be an object of options (max_trials, budget_min, ...)')
        specimen = _name(req, "specimen", "specimen")
        text = req.get("protocol_text") or None
        if text is not None:
            if not isinstance(text, str):
                raise RequestError('"protocol_text" must be the protocol file\'s contents')
            parse_protocol(text, _text(req, "protocol_path", "<protocol>"))  # refused here, not later
        _name(req, "operator", user)  # checked now: each trial takes it
        from_contact, in_contact = _flag(req, "from_contact"), []
        if self.left_in is not None:  # where the probe is, read only when a trial left it in contact
            with self.state_lock:
                self._refuse_if_busy()  # a running trial's devices are not free to read
            in_contact = self._in_contact(self._read_position(), from_contact)
        kw = {}
        for name in ("max_trials", "budget_min", "target_rse", "rest_s"):
            if opts.get(name) is None:
                continue
            value = _number(opts[name])
            if name == "max_trials":
                if value is None or value < 1 or not value.is_integer():
                    raise RequestError(f'characterize "{name}" must be a whole number >= 1, '
                                       f"not {_shown(opts[name])}")
                kw[name] = int(value)
            elif value is None or value < 0:
                raise RequestError(f'characterize "{name}" must be a number >= 0, not {_shown(opts[name])}')
            else:
                kw[name] = value
        model = _text(opts, "model", "proposed")
        indenter = _text(opts, "indenter", "") or None
        # The specimen's name is text; the campaign's folder, journal and logs are named from
        # its file-name form, inside the log folder (characterize names them from Request.specimen).
        stem = file_part(specimen, default="specimen")
        out = inside(self.out_dir, self.out_dir / f"characterize-{stem}")
        warnings = [*in_contact, *self.devices.warnings]
        if stem != specimen:
            warnings.append(f"specimen {specimen!r} is not a file name: the campaign's folder, journal and "
                            f"logs are named '{stem}' ({out})")
        with self.state_lock:
            self._refuse_if_busy()
            self.campaign_stop = threading.Event()
            self.campaign_gen = self.stop_gen
            request = Request(stem, self.config, out, model=model, indenter=indenter, first_text=text,
                              speed=1.0, say=self.say,
                              runner=lambda proto, n, log: self._campaign_trial(proto, n, log, req, user),
                              stop=self.campaign_stop, on_event=self._campaign_event, **kw)
            self.campaign = {"specimen": specimen, "user": user, "started": time.strftime("%H:%M:%S"),
                             "phase": "starting", "trials": 0, "status": "running", "journal": None}
            self.campaign_thread = threading.Thread(target=self._run_campaign, args=(request,),
                                                    name="campaign", daemon=True)
            self.campaign_thread.start()
        self.say(f"{user} started characterizing specimen {specimen} -> {out}")
        notify(f"STATUS=characterizing {specimen}")
        return {"ok": True, "characterize": specimen, "out": str(out), "warnings": warnings}

    def _run_campaign(self, request) -> None:
        from rig.service.characterize import characterize

        try:
            camp = characterize(request)
            self.campaign.update(status=camp.status, reason=camp.reason, phase=f"ended: {camp.status}",
                                 journal=str(camp.journal))
            self.say(f"campaign {camp.status}: {camp.reason}; journal {camp.journal}")
            self.last = {**(self.last or {}), "campaign": camp.summary()}
        except BaseException as exc:  # noqa: BLE001 - the daemon must outlive a failed campaign
            self.campaign.update(status="error", reason=f"{type(exc).__name__}: {exc}", phase="ended: error")
            self.say(f"campaign failed: {exc}")
        finally:
            notify("STATUS=idle")

    def _campaign_event(self, event: str, data: dict) -> None:
        """Each journal event: the campaign's phase for status and watch, and the live view's
        event channel (the decisions beside the trial's samples)."""
        phase = {"trial": lambda: f"trial {data.get('n')}: {data.get('protocol')} ({data.get('why')})",
                 "fit": lambda: f"fitted {data.get('trials')} trials: {data.get('model')}"
                                f"{'' if data.get('adequate') else ' (not adequate)'}",
                 "decision": lambda: f"decided: {data.get('kind')}"}.get(event)
        if phase is not None:
            self.campaign["phase"] = phase()
        if event == "trial":
            self.campaign["trials"] = data.get("n", 0)
        if event == "start":
            self.campaign["journal"] = data.get("journal")
        if self.live is not None and event != "start":
            from rig.recording.messages import EVENT

            text = self.campaign["phase"] if phase is not None else event
            self.live.put(EVENT.topic, time.time_ns(),
                          EVENT.record(t_s=0.0, kind=f"characterize {event}", message=text,
                                       data={k: v for k, v in data.items() if k != "yaml"}))

    def _campaign_trial(self, proto, n: int, log_path: Path, req: dict, user: str) -> TrialResult:
        """One trial of the campaign, on this thread, with the devices held for its whole length;
        cancelled before anything moves (outcome "cancelled", no log) if a stop came since the
        campaign started."""
        specimen = self.campaign["specimen"]
        operator = _name(req, "operator", user)
        with self.state_lock:
            setup = self._begin_setup(f"the campaign's trial {n} ('{proto.name}', specimen {specimen})",
                                      gen=self.campaign_gen)
        try:
            inside(self.out_dir, log_path)
            check_limits(proto, self.config, start_mm=self._read_position())
            trial = self._new_trial(proto, specimen, operator, f"characterize trial {n}", user, log_path, None)
            meta = {"protocol": proto.name, "specimen": specimen, "user": user, "operator": operator,
                    "log": str(log_path), "started": time.strftime("%H:%M:%S"),
                    "campaign": f"characterize trial {n}"}
            why = self._hand_over(setup, trial, meta)
        finally:
            self._end_setup(setup)
        if why is not None:
            self.say(f"campaign trial {n} cancelled: {why} arrived while it was set up")
            return TrialResult("cancelled", log_path, 0, 0, 0, 0.0,
                               fault=f"{why} arrived while it was being set up: cancelled before anything "
                                     "moved (no log written)")
        try:
            return self._trial_ran(trial, f"campaign trial {n}")
        finally:
            with self.state_lock:
                self.trial_thread = None
            self.dev_lock.release()

    def _new_trial(self, proto, specimen: str, operator: str, notes: str, user: str, log_path: Path,
                   model, size: dict[str, str] | None = None) -> Trial:
        info = TrialInfo(specimen=specimen, operator=operator, notes=notes, clock="real",
                         extra={"requested_by": user, "devices": self.devices.description, "daemon": "rigd",
                                "backstop": self.devices.backstop,
                                "warnings": " | ".join(self.devices.warnings), **(size or {})})
        trial = Trial(proto, self.config, self.devices.slider, self.devices.loadcell,
                      RealClock(self.config.loop.spin_ms / 1000.0), log_path, info, model=model, zero=self.zero)
        trial.on_tick = self._on_tick
        trial.live = self.live
        return trial

    def _model(self, req: dict):
        """The model sent with the request ("model_text"), else the config's `model:`."""
        from rig.models.saved import loads, model_for_run, runnable

        text = req.get("model_text")
        if text is None:
            return model_for_run(self.config)
        if not isinstance(text, str):
            raise RequestError('"model_text" must be the model file\'s contents')
        return runnable(loads(text, _text(req, "model_path", "<model>")))

    @contextlib.contextmanager
    def _idle_devices(self, busy: str):
        """The devices while no trial owns them; `RequestError(busy)` if they stay taken for 1 s
        (a status read or a stop from another client)."""
        if not self.dev_lock.acquire(timeout=1.0):
            raise RequestError(busy)
        try:
            yield self.devices
        finally:
            self.dev_lock.release()

    def _read_position(self) -> float:
        """A fresh position while no trial owns the devices."""
        with self._idle_devices("the devices are busy (a status read or a stop); try again") as dev:
            reading = dev.slider.position()
        if not reading.fresh:
            raise RequestError(f"cannot read the slider's position; not starting "
                               f"({getattr(self.devices.slider, 'last_error', '')})")
        return reading.value

    def _on_tick(self, snap: Snapshot) -> None:
        self.beat = time.monotonic()

    def _trial_ran(self, trial: Trial, label: str) -> TrialResult:
        """Run a trial on this thread (it holds the devices) and record its outcome as the last;
        a started trial and a campaign's both come here."""
        old = sys.getswitchinterval()
        sys.setswitchinterval(0.0005)
        try:
            result: TrialResult = trial.run()
        finally:
            sys.setswitchinterval(old)
        self.zero = trial.zero or self.zero
        tol = self.config.slider.position_tolerance_mm
        left, before, end = _left_in_contact(trial, result, tol), self.left_in, trial.end_place
        if left is None and before is not None:
            # a trial run from contact (--from-contact) ends where it started, still in: the
            # surface found before is still the one to return above
            if end is None:
                left = before
            elif end.position_mm > before["surface_mm"] + tol:
                left = {**before, "position_mm": round(end.position_mm, 4),
                        "depth_mm": round(end.position_mm - before["surface_mm"], 4)}
        self.left_in = left
        if left is not None:
            self.say(f"the probe is left in contact: {_where(left)}")
        self.last = {"outcome": result.outcome, "log": str(result.log_path), "samples": result.samples,
                     "duration_s": round(result.duration_s, 3), "fault": result.fault,
                     **{k: self.trial_meta[k] for k in ("protocol", "specimen", "user")}}
        self.say(f"{label} {result.outcome}: {result.samples} samples -> {result.log_path}")
        return result

    def _run_trial(self, trial: Trial) -> None:
        try:
            self._trial_ran(trial, "trial")
        except BaseException as exc:  # noqa: BLE001 - the daemon must outlive a failed trial
            self.last = {"outcome": "error", "error": f"{type(exc).__name__}: {exc}"}
            self.say(f"trial failed: {exc}")
        finally:
            self.dev_lock.release()
            notify("STATUS=idle")

    # ------------------------------------------------------------------ stops
    def _latch(self, what: str) -> _Cut:
        """One more stop (the caller holds state_lock): what it cuts, from now on."""
        self.stop_gen += 1
        self.stops_in_progress += 1
        self.last_stop = what
        campaign = self._campaign_running()
        if self.campaign_stop is not None:
            self.campaign_stop.set()  # no further trial of a campaign (a rest in progress ends now)
        t = self.trial if self.trial is not None and self.trial.lifecycle is not Lifecycle.ENDED else None
        return _Cut(t, self.trial_meta.get("protocol", "") if t is not None else "",
                    cancelled=[s.what for s in self.setting_up.values() if not s.moves], campaign=campaign,
                    moves_stopped=[s.what for s in self.setting_up.values() if s.moves])

    def _unlatch(self) -> None:
        with self.state_lock:
            self.stops_in_progress -= 1

    def _send_stop(self, mode: StopMode, notes: list[str]) -> None:
        """STOP on the idle devices (no trial owns them), or `RequestError` saying why not; a
        trial that ended a moment ago may still be letting go of them."""
        deadline = time.monotonic() + STOP_SENT_S
        while not self.dev_lock.acquire(timeout=0.01):
            if time.monotonic() > deadline:
                raise RequestError(_joined(f"{mode}: could not reach the drive (the devices stayed busy for "
                                           f"{STOP_SENT_S:g} s)", notes))
        try:
            ok = self.devices.slider.stop()
        except RigError as exc:
            raise RequestError(_joined(f"{mode}: STOP not sent: {exc}", notes)) from None
        finally:
            self.dev_lock.release()
        if not ok:
            raise RequestError(_joined(f"{mode}: the drive did not acknowledge STOP "
                                       f"({getattr(self.devices.slider, 'last_error', '')})", notes))

    def _stop_reply(self, ticket, mode: StopMode, notes: list[str]) -> dict:
        """Answer once the STOP went out (from the loop's next tick, or at once while the trial
        starts or closes): the truth about whether the drive took it, or why it was refused."""
        if not ticket.wait(STOP_SENT_S):
            raise RequestError(_joined(f"{mode}: the trial's loop did not send the STOP within "
                                       f"{STOP_SENT_S:g} s", notes))
        if not ticket.acknowledged:
            raise RequestError(_joined(f"{mode}: {ticket.message}", notes))
        said = ticket.message
        if "acknowledged" not in said:  # the loop's own word is "STOP sent in 2.1 ms"
            said += ", acknowledged by the drive"
        return {"ok": True, "mode": mode, "message": said, "acknowledged": True, "trial_running": True}

    def _carry_out(self, cut: _Cut, mode: StopMode, user: str, received: float) -> dict:
        """Carry a latched stop or estop out: through the trial that owns the devices, else on the
        idle devices when it cut something (a start being set up, a campaign between trials)."""
        if cut.trial is not None:
            ticket = cut.trial.request_stop(mode, user=user, received_s=received)
            if not ticket.trial_over:
                notes = cut.notes(trial_running=True)
                reply = self._stop_reply(ticket, mode, notes)
                head = {StopMode.ABORT: f"stopping, then returning to the start position: {reply['message']}",
                        StopMode.HOLD: f"stopping and staying in place: {reply['message']}",
                        StopMode.ESTOP: f"{reply['message']} (trial '{cut.protocol}' was running)"}[mode]
                reply.update(message=_joined(head, notes), cancelled=cut.cancelled, campaign_ends=cut.campaign)
                return reply
        notes = cut.notes(trial_running=False)
        if mode is not StopMode.ESTOP and not (cut.cancelled or cut.campaign or cut.moves_stopped):
            raise RequestError("no trial is running" + (" (it has just ended)" if cut.trial else ""))
        self._send_stop(mode, notes)
        return {"ok": True, "mode": mode, "acknowledged": True, "trial_running": False,
                "cancelled": cut.cancelled, "campaign_ends": cut.campaign,
                "message": _joined("STOP acknowledged by the drive (no trial was running)", notes)}

    # ------------------------------------------------------------------ the probe in contact
    def _in_contact(self, here_mm: float, confirmed: bool) -> list[str]:
        """Refuse a start while a trial cut short has left the probe in the specimen (it is still
        below the surface), unless the operator confirmed it (`from_contact`): then the warning
        the start's reply carries. A probe since raised above the surface is out: forgotten."""
        left = self.left_in
        if left is None:
            return []
        tol = self.config.slider.position_tolerance_mm
        if here_mm <= left["surface_mm"] + tol:
            self.left_in = None
            return []
        now = {**left, "position_mm": round(here_mm, 4), "depth_mm": round(here_mm - left["surface_mm"], 4)}
        if not confirmed:
            raise RequestError(
                f"not started: the probe is in contact, {_where(now)}; return it first (`rig return` moves it "
                f"back to {left['return_to_mm']:.3f} mm, where that trial started) or, to run from there, "
                "start again with --from-contact")
        return [f"starting in contact, as confirmed (--from-contact): the probe is {_where(now)}; the "
                "trial's zero is there and its preload counts against the force limit"]

    def cmd_return(self, req: dict, user: str, received: float) -> dict:
        """`rig return`: the probe back to where the trial that left it in contact started, watched
        as any move (force, travel, speed, alarm, deadline); a stop or an estop halts it."""
        left = self.left_in
        if left is None:
            raise RequestError("return: no trial has left the probe in contact; nothing to return "
                               "(`rig move --to-mm` moves it without the daemon)")
        to_mm = left["return_to_mm"]
        with self.state_lock:
            self._refuse_if_busy()
            setup = self._begin_setup(f"the return of the probe to {to_mm:.3f} mm (by {user})", moves=True)

        def stopped() -> str | None:
            with self.state_lock:
                return f"{self.last_stop} arrived" if self.stop_gen != setup.gen else None

        speed = min(RETURN_SPEED_MM_S, self.config.limits.max_speed_mm_s)
        self.say(f"{user} asked the probe back out of contact: from {left['position_mm']:.3f} to "
                 f"{to_mm:.3f} mm")
        try:
            with self._idle_devices("return: the devices are busy (a status read or a stop); try again") as dev:
                moved = move_on(dev, self.config, to_mm, speed, interrupted=stopped)
        except RigError as exc:
            raise RequestError(f"return: {exc}") from None
        finally:
            self._end_setup(setup)
        self.left_in = None
        message = (f"returned the probe to {moved['position_mm']:.3f} mm (from {moved['from_mm']:.3f} mm, "
                   f"{moved['seconds']:.1f} s): out of contact")
        self.say(f"{user}: {message}")
        return {"ok": True, "message": message, **moved}

    def cmd_stop(self, req: dict, user: str, received: float) -> dict:
        word = req.get("mode", StopMode.ABORT)
        if not isinstance(word, str) or word not in (StopMode.ABORT, StopMode.HOLD):
            raise RequestError('stop "mode" must be "abort" (stop, then return) or "hold" (stop and stay), '
                               f"not {_shown(word)}")
        mode = StopMode(word)
        with self.state_lock:
            cut = self._latch(f"a stop ({mode}) from {user} at {time.strftime('%H:%M:%S')}")
        try:
            self.say(f"{user} requested stop ({mode})")
            reply = self._carry_out(cut, mode, user, received)
        finally:
            self._unlatch()
        self.say(f"{user}'s stop: {reply['message']}")
        return reply

    def cmd_estop(self, req: dict, user: str, received: float) -> dict:
        with self.state_lock:
            cut = self._latch(f"an estop from {user} at {time.strftime('%H:%M:%S')}")
        try:
            self.say(f"{user} requested an emergency stop")
            reply = self._carry_out(cut, StopMode.ESTOP, user, received)
        finally:
            self._unlatch()
        self.say(f"{user}'s estop: {reply['message']}")
        return reply

    def cmd_reset_alarm(self, req: dict, user: str, received: float) -> dict:
        if self._busy():
            raise RequestError("reset_alarm: " + ("a trial is running" if self._trial_running() else
                                                  "a campaign is running (between trials)") + "; stop it first")
        with self._idle_devices("reset_alarm: the devices stayed busy for 1 s") as dev:
            before = dev.slider.status().value.alarm_code
            dev.slider.reset_alarm()
            after = dev.slider.status()
        self.say(f"{user} reset the drive alarm (0x{before:02X} -> 0x{after.value.alarm_code:02X})")
        if after.value.alarm_code:
            raise RequestError(f"reset_alarm: the drive still reports alarm 0x{after.value.alarm_code:02X} "
                               "(its cause is still there)")
        return {"ok": True, "alarm_before": before, "alarm_after": after.value.alarm_code}

    def cmd_watch(self, conn: socket.socket, req: dict) -> bool:
        given = req.get("rate_Hz")
        if given is None:
            rate = self.config.daemon.watch_rate_Hz
        else:
            rate = _number(given)
            if rate is None or rate <= 0:
                return send(conn, {"ok": False, "error": 'watch "rate_Hz" must be a number > 0 (updates per '
                                                         f"second; 0.5 to 100 are sent), not {_shown(given)}"})
        period = 1.0 / min(max(rate, 0.5), 100.0)
        while self._busy():
            t = self.trial
            msg = {"ok": True, "snapshot": asdict(t.snapshot) if t is not None else None,
                   "trial": self.trial_meta}
            if self._campaign_running():
                msg["campaign"] = dict(self.campaign)
            if not send(conn, msg):
                return False
            time.sleep(period)
        send(conn, {"ok": True, "end": True, "last": self.last})
        return False  # a watch ends its connection


def run_daemon(config: RigConfig, socket_path: Path | None = None, spy_path: str | None = None) -> int:
    """`rig daemon`: start the service, stop it cleanly on SIGTERM or SIGINT, serve until then; the exit
    status."""
    d = Daemon(config, socket_path, spy_path=spy_path)
    d.start()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: d.request_shutdown())
    d.serve_forever()
    d.say("stopped")
    return 0
