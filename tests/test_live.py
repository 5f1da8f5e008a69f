"""The live view over the Foxglove WebSocket protocol, as a viewer sees it: a client of our own
(`websockets`, subprotocol foxglove.sdk.v1) subscribes to the log's channels during a daemon
trial; another connects, subscribes and never reads."""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import threading
import time

import pytest
from rig.sim.params import SimParams
from rig.sim.server import WireSim, free_tcp_port

from rig.recording.logs import read_log
from rig.recording.messages import SAMPLE
from tests.test_daemon import DaemonProc

pytest.importorskip("foxglove", reason="the live view needs foxglove-sdk (pip install '.[live]')")
websockets = pytest.importorskip("websockets", reason="the test client needs websockets: pip install '.[test]'")

TRIAL = ("name: live\nsteps:\n  - ramp: {to_mm: 4, speed_mm_s: 4}\n  - hold: {duration_s: 6}\n"
         "  - return: {speed_mm_s: 5}\n")


class FoxgloveClient(threading.Thread):
    """Subscribes to `topic` and collects every message (or, `reading=False`, stops reading)."""

    def __init__(self, port: int, topic: str, reading: bool = True) -> None:
        super().__init__(daemon=True)
        self.port, self.topic, self.reading = port, topic, reading
        self.advertised: dict = {}
        self.messages: list[dict] = []
        self.subscribed = threading.Event()
        self.done = threading.Event()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported to the test
            self.error = exc
            self.subscribed.set()

    async def _main(self) -> None:
        sock = socket.create_connection(("127.0.0.1", self.port))
        if not self.reading:  # a tiny window: the server's sends to this viewer stall for real
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        async with websockets.connect(f"ws://127.0.0.1:{self.port}", subprotocols=["foxglove.sdk.v1"],
                                      sock=sock, max_queue=None if self.reading else 1,
                                      close_timeout=0.5) as ws:
            while not self.subscribed.is_set():
                msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
                if msg.get("op") == "advertise":
                    for ch in msg["channels"]:
                        self.advertised[ch["topic"]] = ch
                    if self.topic in self.advertised:
                        cid = self.advertised[self.topic]["id"]
                        await ws.send(json.dumps({"op": "subscribe",
                                                  "subscriptions": [{"id": 1, "channelId": cid}]}))
                        self.subscribed.set()
            if not self.reading:
                while not self.done.is_set():  # connected and subscribed, reading nothing
                    await asyncio.sleep(0.05)
                return
            while not self.done.is_set():
                try:
                    data = await asyncio.wait_for(ws.recv(), 0.2)
                except TimeoutError:
                    continue
                if isinstance(data, bytes) and data[0] == 0x01:
                    (sub_id,) = struct.unpack_from("<I", data, 1)  # then u64 log time, then the payload
                    assert sub_id == 1
                    self.messages.append(json.loads(data[13:]))


def test_every_tick_reaches_a_live_viewer_and_a_stalled_one_costs_nothing(tmp_path):
    port = free_tcp_port()
    with WireSim(SimParams(), rtu=False) as sim:
        d = DaemonProc(tmp_path, sim, extra={"daemon": {"live": {"port": port}}})
        reader = FoxgloveClient(port, "/rig/sample")
        stalled = FoxgloveClient(port, "/rig/sample", reading=False)
        try:
            for c in (reader, stalled):
                c.start()
                assert c.subscribed.wait(10) and c.error is None, c.error
            # the same channel and schema as the log's
            ch = reader.advertised["/rig/sample"]
            assert ch["encoding"] == "json" and ch["schemaEncoding"] == "jsonschema"
            assert json.loads(ch["schema"]) == SAMPLE.schema
            assert {"/rig/sample", "/rig/event", "/rig/health"} <= set(reader.advertised)
            r = d.start_trial(TRIAL)
            assert r["ok"], r
            assert d.wait_idle()["last"]["outcome"] == "completed"
            time.sleep(0.5)  # the last messages on their way
        finally:
            for c in (reader, stalled):
                c.done.set()
            d.stop()  # the server goes: the stalled client's connection with it
            for c in (reader, stalled):
                c.join(10)
        log = read_log(r["log"])
        seqs = [m["seq"] for m in reader.messages if m.get("seq") is not None]
        assert seqs == list(range(log.n)), (len(seqs), log.n)  # every tick, in order, none twice
        assert [m["force_N"] for m in reader.messages] == list(log.samples["force_N"])
        health = log.health[-1]
        assert health["late_ticks"] == 0 and health["missed_ticks"] == 0
        assert health["live_dropped"] == 0  # our queue never overflowed: the SDK's backlog absorbs the stall


def test_the_shipped_layout_plots_only_fields_the_log_has():
    from rig.recording.messages import SCHEMAS
    from tests.conftest import ROOT

    layout = json.loads((ROOT / "config" / "foxglove-layout.json").read_text())
    panels = layout["configById"]
    paths = [p["value"] for cfg in panels.values() for p in cfg.get("paths", [])]
    assert paths
    for path in paths:
        topic, field = path.rsplit(".", 1)
        assert field in SCHEMAS[topic]["properties"], path
    topics = [cfg["topicPath"] for cfg in panels.values() if "topicPath" in cfg]
    assert all(t in SCHEMAS for t in topics)

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)
