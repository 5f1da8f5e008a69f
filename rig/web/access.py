"""Who may use `rig web`: a token on every route and websocket, no foreign Origin, loopback unless told.

As Jupyter does: a random token is made at start, printed in the URL and written to a file only
its user can read (mode 0600, in a 0700 directory). A request carries it as `?token=` (the first
page, which then sets a cookie for the rest), the cookie, or an `Authorization: token ...`
header; without it every page, API route and websocket is refused (401). A request whose Origin
is not this server's own (another site's page in the same browser) is refused (403), and so is
one whose Host is not a name of this server's (a DNS-rebinding page), so a page elsewhere can
neither read nor drive the rig even from a browser that holds the cookie.
"""

from __future__ import annotations

import hmac
import os
import secrets
from http.cookies import SimpleCookie
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

LOOPBACK = ("127.0.0.1", "::1", "localhost")


def new_token() -> str:
    return secrets.token_urlsafe(32)


def token_dir() -> Path:
    """$XDG_RUNTIME_DIR/rig, else ~/.local/state/rig: the user's own."""
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    base = Path(runtime) if runtime else Path.home() / ".local" / "state"
    return base / "rig"


def write_token(token: str, port: int, folder: Path | None = None) -> Path:
    """The token in `folder`/web-PORT.token, readable by its user only."""
    folder = folder or token_dir()
    folder.mkdir(parents=True, exist_ok=True, mode=0o700)
    path = folder / f"web-{port}.token"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, (token + "\n").encode())
    finally:
        os.close(fd)
    return path


def is_loopback(host: str) -> bool:
    return host in LOOPBACK or host.startswith("127.")


def cookie_name(port: int) -> str:
    return f"rig-web-{port}"


class Guard:
    """ASGI middleware: the token and the Origin checked on every HTTP request and websocket."""

    def __init__(self, app, token: str, port: int, host: str, exposed: bool = False) -> None:
        self.app = app
        self.token = token
        self.port = port
        self.cookie = cookie_name(port)
        self.exposed = exposed
        names = {"127.0.0.1", "localhost", "[::1]"} | ({host} if not is_loopback(host) else set())
        self.hosts = {f"{n}:{port}" for n in names}

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        why = self.refusal(scope, headers)
        if why is None:
            return await self.app(scope, receive, send)
        status, text = why
        if scope["type"] == "websocket":
            # closing before accepting refuses the handshake (HTTP 403 to the client)
            await receive()  # websocket.connect
            await send({"type": "websocket.close", "code": 4000 + status, "reason": text[:120]})
            return None
        body = text.encode()
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", b"text/plain; charset=utf-8"),
                                (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})
        return None

    def refusal(self, scope, headers: dict[str, str]) -> tuple[int, str] | None:
        host = headers.get("host", "")
        if not self.exposed and host not in self.hosts:
            return 403, f"refused: Host {host!r} is not this server (use http://127.0.0.1:{self.port}/)"
        origin = headers.get("origin")
        if origin is not None:
            o = urlsplit(origin)
            if o.scheme not in ("http", "https") or o.netloc != host:
                return 403, f"refused: a request from another site ({origin})"
        if not self.has_token(scope, headers):
            return 401, ("refused: this server needs its token: open the URL `rig web` printed "
                         "(http://HOST:PORT/?token=...), or read it from its token file")
        return None

    def has_token(self, scope, headers: dict[str, str]) -> bool:
        given = []
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        given += query.get("token", [])
        auth = headers.get("authorization", "")
        if auth.lower().startswith("token "):
            given.append(auth[6:].strip())
        if "cookie" in headers:
            jar = SimpleCookie()
            try:
                jar.load(headers["cookie"])
            except Exception:  # noqa: BLE001 - a malformed cookie header is no token
                jar = SimpleCookie()
            if self.cookie in jar:
                given.append(jar[self.cookie].value)
        return any(hmac.compare_digest(g.encode(), self.token.encode()) for g in given)
