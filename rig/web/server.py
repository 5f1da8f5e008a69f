"""Serve `rig web`: bind, make the token, say where, run uvicorn until Ctrl-C."""

from __future__ import annotations

import socket
import sys
import threading
from pathlib import Path

from rig.errors import RigError
from rig.web.access import is_loopback, new_token, write_token
from rig.web.app import Web, WebOptions

EXPOSED_WARNING = (
    "WARNING: rig web is serving beyond this machine on {host}:{port}. Anyone who can reach that "
    "address and has the token can watch every trial, read every log and batch table in {logs} and "
    "{tables}, start protocols from {protocols}, and stop the rig. The traffic is plain HTTP: the "
    "token can be read on the network. Serve on 127.0.0.1 (the default) unless the network is the lab's own.")


def bind(host: str, port: int) -> socket.socket:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise RigError(f"rig web: cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    sock.listen(128)
    sock.setblocking(False)
    return sock


def refuse_unexposed(host: str, expose: bool) -> None:
    if not is_loopback(host) and not expose:
        raise RigError(f"rig web: --host {host} serves beyond this machine; say so with --expose "
                       "(anyone who reaches it with the token can drive the rig)")


class WebServer:
    """The app on a bound socket, run by uvicorn (in this thread with `run`, or in a thread)."""

    def __init__(self, opts: WebOptions, token_dir: Path | None = None) -> None:
        import uvicorn

        refuse_unexposed(opts.host, opts.exposed)
        self.sock = bind(opts.host, opts.port)
        opts.port = self.sock.getsockname()[1]
        opts.token = opts.token or new_token()
        self.opts = opts
        self.token_file = write_token(opts.token, opts.port, token_dir)
        self.web = Web(opts)
        shown = f"[{opts.host}]" if ":" in opts.host else opts.host
        self.url = f"http://{shown}:{opts.port}/?token={opts.token}"
        config = uvicorn.Config(self.web.app, log_level="warning", ws="websockets-sansio", lifespan="on",
                                ws_ping_interval=None, timeout_graceful_shutdown=2)
        self.server = uvicorn.Server(config)
        self._thread: threading.Thread | None = None

    def run(self) -> None:
        self.server.run(sockets=[self.sock])

    def start_in_thread(self) -> None:
        self._thread = threading.Thread(target=self.run, name="rig-web", daemon=True)
        self._thread.start()
        import time

        deadline = time.monotonic() + 10
        while not self.server.started and time.monotonic() < deadline:
            time.sleep(0.02)

    def stop(self) -> None:
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(10)
        self.sock.close()
        self.token_file.unlink(missing_ok=True)


def serve(opts: WebOptions) -> int:
    srv = WebServer(opts)
    if opts.exposed:
        print(EXPOSED_WARNING.format(host=opts.host, port=opts.port, logs=opts.logs, tables=opts.tables,
                                     protocols=opts.protocols), file=sys.stderr)
    print(f"rig web: the daemon at {opts.socket_path}, logs in {opts.logs}, protocols in {opts.protocols}, "
          f"tables in {opts.tables}", flush=True)
    print(f"rig web: token in {srv.token_file} (readable by you only)", flush=True)
    print(f"open    {srv.url}", flush=True)
    try:
        srv.run()
    finally:
        srv.token_file.unlink(missing_ok=True)
    return 0
