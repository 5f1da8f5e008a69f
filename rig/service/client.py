"""Talk to `rig daemon` over its Unix socket: one request, one reply (or a stream for watch)."""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator
from pathlib import Path

from rig.errors import RigError


def _connect(path: Path, timeout_s: float) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout_s)
    try:
        sock.connect(str(path))
    except FileNotFoundError:
        sock.close()
        raise RigError(f"no daemon at {path} (start one with `rig daemon`, or pass --socket)") from None
    except ConnectionRefusedError:
        sock.close()
        raise RigError(f"no daemon listening at {path} (a stale socket?)") from None
    except PermissionError:
        sock.close()
        raise RigError(f"permission denied on {path}: you must be its owner or in its group") from None
    return sock


def _lines(sock: socket.socket) -> Iterator[dict]:
    buf = b""
    while True:
        try:
            chunk = sock.recv(65536)
        except TimeoutError:
            raise RigError("the daemon did not answer in time") from None
        except OSError as exc:  # reset: the daemon went away (stopping, killed) mid-request
            raise RigError(f"the daemon closed the connection ({exc.strerror or exc})") from None
        if not chunk:
            if buf.strip():
                yield _decode(buf)
            return
        buf += chunk
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            if line.strip():
                yield _decode(line)


def _decode(line: bytes) -> dict:
    try:
        reply = json.loads(line)
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise RigError(f"the daemon's reply is not a JSON line: {line[:80]!r}") from None
    if not isinstance(reply, dict):
        raise RigError(f"the daemon's reply is not a JSON object: {line[:80]!r}")
    return reply


def _send(sock: socket.socket, obj: dict) -> None:
    try:
        sock.sendall((json.dumps(obj) + "\n").encode())
    except OSError as exc:
        raise RigError(f"the daemon closed the connection ({exc.strerror or exc})") from None


def request(path: Path, obj: dict, timeout_s: float = 10.0) -> dict:
    """Send one request to the daemon's socket and return its reply (RigError if there is none)."""
    with _connect(path, timeout_s) as sock:
        _send(sock, obj)
        for reply in _lines(sock):
            return reply
    raise RigError("the daemon closed the connection without a reply")


def stream(path: Path, obj: dict, timeout_s: float = 10.0) -> Iterator[dict]:
    """Send one request to the daemon's socket and yield each reply line as it comes (`rig watch`)."""
    with _connect(path, timeout_s) as sock:
        _send(sock, obj)
        yield from _lines(sock)
