"""One poller of the daemon, fanned out to every viewer.

A thread asks the daemon for its status (twice a second while idle) and, while a trial or a
campaign runs, follows its `watch` stream (50 updates a second). The updates are handed on 25
times a second, each message carrying the points since the last (the page draws 25 times a
second: twice the messages would show nothing more and cost every viewer twice the wake-ups).
Each message is encoded once and handed to every viewer's bounded queue on the server's event
loop (the oldest dropped for a viewer that falls behind), so ten viewers cost the daemon what
one does, and a slow viewer delays nobody. The running trial's points so far are kept, so a
viewer who arrives late sees the whole trial. The thread never touches a device: it is a client
of the daemon's socket.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time
from pathlib import Path

from rig.errors import RigError
from rig.service.client import request, stream

IDLE_PERIOD_S = 0.5
WATCH_RATE_HZ = 50.0
PUSH_PERIOD_S = 0.04  # the viewers are sent the new points at most this often (a new step at once)
QUEUE = 256  # messages a viewer may fall behind by before its oldest are dropped
MAX_POINTS = 200_000  # the running trial's points kept for late viewers (over an hour at 50 Hz)


def _point(snap: dict) -> list:
    return [round(snap.get("t_s", 0.0), 3), snap.get("force_N"), snap.get("position_mm"),
            snap.get("stiffness_N_per_m"), snap.get("step", -1)]


class Hub:
    def __init__(self, socket_path: Path, rate_Hz: float = WATCH_RATE_HZ) -> None:
        self.socket_path = socket_path
        self.rate_Hz = rate_Hz
        self._viewers: dict[asyncio.Queue, asyncio.AbstractEventLoop] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._nudge = threading.Event()
        self._thread: threading.Thread | None = None
        self.status: dict = {"ok": False, "error": "not asked yet"}
        self.trial: dict | None = None  # the running trial's meta, and its limits when known
        self.points: list[list] = []
        self.steps: list[list] = []  # [t_s, step, kind] where each step began
        self.last_end: dict | None = None
        self.limits_by_log: dict[str, dict] = {}
        self.campaign: dict | None = None  # the running campaign as the watch stream last said
        self._unsent: list[list] = []  # points not yet sent to the viewers
        self._pushed = 0.0  # when they were last sent (time.monotonic())
        self.messages = 0

    # ------------------------------------------------------------------ viewers
    def subscribe(self) -> asyncio.Queue:
        q: asyncio.Queue = asyncio.Queue(QUEUE)
        with self._lock:
            self._viewers[q] = asyncio.get_running_loop()
        return q

    def unsubscribe(self, q: asyncio.Queue) -> None:
        with self._lock:
            self._viewers.pop(q, None)

    @property
    def viewers(self) -> int:
        return len(self._viewers)

    def hello(self) -> str:
        """What a viewer is sent first: the state, and the running trial so far."""
        return json.dumps({"kind": "hello", "status": self.status, "trial": self.trial,
                           "points": self.points, "steps": self.steps, "last_end": self.last_end,
                           "sent": time.time()}, default=str)

    def _publish(self, msg: dict) -> None:
        self.messages += 1
        msg["sent"] = time.time()
        text = json.dumps(msg, default=str)
        with self._lock:
            viewers = list(self._viewers.items())
        for q, loop in viewers:
            with contextlib.suppress(RuntimeError):  # the loop has closed
                loop.call_soon_threadsafe(_offer, q, text)

    # ------------------------------------------------------------------ the poller
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="rig-web-poller", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._nudge.set()
        if self._thread is not None:
            self._thread.join(5)

    def nudge(self) -> None:
        """Ask the daemon again now (a start was just made)."""
        self._nudge.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                st = request(self.socket_path, {"cmd": "status"}, 5.0)
            except RigError as exc:
                st = {"ok": False, "error": str(exc)}
            self.status = st
            self._publish({"kind": "status", "status": st})
            if st.get("ok") and st.get("state") in ("running", "fault", "characterizing"):
                self._follow()
                continue
            self._nudge.wait(IDLE_PERIOD_S)
            self._nudge.clear()

    def _follow(self) -> None:
        """The watch stream, until the daemon is idle again."""
        try:
            for msg in stream(self.socket_path, {"cmd": "watch", "rate_Hz": self.rate_Hz}, 10.0):
                if self._stop.is_set():
                    return
                if not msg.get("ok"):
                    self._publish({"kind": "error", "error": msg.get("error", "")})
                    return
                if msg.get("end"):
                    self.last_end = msg.get("last")
                    self._publish({"kind": "end", "last": self.last_end})
                    self.trial = None
                    return
                self._live(msg)
        except RigError as exc:
            self._publish({"kind": "error", "error": str(exc)})
            time.sleep(IDLE_PERIOD_S)

    def _live(self, msg: dict) -> None:
        snap = msg.get("snapshot") or {}
        meta = msg.get("trial") or {}
        log = meta.get("log", "")
        if self.trial is None or self.trial.get("log") != log:
            self.trial = {**meta, "limits": self.limits_by_log.get(log) or self.limits_by_log.get(
                meta.get("protocol", ""))}
            self.points, self.steps, self._unsent = [], [], []
            self._publish({"kind": "trial", "trial": self.trial})
        camp = msg.get("campaign")
        if camp is not None and camp != self.campaign:  # between a campaign's trials too (no snapshot)
            self.campaign = camp
            self._publish({"kind": "campaign", "campaign": camp})
        if not snap:
            return
        point = _point(snap)
        if self.points and point[0] <= self.points[-1][0] and point[4] == self.points[-1][4]:
            return  # the same tick again (the stream is faster than the loop, or it paused)
        new_step = not self.steps or self.steps[-1][1] != point[4]
        if new_step:
            self.steps.append([point[0], point[4], snap.get("step_kind", "")])
        if len(self.points) < MAX_POINTS:
            self.points.append(point)
        self._unsent.append(point)
        now = time.monotonic()
        if not (new_step or snap.get("fault") or now - self._pushed >= PUSH_PERIOD_S):
            return
        self._pushed = now
        batch, self._unsent = self._unsent, []
        self._publish({"kind": "live", "p": point, "ps": batch, "state": snap.get("state"),
                       "step_kind": snap.get("step_kind"), "step": snap.get("step"),
                       "steps_total": snap.get("steps_total"),
                       "time_left_s": snap.get("time_left_s"), "fault": snap.get("fault"),
                       "campaign": msg.get("campaign")})


def _offer(q: asyncio.Queue, text: str) -> None:
    if q.full():
        with contextlib.suppress(asyncio.QueueEmpty):
            q.get_nowait()
    q.put_nowait(text)
