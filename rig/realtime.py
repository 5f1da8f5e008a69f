"""Real-time scheduling for the loop thread: SCHED_FIFO and locked memory, where allowed.

Under CPU load a normal thread waits behind other processes for milliseconds: late
ticks. SCHED_FIFO puts the loop thread ahead of every normal thread on the machine
(the kernel's RT throttling still leaves 5 % to the rest), and mlockall keeps its pages
from being swapped out. Both need privilege (root, CAP_SYS_NICE / CAP_IPC_LOCK, or
`LimitRTPRIO`/`LimitMEMLOCK` in the systemd unit); without it the loop runs as before
and the trial log says so.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import threading
from dataclasses import dataclass

from rig.errors import RigError

_MCL_CURRENT, _MCL_FUTURE, _MCL_ONFAULT = 1, 2, 4


@dataclass
class RealtimeState:
    """The scheduling the loop thread got: its policy, whether memory is locked, and why not when something
    was refused."""

    policy: str  # "SCHED_FIFO 50", or "normal"
    memory_locked: bool
    detail: str  # why not, when it was not granted

    def describe(self) -> str:
        mem = "memory locked" if self.memory_locked else "memory not locked"
        why = f" ({self.detail})" if self.detail else ""
        return f"{self.policy}, {mem}{why}"

    @property
    def granted(self) -> bool:
        return self.policy.startswith("SCHED_FIFO")


class Realtime:
    """Enter real-time scheduling for the calling thread; `leave()` restores what it had."""

    def __init__(self, mode: str = "auto", priority: int = 50) -> None:
        self.mode = mode
        self.priority = priority
        self._old: tuple[int, int] | None = None
        self._helpers: list[tuple[int, int, int]] = []  # (tid, old policy, old priority)
        self._locked = False

    def enter(self, helpers: list[threading.Thread | None] = ()) -> RealtimeState:
        """Real-time for the calling thread at `priority`, and for `helpers` just below it.

        The helpers are the threads the loop waits on for the interpreter lock (the recorder's
        writer, the load cell's reader): left at normal priority, a busy machine can preempt one
        while it holds the lock, and the loop waits behind it (priority inversion).
        """
        if self.mode == "off" or not hasattr(os, "sched_setscheduler"):
            return RealtimeState("normal", False, "off in the config" if self.mode == "off" else
                                 "not supported on this platform")
        problems = []
        policy = "normal"
        try:
            old = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))
            self._old = old
            policy = f"SCHED_FIFO {self.priority}"
            for thread in helpers:
                tid = getattr(thread, "native_id", None)
                if tid is None or not thread.is_alive():
                    continue
                with contextlib.suppress(OSError):  # a thread that just ended
                    was = (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority)
                    os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(max(self.priority - 1, 1)))
                    self._helpers.append((tid, *was))
        except OSError as exc:
            problems.append(f"SCHED_FIFO refused: {exc.strerror}")
        self._locked = _mlockall()
        if not self._locked:
            problems.append("mlockall refused")
        state = RealtimeState(policy, self._locked, "; ".join(problems))
        if self.mode == "required" and not state.granted:
            self.leave()
            raise RigError(f"loop.realtime is 'required' but {state.detail}: run as root, give the "
                           "process CAP_SYS_NICE (systemd: LimitRTPRIO=), or set loop.realtime: auto")
        return state

    def leave(self) -> None:
        for tid, policy, prio in self._helpers:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(tid, policy, os.sched_param(prio))
        self._helpers = []
        if self._old is not None:
            policy, prio = self._old
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, policy, os.sched_param(prio))
            self._old = None
        if self._locked:
            _munlockall()
            self._locked = False


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name, use_errno=True) if name else None
    except OSError:
        return None


def _mlockall() -> bool:
    """Lock pages as they are touched (MCL_ONFAULT, Linux 4.4+): prefaulting every mapping, and
    every new thread's 8 MB stack, would cost tens of milliseconds each time."""
    libc = _libc()
    if not libc:
        return False
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE | _MCL_ONFAULT) == 0:
        return True
    return libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0


def _munlockall() -> None:
    libc = _libc()
    if libc:
        libc.munlockall()
