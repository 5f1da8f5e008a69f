"""systemd notifications (sd_notify(3)) and a watchdog that stops pinging when the loop stalls."""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Callable


def notify(message: str) -> bool:
    """Send one notification to $NOTIFY_SOCKET (READY=1, WATCHDOG=1, STATUS=...); False if unset."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return False
    if addr.startswith("@"):  # abstract namespace
        addr = "\0" + addr[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            s.connect(addr)
            s.sendall(message.encode())
        return True
    except OSError:
        return False


def watchdog_interval_s() -> float | None:
    """Half of $WATCHDOG_USEC (systemd's advice), or None when no watchdog is configured."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and int(pid) != os.getpid()):
        return None
    return int(usec) / 2e6


def healthy(now: float, last_beat: float | None, running: bool, stall_s: float) -> bool:
    """Ping only while alive: idle, or running with a loop tick within `stall_s`."""
    if not running:
        return True
    return last_beat is not None and now - last_beat <= stall_s


class Watchdog:
    """Sends WATCHDOG=1 every `interval_s` while `is_healthy()` holds; silence lets systemd act."""

    def __init__(self, interval_s: float, is_healthy: Callable[[], bool]) -> None:
        self.interval_s = interval_s
        self.is_healthy = is_healthy
        self.pings = 0
        self.withheld = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="watchdog", daemon=True)

    def start(self) -> Watchdog:
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            if self.is_healthy():
                notify("WATCHDOG=1")
                self.pings += 1
            else:
                self.withheld += 1
                notify("STATUS=control loop stalled: watchdog pings withheld")

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
