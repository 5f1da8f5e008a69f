"""One owner per drive and bus: an advisory lock per device, naming whoever holds it.

Two masters on one RS-485 bus collide, and a second connect to a drive rewrites its input
command (releasing a STOP the owner holds) and its communication timeout. So every process
takes the device's lock before it writes a byte, and keeps it until it closes the device.

The lock is `flock` on a file in a directory every user of the machine shares (/run/lock,
else the temporary directory): one file per serial device (keyed by the device's real path,
so a symlink such as /dev/serial/by-id/... and /dev/ttyUSB0 are one device) and one per TCP
drive (host:port). `flock` ends with the process, so a killed holder never blocks; the file's
contents only say who holds it (pid, user, command line, and what it is, e.g. a daemon and
its socket), for the one-line error a second user reads.
"""

from __future__ import annotations

import contextlib
import fcntl
import getpass
import json
import os
import re
import shlex
import socket
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from rig.errors import DeviceError

LOCK_DIR_ENV = "RIG_LOCK_DIR"


class DeviceInUse(DeviceError):
    """The device is owned by another process; the message names it."""


@dataclass(frozen=True)
class Holder:
    """Who holds a device's lock: the process, its user and command line, and a note on how to reach it
    instead (a daemon's socket)."""

    pid: int | None
    user: str
    command: str
    note: str = ""

    def describe(self) -> str:
        if self.pid is None:
            return "another process (it has not said which yet)"
        return f"pid {self.pid} (user {self.user}: {self.command})"


def lock_dir() -> Path:
    """Where the lock files live: $RIG_LOCK_DIR, /run/lock, /var/lock, else the temp directory."""
    for candidate in (os.environ.get(LOCK_DIR_ENV), "/run/lock", "/var/lock", tempfile.gettempdir()):
        if candidate and os.path.isdir(candidate) and os.access(candidate, os.W_OK | os.X_OK):
            return Path(candidate)
    raise DeviceError("no writable directory for device locks (tried $RIG_LOCK_DIR, /run/lock, /var/lock, "
                      f"{tempfile.gettempdir()})")


def serial_key(port: str) -> str:
    """A serial device by its real path (a pyserial URL such as loop:// stays as written)."""
    return os.path.realpath(port) if "://" not in port else port


def tcp_key(host: str, port: int) -> str:
    """The lock key of a drive on TCP: host (resolved, so localhost and 127.0.0.1 are one drive) and port."""
    with contextlib.suppress(OSError, UnicodeError):
        host = socket.gethostbyname(host)  # localhost and 127.0.0.1 are one drive
    return f"{host}:{port}"


def _lock_path(key: str) -> Path:
    slug = re.sub(r"[^A-Za-z0-9.]+", "-", key).strip("-") or "device"
    return lock_dir() / f"rig-{slug}.lock"


def _open_lock_file(path: Path) -> int:
    """The lock file, created shareable if absent.

    Another user's file in a sticky directory cannot be opened with O_CREAT where
    fs.protected_regular is on, so an existing file is opened without it; read-only is
    enough for flock when its mode does not let us write.
    """
    flags = os.O_NOFOLLOW | os.O_CLOEXEC
    for _ in range(3):
        for mode in (os.O_RDWR, os.O_RDONLY):
            try:
                return os.open(path, mode | flags)
            except PermissionError:
                continue
            except FileNotFoundError:
                break
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | flags, 0o666)
        except FileExistsError:
            continue  # created by someone else just now: open theirs
        # Every user of the machine must be able to record itself as the next holder.
        with contextlib.suppress(OSError):
            os.fchmod(fd, 0o666)
        return fd
    raise DeviceError(f"cannot open the device lock {path}")


def read_holder(path: Path) -> Holder:
    """The holder named in a lock file; an empty Holder while it is being written."""
    try:
        data = json.loads(path.read_text(errors="replace"))
        return Holder(int(data["pid"]), str(data.get("user", "")), str(data.get("command", "")),
                      str(data.get("note", "")))
    except (OSError, ValueError, KeyError, TypeError):  # empty: taken a moment ago, not yet named
        return Holder(None, "", "")


def _me() -> str:
    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return str(os.geteuid())


def _command_line() -> str:
    try:
        raw = Path(f"/proc/{os.getpid()}/cmdline").read_bytes()
        args = [a.decode(errors="replace") for a in raw.split(b"\0") if a]
    except OSError:
        args = [sys.executable, *sys.argv]
    # one line in the error message, whatever the arguments hold
    text = " ".join(shlex.quote(a) if a.isprintable() else repr(a) for a in args)
    return text if len(text) <= 300 else text[:297] + "..."


class DeviceLock:
    """Held from `acquire` until `release` (or the process ends)."""

    def __init__(self, what: str, key: str, path: Path, fd: int) -> None:
        self.what = what
        self.key = key
        self.path = path
        self._fd: int | None = fd

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is None:
            return
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)  # no stale name for the next reader; the flock is what counts
        with contextlib.suppress(OSError):
            fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def acquire(what: str, key: str, *, note: str = "") -> DeviceLock:
    """The lock on `key` (see `serial_key`, `tcp_key`), or `DeviceInUse` naming its holder.

    `what` names the device for the message ("the slider on /dev/ttyUSB0"); `note` tells a
    second user how to reach this holder instead (a daemon's socket)."""
    path = _lock_path(key)
    fd = _open_lock_file(path)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        holder = read_holder(path)
        how = (f"it is {holder.note}: ask it (rig status, rig position/reset-alarm --socket), or stop it"
               if holder.note else "wait for it to end, or stop it")
        raise DeviceInUse(f"{what} is in use by {holder.describe()}; {how}") from None
    except OSError as exc:
        os.close(fd)
        raise DeviceError(f"cannot lock {what} ({path}): {exc}") from None
    with contextlib.suppress(OSError):  # a read-only lock file: we hold it, only unnamed
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": os.getpid(), "user": _me(), "command": _command_line(),
                                  "note": note}).encode() + b"\n", 0)
    return DeviceLock(what, key, path, fd)


def hold_with(device, lock: DeviceLock):
    """`device` whose close() also releases `lock` (after the device is closed)."""
    close = device.close

    def close_and_release() -> None:
        try:
            close()
        finally:
            lock.release()

    device.close = close_and_release
    device.owner_lock = lock
    return device


def tty_exclusive(port) -> bool:
    """TIOCEXCL on an open serial port: no further open of the device (but root's) succeeds.

    Not on a pseudo-terminal: its pair outlives a killed holder while the other end stays
    open, and so would the flag. True if set."""
    import termios

    try:
        fd = port.fileno()
        if os.major(os.fstat(fd).st_rdev) in _PTY_MAJORS or not os.isatty(fd):
            return False
        fcntl.ioctl(fd, termios.TIOCEXCL)
        return True
    except (AttributeError, OSError, ValueError):
        return False


_PTY_MAJORS = set(range(136, 144))  # Unix98 pty slaves (Linux devices.txt)
