"""Run the simulated devices on the wire in a process of their own (`rig sim`).

A separate process is what real hardware is: the controller shares no memory and no
interpreter lock with it, and a controller killed with SIGKILL leaves the drive running
on its own, so its communication timeout can be shown to stop the slider.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import tempfile
import threading

from rig.errors import DeviceError


class SimProcess:
    """`python -m rig sim --json` with the given config text; endpoints from its first line."""

    def __init__(self, config_text: str, *, exit_with_parent: bool = True, timeout_s: float = 20.0) -> None:
        fd, self.config_path = tempfile.mkstemp(prefix="rig-sim-", suffix=".yaml")
        with os.fdopen(fd, "w") as fh:
            fh.write(config_text)
        args = [sys.executable, "-m", "rig", "sim", "--config", self.config_path, "--json"]
        if exit_with_parent:
            args.append("--exit-with-parent")
        self.proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, bufsize=1)
        line = _readline(self.proc, timeout_s)
        if not line:
            err = self.proc.stderr.read() if self.proc.poll() is not None else ""
            self.close()
            raise DeviceError(f"simulated devices did not start: {err.strip()[-300:] or 'no output'}")
        self.endpoints: dict = json.loads(line)

    def send(self, command: dict) -> None:
        """Change faults at run time, e.g. {"faults": {"drop_replies": 1}}."""
        self.proc.stdin.write(json.dumps(command) + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError):
                self.proc.stdin.close()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream:
                stream.close()
        with contextlib.suppress(OSError):
            os.unlink(self.config_path)


def _readline(proc: subprocess.Popen, timeout_s: float) -> str:
    out: list[str] = []
    t = threading.Thread(target=lambda: out.append(proc.stdout.readline()), daemon=True)
    t.start()
    t.join(timeout_s)
    return out[0].strip() if out else ""
