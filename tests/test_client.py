"""The control socket's client: whatever the other end does, one RigError line, never a traceback."""

from __future__ import annotations

import socket
import struct
import threading

import pytest

from rig.errors import RigError
from rig.service.client import request


def serve_once(path, reply: bytes | None):
    """A one-shot server at `path`: reads the request, then sends `reply` or resets the connection."""
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(path))
    srv.listen(1)

    def run():
        conn, _ = srv.accept()
        with conn:
            conn.recv(65536)
            if reply is None:  # close with a reset, as a killed process's socket does
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            else:
                conn.sendall(reply)
        srv.close()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


@pytest.mark.parametrize(("reply", "said"), [
    (None, "the daemon closed the connection"),
    (b"not json\n", "the daemon's reply is not a JSON line"),
    (b"[1, 2]\n", "the daemon's reply is not a JSON object"),
    (b"", "the daemon closed the connection without a reply"),
])
def test_a_bad_or_broken_reply_is_one_clear_error(tmp_path, reply, said):
    sock = tmp_path / "rigd.sock"
    t = serve_once(sock, reply)
    with pytest.raises(RigError) as err:
        request(sock, {"cmd": "ping"}, 5.0)
    assert said in str(err.value) and "\n" not in str(err.value)
    t.join(5)


def test_a_good_reply_is_returned(tmp_path):
    sock = tmp_path / "rigd.sock"
    t = serve_once(sock, b'{"ok": true}\n')
    assert request(sock, {"cmd": "ping"}, 5.0) == {"ok": True}
    t.join(5)
