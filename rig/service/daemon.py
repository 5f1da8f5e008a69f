"""`rig daemon`: owns the slider and load cell and runs one trial at a time for its clients.

Control is a Unix-domain socket (`control_socket.py`: mode 0660, the peer checked by
`peers.py`), no network listener. The protocol is JSON lines: one request, one reply; `watch`
streams status lines until the trial ends. The peer user is recorded with the starts and
stops it makes.

Requests: {"cmd": "ping"}, {"cmd": "status"}, {"cmd": "logs"},
{"cmd": "start", "protocol_text": ..., "protocol_path": ..., "specimen": ..., "operator": ..., "notes": ...},
{"cmd": "stop", "mode": "abort" | "hold"}, {"cmd": "estop"}, {"cmd": "reset_alarm"},
{"cmd": "watch", "rate_Hz": 10}.
Replies carry "ok": true, or "ok": false with "error". A stop or estop is answered once the
STOP has gone out on the bus and the drive acknowledged it; "ok": false says it did not.
"""

from __future__ import annotations

import contextlib
import grp
import os
import signal
import socket
import sys
import tempfile
import threading
import time
from dataclasses import asdict
from pathlib import Path

from rig import __version__
from rig.clock import RealClock
from rig.control.devices import Devices, open_devices
from rig.control.stopping import StopMode
from rig.control.trial import Snapshot, Trial, TrialResult, default_log_path
from rig.errors import RigError
from rig.recording.recorder import TrialInfo
from rig.recording.recovery import find_unfinished, list_trials, recover
from rig.service.control_socket import ControlSocket, private_dir, send
from rig.service.sdnotify import Watchdog, healthy, notify, watchdog_interval_s
from rig.specs.config import RigConfig
from rig.specs.protocol import check_limits, parse_protocol

LOG_NAMED_S = 5.0  # a start waits this long at most for its log to be named


def default_socket_path(config: RigConfig | None = None) -> Path:
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


class Daemon:
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
        self.state_lock = threading.Lock()
        self.trial: Trial | None = None
        self.trial_thread: threading.Thread | None = None
        self.trial_meta: dict = {}
        self.zero = None  # the load cell's free-air zero the last trial used: the next one counts from it
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
        in_use: list[Path] = []
        for path in find_unfinished(self.out_dir, in_use=in_use):
            try:
                recover(path)
                self.recovered.append(str(path))
                self.say(f"recovered interrupted trial log {path}")
            except RigError as exc:
                self.say(f"could not recover {path}: {exc}")
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
        running = t is not None and t.snapshot.state in ("running", "stopping")
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
        t = self.trial
        if self.campaign_stop is not None:
            self.campaign_stop.set()
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
        if self._campaign_running():
            c = self.campaign
            raise RequestError(f"busy: characterizing specimen {c['specimen']} (started by {c['user']} at "
                               f"{c['started']}; {c['phase']}); `rig stop` ends it")
        if self._trial_running():
            m = self.trial_meta
            raise RequestError(f"busy: trial '{m['protocol']}' (specimen {m['specimen']}, started "
                               f"by {m['user']} at {m['started']}) is running; log {m['log']}")

    def cmd_start(self, req: dict, user: str, received: float) -> dict:
        if req.get("characterize") is not None:
            return self._start_campaign(req, user)
        text = req.get("protocol_text")
        if not isinstance(text, str) or not text.strip():
            raise RequestError('start needs "protocol_text" (the protocol file\'s contents)')
        path = str(req.get("protocol_path") or "<protocol>")
        with self.state_lock:
            self._refuse_if_busy()
            proto = parse_protocol(text, path)  # SpecError -> error reply
            # From where the slider is now: the trial's zero is there, not at 0.
            check_limits(proto, self.config, start_mm=self._read_position())  # LimitError -> error reply
            specimen = str(req.get("specimen") or "specimen")
            operator = str(req.get("operator") or user)
            log_path = default_log_path(self.out_dir, proto, specimen)
            warnings = self.devices.warnings
            trial = self._new_trial(proto, specimen, operator, str(req.get("notes") or ""), user, log_path,
                                    self._model(req))
            warnings = [*warnings, *trial.warnings]
            self.trial = trial
            self.trial_meta = {"protocol": proto.name, "specimen": specimen, "user": user,
                               "operator": operator, "log": str(log_path),
                               "started": time.strftime("%H:%M:%S")}
            self.beat = time.monotonic()
            self.trial_thread = threading.Thread(target=self._run_trial, args=(trial,), name="trial",
                                                 daemon=True)
            self.dev_lock.acquire()
            self.trial_thread.start()
        # the recorder may take the next free name (a log of the same second exists): the reply
        # names the file this trial writes, never an earlier one
        trial.log_named.wait(LOG_NAMED_S)
        log_path = trial.log_path
        if trial.recorder is None and trial.log_named.is_set():
            # it ended before opening its log (a limit from where the slider stands, the first
            # position read, the log's folder): the truth is that it did not start
            self.trial_thread.join(LOG_NAMED_S)
            why = (self.last or {}).get("error", "it ended at once")
            raise RequestError(f"the trial did not start: {why}")
        with self.state_lock:
            if self.trial is trial:
                self.trial_meta["log"] = str(log_path)
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
        specimen = str(req.get("specimen") or "specimen")
        text = req.get("protocol_text") or None
        if text is not None:
            if not isinstance(text, str):
                raise RequestError('"protocol_text" must be the protocol file\'s contents')
            parse_protocol(text, str(req.get("protocol_path") or "<protocol>"))  # refused here, not later
        numbers = {"max_trials": int, "budget_min": float, "target_rse": float, "rest_s": float}
        kw = {}
        for name, kind in numbers.items():
            if opts.get(name) is not None:
                try:
                    kw[name] = kind(opts[name])
                except (TypeError, ValueError):
                    raise RequestError(f'characterize "{name}" must be a number, not {opts[name]!r}') from None
                if kw[name] < 0 or (name == "max_trials" and kw[name] < 1):
                    raise RequestError(f'characterize "{name}" must be positive, not {opts[name]!r}')
        with self.state_lock:
            self._refuse_if_busy()
            self.campaign_stop = threading.Event()
            out = self.out_dir / f"characterize-{specimen}"
            request = Request(specimen, self.config, out, model=str(opts.get("model") or "proposed"),
                              indenter=opts.get("indenter"), first_text=text, speed=1.0, say=self.say,
                              runner=lambda proto, n, log: self._campaign_trial(proto, n, log, req, user),
                              stop=self.campaign_stop, on_event=self._campaign_event, **kw)
            self.campaign = {"specimen": specimen, "user": user, "started": time.strftime("%H:%M:%S"),
                             "phase": "starting", "trials": 0, "status": "running", "journal": None}
            self.campaign_thread = threading.Thread(target=self._run_campaign, args=(request,),
                                                    name="campaign", daemon=True)
            self.campaign_thread.start()
        self.say(f"{user} started characterizing specimen {specimen} -> {out}")
        notify(f"STATUS=characterizing {specimen}")
        return {"ok": True, "characterize": specimen, "out": str(out),
                "warnings": list(self.devices.warnings)}

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
        """One trial of the campaign, on this thread, with the devices held for its whole length."""
        specimen = self.campaign["specimen"]
        with self.state_lock:
            check_limits(proto, self.config, start_mm=self._read_position())
            trial = self._new_trial(proto, specimen, str(req.get("operator") or user),
                                    f"characterize trial {n}", user, log_path, None)
            self.trial_meta = {"protocol": proto.name, "specimen": specimen, "user": user,
                               "operator": str(req.get("operator") or user), "log": str(log_path),
                               "started": time.strftime("%H:%M:%S"), "campaign": f"characterize trial {n}"}
            self.trial = trial
            self.trial_thread = threading.current_thread()
            self.beat = time.monotonic()
            self.dev_lock.acquire()
        try:
            return self._trial_ran(trial, f"campaign trial {n}")
        finally:
            with self.state_lock:
                self.trial_thread = None
            self.dev_lock.release()

    def _new_trial(self, proto, specimen: str, operator: str, notes: str, user: str, log_path: Path,
                   model) -> Trial:
        info = TrialInfo(specimen=specimen, operator=operator, notes=notes, clock="real",
                         extra={"requested_by": user, "devices": self.devices.description, "daemon": "rigd",
                                "backstop": self.devices.backstop,
                                "warnings": " | ".join(self.devices.warnings)})
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
        return runnable(loads(text, str(req.get("model_path") or "<model>")))

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
        """A fresh position while no trial owns the devices (the caller holds state_lock)."""
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

    def _running_trial(self) -> Trial:
        if not self._trial_running():
            raise RequestError("no trial is running")
        return self.trial

    def cmd_stop(self, req: dict, user: str, received: float) -> dict:
        mode = req.get("mode", "abort")
        if mode not in ("abort", "hold"):
            raise RequestError('stop "mode" must be "abort" (stop, then return) or "hold" (stop and stay)')
        campaign = self._campaign_running()
        if campaign:
            self.campaign_stop.set()
            if not self._trial_running():
                self.say(f"{user} stopped the campaign between trials")
                return {"ok": True, "mode": mode, "message": "the campaign ends before its next trial (no "
                        "trial was running; the probe is where the last trial left it)"}
        ticket = self._running_trial().request_stop(StopMode(mode), user=user, received_s=received)
        self.say(f"{user} requested stop ({mode})")
        if ticket.trial_over:
            raise RequestError("no trial is running (it has just ended)")
        return self._stop_reply(ticket, mode)

    def _stop_reply(self, ticket, mode: str) -> dict:
        """Answer once the STOP went out (from the loop's next tick, or at once while the trial
        starts or closes): the truth about whether the drive took it, or why it was refused."""
        if not ticket.wait(1.0):
            raise RequestError(f"{mode}: the trial's loop did not send the STOP within 1 s")
        if not ticket.acknowledged:
            raise RequestError(f"{mode}: {ticket.message}")
        return {"ok": True, "mode": mode, "message": ticket.message}

    def cmd_estop(self, req: dict, user: str, received: float) -> dict:
        self.say(f"{user} requested an emergency stop")
        if self.campaign_stop is not None:
            self.campaign_stop.set()  # no further trial of a campaign
        # A trial owns the bus from its thread's start to its end: ask it (it sends at once when
        # its loop is not ticking); otherwise take the idle devices. Re-checked until one of the
        # two answers, so an estop that meets a trial starting or ending is never turned away.
        deadline = time.monotonic() + 1.0
        while True:
            t = self.trial
            if self._trial_running():
                ticket = t.request_stop(StopMode.ESTOP, user=user, received_s=received)
                if not ticket.trial_over:
                    return self._stop_reply(ticket, "estop")
            if self.dev_lock.acquire(timeout=0.01):
                break
            if time.monotonic() > deadline:
                raise RequestError("estop: could not reach the drive (the devices stayed busy for 1 s)")
        try:
            ok = self.devices.slider.stop()
        except RigError as exc:
            raise RequestError(f"estop: STOP not sent: {exc}") from None
        finally:
            self.dev_lock.release()
        if not ok:
            raise RequestError(f"estop: the drive did not acknowledge STOP "
                               f"({getattr(self.devices.slider, 'last_error', '')})")
        return {"ok": True, "mode": "estop", "message": "STOP acknowledged by the drive (no trial was running)"}

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
        rate = float(req.get("rate_Hz") or self.config.daemon.watch_rate_Hz)
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
    d = Daemon(config, socket_path, spy_path=spy_path)
    d.start()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: d.request_shutdown())
    d.serve_forever()
    d.say("stopped")
    return 0
