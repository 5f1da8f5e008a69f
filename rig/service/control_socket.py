"""The daemon's control socket: a Unix-domain socket, JSON lines in and out.

The socket is born mode 0660 (its owner and the configured group) and no network listener
exists. Each connection gets a thread; its peer (SO_PEERCRED) is checked before a byte is
read; a request longer than the limit is refused and its tail discarded; a line that is not
a JSON object with a "cmd" gets an error reply (so does one nested too deeply to read, or one
with NaN or Infinity, which JSON does not have). What a command does is the handler's
business: `handle(conn, request, user, received_s)` returns False to end the connection; an
exception it did not foresee is answered as an error and logged, and the connection carries
on (a client is never left without a reply).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import stat
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path

from rig.errors import RigError
from rig.service.peers import peer_allowed, peer_credentials, peer_groups, user_name

Handler = Callable[[socket.socket, dict, str, float], bool]


def send(conn: socket.socket, obj: dict) -> bool:
    """One reply line; False once the client has gone."""
    try:
        conn.sendall((json.dumps(obj, default=str) + "\n").encode())
        return True
    except OSError:
        return False


def private_dir(path: Path) -> Path:
    """`path`, a directory owned by this user and closed to group and others (made 0700 if
    absent); `RigError` saying what is wrong otherwise."""
    with contextlib.suppress(FileExistsError):
        os.mkdir(path, 0o700)
    try:
        st = os.lstat(path)
    except OSError as exc:
        raise RigError(f"socket directory {path}: {exc.strerror}") from None
    if not stat.S_ISDIR(st.st_mode):
        raise RigError(f"socket directory {path} is not a directory (a symlink or file is in its place); "
                       "remove it, or set XDG_RUNTIME_DIR or --socket")
    if st.st_uid != os.geteuid():
        raise RigError(f"socket directory {path} belongs to user {user_name(st.st_uid)}, not to you: another "
                       "user could serve a socket there; remove it, or set XDG_RUNTIME_DIR or --socket")
    if st.st_mode & 0o022:
        raise RigError(f"socket directory {path} is writable by group or others (mode "
                       f"{stat.S_IMODE(st.st_mode):04o}); chmod 700 it, or set XDG_RUNTIME_DIR or --socket")
    return path


class ControlSocket:
    """The daemon's Unix socket: each connection's requests, one JSON object a line, handed to `handle` with
    who sent them (peer credentials), in the daemon's group, with a size limit a request cannot pass."""

    def __init__(self, path: Path, handle: Handler, *, group_gid: int | None, max_request_bytes: int,
                 say: Callable[[str], None]) -> None:
        self.path = path
        self.handle = handle
        self.group_gid = group_gid
        self.limit = max_request_bytes
        self.say = say
        self._listener: socket.socket | None = None
        self._threads: list[threading.Thread] = []

    def listen(self) -> None:
        path = self.path
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.exists():
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                probe.connect(str(path))
                probe.close()
                raise RigError(f"another daemon is serving {path}")
            except (ConnectionRefusedError, FileNotFoundError):
                path.unlink()  # stale socket from a daemon that died
            finally:
                probe.close()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old_umask = os.umask(0o117)  # the socket is born 0660: no window with wider access
        try:
            sock.bind(str(path))
        finally:
            os.umask(old_umask)
        os.chmod(path, 0o660)
        if self.group_gid is not None:
            os.chown(path, -1, self.group_gid)
        sock.listen(16)
        sock.settimeout(0.2)
        self._listener = sock

    def serve(self, stop: threading.Event) -> None:
        """Accept connections until `stop` is set (or the socket is closed under it)."""
        while not stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                if stop.is_set():
                    break
                raise
            t = threading.Thread(target=self._serve_conn, args=(conn, stop), name="rigd-conn", daemon=True)
            self._threads = [c for c in self._threads if c.is_alive()] + [t]
            t.start()

    def close(self, join_s: float = 1.0) -> None:
        if self._listener is not None:
            self._listener.close()
            self._listener = None
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
        for c in self._threads:
            c.join(join_s)

    def _serve_conn(self, conn: socket.socket, stop: threading.Event) -> None:
        with conn:
            try:
                pid, uid, gid = peer_credentials(conn)
            except OSError:
                return
            owner = os.stat(self.path).st_uid if self.path.exists() else os.geteuid()
            if not peer_allowed(uid, gid, peer_groups(pid), owner, self.group_gid):
                send(conn, {"ok": False, "error": f"user {user_name(uid)} is not allowed here"})
                self.say(f"refused a connection from {user_name(uid)} (pid {pid})")
                return
            user = user_name(uid)
            conn.settimeout(None)
            limit = self.limit
            buf = b""
            discarding = False
            while not stop.is_set():
                try:
                    chunk = conn.recv(65536)
                except OSError:
                    return
                if not chunk:
                    return
                buf += chunk
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    if discarding:  # the tail of an oversized request
                        discarding = False
                        continue
                    if len(line) > limit:
                        send(conn, {"ok": False,
                                    "error": f"request too long ({len(line)} bytes; limit {limit})"})
                        continue
                    if line.strip() and not self._line(conn, line, user):
                        return
                if len(buf) > limit:
                    send(conn, {"ok": False, "error": f"request too long (over {limit} bytes)"})
                    buf = b""
                    discarding = True

    def _line(self, conn: socket.socket, line: bytes, user: str) -> bool:
        received = time.monotonic()
        try:
            req = json.loads(line, parse_constant=_not_json)
        except RecursionError:  # a few thousand nested brackets
            return send(conn, {"ok": False, "error": "not JSON this daemon reads: nested too deeply"})
        except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, a 5000-digit integer, NaN
            return send(conn, {"ok": False, "error": f"not JSON: {exc}"})
        if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
            return send(conn, {"ok": False, "error": 'expected a JSON object with "cmd"'})
        try:
            return self.handle(conn, req, user, received)
        except Exception as exc:  # noqa: BLE001 - a request the handler did not foresee: answer, carry on
            self.say(f"request {line[:200]!r} from {user} failed: {traceback.format_exc()}")
            why = f"{type(exc).__name__}: {exc}"
            return send(conn, {"ok": False, "error": f"the daemon could not carry out {req['cmd']!r}: {why} "
                                                     "(a bug; the daemon's log has the details)"})


def _not_json(name: str):
    """NaN, Infinity and -Infinity: Python's json reads them, JSON has no such numbers."""
    raise ValueError(f"{name} is not a JSON number")
