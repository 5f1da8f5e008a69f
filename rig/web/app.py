"""`rig web`: the lab in a browser (Starlette, served by uvicorn; plots by plotly.js).

Pages: the console (the live trial, a start from the protocol library, STOP / HOLD / ESTOP),
the history of every trial in the log folder, and batch tables as maps. The app is a client of
the daemon's socket and a reader of files: it never opens a device, and every move it asks for
goes through the daemon's checks. Every asset comes from the installed packages (this one's
`static/` and plotly.js from the plotly package), so it works offline.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.resources
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, HTMLResponse, JSONResponse, PlainTextResponse, Response
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from rig.errors import RigError
from rig.service.client import request
from rig.specs.config import RigConfig
from rig.web import console
from rig.web.access import Guard, cookie_name
from rig.web.history import History
from rig.web.live import Hub
from rig.web.maps import Maps

STATIC = Path(__file__).resolve().parent / "static"
PAGES = {"/": "console.html", "/history": "history.html", "/trial": "trial.html", "/compare": "compare.html",
         "/maps": "maps.html"}
STOP_TIMEOUT_S = 5.0


def plotly_js() -> Path:
    return Path(str(importlib.resources.files("plotly") / "package_data" / "plotly.min.js"))


@dataclass
class WebOptions:
    socket_path: Path
    logs: Path
    protocols: Path
    tables: Path
    config: RigConfig = field(default_factory=RigConfig)
    token: str = ""
    host: str = "127.0.0.1"
    port: int = 0
    exposed: bool = False
    say: object = None  # a function of one string: the server's log (stderr by default)


class Web:
    def __init__(self, opts: WebOptions) -> None:
        self.opts = opts
        self.hub = Hub(opts.socket_path)
        self.history = History(opts.logs)
        self.maps = Maps(opts.tables)
        self.say = opts.say or (lambda msg: print(f"rig web: {msg}", file=sys.stderr, flush=True))
        self.stops: list[dict] = []  # every STOP/HOLD/ESTOP: the click's time, the request's, the reply's
        routes = [Route(path, self.page) for path in PAGES]
        routes += [
            Route("/static/plotly.min.js", self.plotly),
            Route("/static/{name}", self.static),
            WebSocketRoute("/ws", self.ws),
            Route("/api/state", self.api_state),
            Route("/api/protocols", self.api_protocols),
            Route("/api/check", self.api_check, methods=["POST"]),
            Route("/api/start", self.api_start, methods=["POST"]),
            Route("/api/stop", self.api_stop, methods=["POST"]),
            Route("/api/estop", self.api_estop, methods=["POST"]),
            Route("/api/reset-alarm", self.api_reset_alarm, methods=["POST"]),
            Route("/api/trials", self.api_trials),
            Route("/api/trials.csv", self.api_trials_csv),
            Route("/api/trials.xlsx", self.api_trials_xlsx),
            Route("/api/trial", self.api_trial),
            Route("/api/compare", self.api_compare),
            Route("/api/journal", self.api_journal),
            Route("/files/log", self.file_log),
            Route("/files/csv", self.file_csv),
            Route("/api/tables", self.api_tables),
            Route("/api/map", self.api_map),
            Route("/api/curve", self.api_curve),
        ]
        inner = Starlette(routes=routes, lifespan=self._lifespan)
        self.app = Guard(inner, opts.token, opts.port, opts.host, exposed=opts.exposed)

    @contextlib.asynccontextmanager
    async def _lifespan(self, app):
        self.hub.start()
        try:
            yield
        finally:
            await asyncio.to_thread(self.hub.close)

    # ------------------------------------------------------------------ pages and assets
    async def page(self, req: Request) -> Response:
        html = (STATIC / PAGES[req.url.path]).read_text()
        resp = HTMLResponse(html, headers={"cache-control": "no-store"})
        token = req.query_params.get("token")
        if token:  # the Guard checked it: remembered for the page's own requests
            resp.set_cookie(cookie_name(self.opts.port), token, httponly=True, samesite="strict")
        return resp

    async def plotly(self, req: Request) -> Response:
        return FileResponse(plotly_js(), media_type="text/javascript",
                            headers={"cache-control": "private, max-age=86400"})

    async def static(self, req: Request) -> Response:
        name = req.path_params["name"]
        path = STATIC / name
        if "/" in name or name.startswith(".") or not path.is_file():
            return PlainTextResponse("not found", 404)
        return FileResponse(path, headers={"cache-control": "no-cache"})

    # ------------------------------------------------------------------ live
    async def ws(self, sock: WebSocket) -> None:
        await sock.accept()
        q = self.hub.subscribe()
        try:
            await sock.send_text(self.hub.hello())
            while True:
                await sock.send_text(await q.get())
        except (WebSocketDisconnect, RuntimeError, OSError):
            pass
        finally:
            self.hub.unsubscribe(q)

    # ------------------------------------------------------------------ console
    async def _daemon(self, obj: dict, timeout_s: float = 10.0) -> dict:
        try:
            return await asyncio.to_thread(request, self.opts.socket_path, obj, timeout_s)
        except RigError as exc:
            return {"ok": False, "error": str(exc)}

    async def api_state(self, req: Request) -> Response:
        cfg = self.opts.config
        return JSONResponse({"status": self.hub.status, "zero": console.zero_state(cfg),
                             "limits": {"max_force_N": cfg.limits.max_force_N,
                                        "max_speed_mm_s": cfg.limits.max_speed_mm_s,
                                        "travel_mm": list(cfg.limits.travel_mm)},
                             "viewers": self.hub.viewers, "exposed": self.opts.exposed,
                             "logs": str(self.opts.logs)})

    async def api_protocols(self, req: Request) -> Response:
        return JSONResponse({"folder": str(self.opts.protocols),
                             "protocols": await asyncio.to_thread(console.protocol_files, self.opts.protocols)})

    def _start_mm(self) -> float | None:
        snap = self.hub.status.get("snapshot") or {}
        pos = snap.get("position_mm") if self.hub.status.get("state") == "idle" else None
        return pos if isinstance(pos, int | float) else None

    async def _body(self, req: Request) -> dict:
        with contextlib.suppress(ValueError):
            body = await req.json()
            if isinstance(body, dict):
                return body
        return {}

    async def api_check(self, req: Request) -> Response:
        body = await self._body(req)
        out = await asyncio.to_thread(console.check, self.opts.protocols, str(body.get("file", "")),
                                      self.opts.config, self._start_mm())
        out.pop("text", None)
        return JSONResponse(out)

    async def api_start(self, req: Request) -> Response:
        body = await self._body(req)
        checked = await asyncio.to_thread(console.check, self.opts.protocols, str(body.get("file", "")),
                                          self.opts.config, self._start_mm())
        if not checked["ok"]:
            return JSONResponse({"ok": False, "error": f"not started: {checked['error']}", "check": checked})
        texts = {k: str(body.get(k) or "") for k in ("specimen", "operator", "notes")}
        reply = await self._daemon({"cmd": "start", "protocol_text": checked.pop("text"),
                                    "protocol_path": checked["path"],
                                    "specimen": texts["specimen"] or "specimen",
                                    "operator": texts["operator"], "notes": texts["notes"]})
        if reply.get("ok"):
            self.hub.limits_by_log[reply.get("log", "")] = checked["limits"]
            self.hub.limits_by_log[checked["protocol"]] = checked["limits"]
            self.say(f"started '{checked['protocol']}' (specimen {texts['specimen']}) -> {reply.get('log')}")
        self.hub.nudge()
        reply["check"] = checked
        return JSONResponse(reply)

    async def _stop(self, req: Request, obj: dict, what: str) -> Response:
        received = time.time()
        body = await self._body(req)
        reply = await self._daemon(obj, STOP_TIMEOUT_S)
        answered = time.time()
        clicked = body.get("clicked_ms")
        entry = {"what": what, "clicked_ms": clicked if isinstance(clicked, int | float) else None,
                 "received_ms": received * 1000, "answered_ms": answered * 1000, "ok": bool(reply.get("ok")),
                 "message": reply.get("message") or reply.get("error", "")}
        self.stops.append(entry)
        self.say(f"{what}: clicked {entry['clicked_ms']}, received {entry['received_ms']:.1f}, answered "
                 f"{entry['answered_ms']:.1f} (ms since the epoch): {entry['message']}")
        self.hub.nudge()
        return JSONResponse(reply)

    async def api_stop(self, req: Request) -> Response:
        body = await self._body(req)
        mode = "hold" if body.get("mode") == "hold" else "abort"
        return await self._stop(req, {"cmd": "stop", "mode": mode}, "HOLD" if mode == "hold" else "STOP")

    async def api_estop(self, req: Request) -> Response:
        return await self._stop(req, {"cmd": "estop"}, "ESTOP")

    async def api_reset_alarm(self, req: Request) -> Response:
        reply = await self._daemon({"cmd": "reset_alarm"})
        self.hub.nudge()
        return JSONResponse(reply)

    # ------------------------------------------------------------------ history
    async def api_trials(self, req: Request) -> Response:
        rows = await asyncio.to_thread(self.history.rows)
        return JSONResponse({"folder": str(self.opts.logs), "trials": rows})

    async def api_trials_csv(self, req: Request) -> Response:
        text = await asyncio.to_thread(self.history.csv_text)
        return Response(text, media_type="text/csv",
                        headers={"content-disposition": 'attachment; filename="trials.csv"'})

    async def api_trials_xlsx(self, req: Request) -> Response:
        try:
            data = await asyncio.to_thread(self.history.xlsx_bytes)
        except RigError as exc:
            return PlainTextResponse(str(exc), 501)
        return Response(data, media_type="application/vnd.openxmlformats-officedocument.spreadsheetml.sheet",
                        headers={"content-disposition": 'attachment; filename="trials.xlsx"'})

    async def api_compare(self, req: Request) -> Response:
        try:
            out = await asyncio.to_thread(self.history.compare, req.query_params.getlist("file"))
        except RigError as exc:
            return JSONResponse({"ok": False, "error": str(exc)}, 404)
        return Response(json.dumps({"ok": True, **out}, default=str), media_type="application/json")

    async def api_journal(self, req: Request) -> Response:
        """The campaign's journal: the running one's (or the last one's) as the daemon names it."""
        camp = self.hub.status.get("campaign") or {}
        out = await asyncio.to_thread(console.journal, self.opts.logs, camp.get("journal"))
        out["campaign"] = camp or None
        return JSONResponse(out)

    async def api_trial(self, req: Request) -> Response:
        try:
            out = await asyncio.to_thread(self.history.trial, req.query_params.get("file", ""))
        except RigError as exc:
            return JSONResponse({"ok": False, "error": str(exc)}, 404)
        return Response(json.dumps({"ok": True, **out}, default=str), media_type="application/json")

    async def file_log(self, req: Request) -> Response:
        try:
            path = self.history.resolve(req.query_params.get("file", ""))
        except RigError as exc:
            return PlainTextResponse(str(exc), 404)
        return FileResponse(path, media_type="application/octet-stream", filename=path.name)

    async def file_csv(self, req: Request) -> Response:
        try:
            name, data = await asyncio.to_thread(self.history.samples_csv, req.query_params.get("file", ""))
        except RigError as exc:
            return PlainTextResponse(str(exc), 404)
        return Response(data, media_type="text/csv",
                        headers={"content-disposition": f'attachment; filename="{name}"'})

    # ------------------------------------------------------------------ maps
    async def api_tables(self, req: Request) -> Response:
        tables = await asyncio.to_thread(self.maps.tables)
        return JSONResponse({"folder": str(self.opts.tables), "tables": tables})

    async def api_map(self, req: Request) -> Response:
        try:
            out = await asyncio.to_thread(self.maps.map, req.query_params.get("table", ""))
        except RigError as exc:
            return JSONResponse({"ok": False, "error": str(exc)}, 404)
        return Response(json.dumps({"ok": True, **out}, default=str), media_type="application/json")

    async def api_curve(self, req: Request) -> Response:
        try:
            row = int(req.query_params.get("row", "-1"))
            out = await asyncio.to_thread(self.maps.curve, req.query_params.get("table", ""), row)
        except (RigError, ValueError) as exc:
            return JSONResponse({"ok": False, "error": str(exc)}, 404)
        return Response(json.dumps({"ok": True, **out}, default=str), media_type="application/json")
