"""Live view: the log's channels, with the log's schemas, published over the Foxglove
WebSocket protocol (the `foxglove-sdk` package, optional extra `rig[live]`).

The loop only appends to a bounded queue (oldest dropped and counted, reported in
`/rig/health` as `live_dropped`); a thread of its own hands messages to the SDK's
server, whose per-client backlog is bounded too. A slow or vanished viewer costs the
loop an append, never a wait.
"""

from __future__ import annotations

import json
import threading
from collections import deque
from typing import Any

from rig.errors import RigError
from rig.recording.messages import SCHEMAS

INSTALL_HINT = "the live view needs the optional extra: python3 -m pip install 'indentation-rig[live]'"


class LiveView:
    """A Foxglove WebSocket server with one channel per log topic."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, *, max_queue: int = 2000,
                 backlog: int = 1000) -> None:
        try:
            import foxglove
        except ImportError:
            raise RigError(INSTALL_HINT) from None
        self._ctx = foxglove.Context()
        try:
            self._server = foxglove.start_server(name="indentation-rig", host=host, port=port,
                                                 context=self._ctx, message_backlog_size=backlog)
        except Exception as exc:  # noqa: BLE001 - the SDK's bind errors have no common type
            raise RigError(f"live view: cannot listen on {host}:{port}: {exc}") from None
        self.host = host
        self.port = self._server.port
        self._channels = {
            topic: foxglove.Channel(topic, message_encoding="json", context=self._ctx,
                                    schema=foxglove.Schema(name=schema["title"], encoding="jsonschema",
                                                           data=json.dumps(schema).encode()))
            for topic, schema in SCHEMAS.items()}
        self._q: deque[tuple[str, int, dict[str, Any]]] = deque(maxlen=max_queue)
        self.dropped = 0
        self.published = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    # ---------------------------------------------------------------- loop side
    def put(self, topic: str, log_time_ns: int, message: dict[str, Any]) -> None:
        if len(self._q) == self._q.maxlen:
            self.dropped += 1  # deque(maxlen) drops the oldest on append
        self._q.append((topic, log_time_ns, message))
        self._wake.set()

    # ---------------------------------------------------------------- publisher
    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.1)
            self._wake.clear()
            while self._q:
                try:
                    topic, stamp, message = self._q.popleft()
                except IndexError:
                    break
                channel = self._channels.get(topic)
                if channel is not None:
                    channel.log(message, log_time=stamp)
                    self.published += 1

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self.thread.join(2.0)
        self._server.stop()
