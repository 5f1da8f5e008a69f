"""What the machine itself takes from a thread nothing on it may preempt.

A process at real-time priority above the loop's sleeps 1 ms at a time and notes each wake-up
later than a threshold ("wake"); after each, it sends a few bytes through a pseudo-terminal of
its own and notes each crossing slower than the threshold ("pty"). Nothing in user space can
delay its wake-ups (it outranks every thread of the rig and of the simulated devices), so they
show the kernel's and the hypervisor's share: a kernel built without preemption finishing
another task's system call, a virtual CPU the host took away. Its pty crossings also wait for
the kernel's tty worker, a thread of normal priority that any busy process competes with: the
same path every byte of the simulated wire takes. Run beside a bench trial, it tells a late
tick the machine caused from one the rig caused. `python -m rig.diagnostics.stalls PRIORITY
THRESHOLD_MS` runs until stdin closes, then prints its stalls as one JSON line:
{"stalls": [[start (time.monotonic, s), stall ms, "wake" or "pty"], ...], ...}.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time


class StallProbe:
    """The probe as a context manager: `stalls` holds (start on `time.monotonic`, stall ms) once it
    exits; the monotonic clock is the machine's, shared by every process on it."""

    def __init__(self, priority: int = 51, threshold_ms: float = 2.0) -> None:
        self.priority = min(max(priority, 1), 99)
        self.threshold_ms = threshold_ms
        self.stalls: list[tuple[float, float, str]] = []
        self.realtime = False
        self._proc: subprocess.Popen | None = None

    def __enter__(self) -> StallProbe:
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "rig.diagnostics.stalls", str(self.priority), str(self.threshold_ms)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        return self

    def __exit__(self, *exc) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            out, _ = proc.communicate("", timeout=5.0)
            report = json.loads(out.strip().splitlines()[-1])
            self.realtime = bool(report["realtime"])
            self.stalls = [(float(t), float(ms), str(kind)) for t, ms, kind in report["stalls"]]
        except (subprocess.TimeoutExpired, ValueError, IndexError, KeyError):
            proc.kill()
            proc.wait()

    def near(self, t_s: float, before_s: float = 0.05) -> float:
        """The longest stall that ended within `before_s` before `t_s` (0.0 if none)."""
        return max((ms for t, ms, _ in self.stalls if t_s - before_s <= t + ms / 1000.0 <= t_s + 0.002),
                   default=0.0)


def tty_workers() -> dict:
    """The kernel's unbound workers (kworker/u*), which carry every byte written to a pty or a
    USB serial adapter to its reader: how many there are and how many run at real-time priority.
    At normal priority (the kernel's default) the bytes wait behind any busy process."""
    import os

    threads = realtime = 0
    for pid in os.listdir("/proc") if os.path.isdir("/proc") else []:
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/comm") as fh:
                if not fh.read().startswith("kworker/u"):
                    continue
            threads += 1
            realtime += os.sched_getscheduler(int(pid)) in (os.SCHED_FIFO, os.SCHED_RR)
        except OSError:  # gone meanwhile, or not ours to read
            continue
    return {"threads": threads, "realtime": realtime}


def _crossing_s(src: int, dst: int, data: bytes) -> float:
    """Seconds for `data` written at one end of a pty to arrive at the other (inf: not in 1 s)."""
    import os
    import select

    start = time.monotonic()
    os.write(src, data)
    got = 0
    while got < len(data):
        if not select.select([dst], [], [], 1.0)[0]:
            return math.inf
        got += len(os.read(dst, 4096))
    return time.monotonic() - start


def main(argv: list[str]) -> int:
    import os
    import pty
    import tty

    priority, threshold_ms = int(argv[0]), float(argv[1])
    realtime = True
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError):
        realtime = False
    done = threading.Event()
    # stdin closing is the stop; a thread of normal priority waits for it (it never holds the
    # interpreter lock for long, and a late stop costs nothing here).
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    master, slave = pty.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    stalls = []
    threshold_s = threshold_ms / 1000.0
    data = bytes(8)  # a Modbus read request's size
    while not done.is_set():
        a = time.monotonic()
        time.sleep(0.001)
        b = time.monotonic()
        if b - a - 0.001 > threshold_s:
            stalls.append((round(a + 0.001, 5), _ms(b - a - 0.001), "wake"))
        took = _crossing_s(master, slave, data)
        if took > threshold_s:
            stalls.append((round(b, 5), _ms(min(took, 1.0)), "pty"))
    print(json.dumps({"realtime": realtime, "stalls": stalls}), flush=True)
    return 0


def _ms(s: float) -> float:
    """A stall in ms to the report's 0.01 ms, never rounded to nought: one above the threshold
    (which may be zero) lasted something."""
    return max(round(s * 1000.0, 2), 0.01)


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
