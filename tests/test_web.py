"""`rig web`: access (the token on every route and websocket, no foreign Origin, loopback by
default) and, in Debian's chromium, the console on a daemon over the simulated rig: a start from
the page, the live plot's updates per second, ESTOP from the page to the simulated drive's wire
(8 tries here, 20 in tests/bench/test_bench_web.py; p95 under 100 ms), the history, a trial's
page and a batch table's maps. The browser test writes the documentation's screenshots
(docs/_static/web-*.png, 1280x800)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import stat
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

pytest.importorskip("starlette", reason="rig web needs the web extra: pip install '.[web]'")

from rig.web.access import is_loopback
from rig.web.app import PAGES, WebOptions
from rig.web.server import WebServer, refuse_unexposed
from tests.conftest import PROTOCOLS, ROOT

API_GET = ["/api/state", "/api/protocols", "/api/trials", "/api/trials.csv", "/api/trial?file=x.mcap",
           "/files/log?file=x.mcap", "/api/tables", "/api/map?table=t.csv", "/api/curve?table=t.csv&row=0",
           "/static/common.js", "/static/plotly.min.js"]
API_POST = ["/api/check", "/api/start", "/api/stop", "/api/estop", "/api/reset-alarm"]
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"


@pytest.fixture
def web(tmp_path):
    """rig web in this process, on a socket where no daemon listens (access needs none)."""
    srv = WebServer(WebOptions(socket_path=tmp_path / "none.sock", logs=tmp_path / "trials",
                               protocols=PROTOCOLS, tables=tmp_path), token_dir=tmp_path / "run")
    srv.start_in_thread()
    try:
        yield srv
    finally:
        srv.stop()


def _http(url: str, *, method: str = "GET", headers: dict | None = None, body: bytes | None = None):
    req = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def _ws(url: str, headers: dict | None = None):
    from websockets.sync.client import connect

    return connect(url, additional_headers=headers or {}, open_timeout=5)


# ------------------------------------------------------------------ access
def test_every_page_api_route_and_websocket_refuses_a_request_without_the_token(web):
    from websockets.exceptions import InvalidStatus

    base = f"http://127.0.0.1:{web.opts.port}"
    wrong = {"Authorization": "token not-the-token"}
    for path in [*PAGES, *API_GET]:
        for headers in ({}, wrong):
            status, body = _http(base + path, headers=headers)
            assert status == 401, (path, status, body[:200])
            assert b"needs its token" in body
    for path in API_POST:
        status, _ = _http(base + path, method="POST", body=b"{}", headers={"content-type": "application/json"})
        assert status == 401, path
    for url in (f"ws://127.0.0.1:{web.opts.port}/ws", f"ws://127.0.0.1:{web.opts.port}/ws?token=wrong"):
        with pytest.raises(InvalidStatus) as refused:
            _ws(url)
        assert refused.value.response.status_code == 403
    # with it: the pages, the assets (plotly.js from the installed package) and the websocket
    for path in PAGES:
        status, body = _http(f"{base}{path}?token={web.opts.token}")
        assert status == 200 and b"rig web" in body, path
    status, body = _http(base + "/static/plotly.min.js", headers={"Authorization": f"token {web.opts.token}"})
    assert status == 200 and len(body) > 1_000_000
    with _ws(f"ws://127.0.0.1:{web.opts.port}/ws?token={web.opts.token}") as ws:
        hello = json.loads(ws.recv(5))
    assert hello["kind"] == "hello"
    # the token file: this user's only
    assert stat.S_IMODE(web.token_file.stat().st_mode) == 0o600
    assert web.token_file.read_text().strip() == web.opts.token


def test_a_foreign_origin_or_host_is_refused_even_with_the_token(web):
    from websockets.exceptions import InvalidStatus

    port = web.opts.port
    base = f"http://127.0.0.1:{port}"
    auth = {"Authorization": f"token {web.opts.token}"}
    for origin in ("http://evil.example", f"http://127.0.0.1:{port + 1}", "null"):
        status, body = _http(base + "/", headers={**auth, "Origin": origin})
        assert status == 403 and b"another site" in body, origin
        status, _ = _http(base + "/api/estop", method="POST", body=b"{}", headers={**auth, "Origin": origin})
        assert status == 403, origin
        with pytest.raises(InvalidStatus) as refused:
            _ws(f"ws://127.0.0.1:{port}/ws", headers={**auth, "Origin": origin})
        assert refused.value.response.status_code == 403
    # a page of another name for this address (DNS rebinding) is refused too
    status, body = _http(base + "/api/state", headers={**auth, "Host": f"evil.example:{port}"})
    assert status == 403 and b"is not this server" in body
    # its own origin is welcome
    status, _ = _http(base + "/api/state", headers={**auth, "Origin": base})
    assert status == 200


def test_the_default_bind_is_loopback_and_beyond_it_needs_expose(web, tmp_path, capsys):
    from rig.cli import build_parser

    args = build_parser().parse_args(["web"])
    assert args.host == "127.0.0.1" and not args.expose
    assert web.sock.getsockname()[0] == "127.0.0.1"
    assert is_loopback("127.0.0.1") and not is_loopback("0.0.0.0")
    from rig.errors import RigError

    with pytest.raises(RigError, match="--expose"):
        refuse_unexposed("0.0.0.0", False)
    refuse_unexposed("0.0.0.0", True)
    from rig.cli import main

    assert main(["web", "--host", "0.0.0.0", "--port", "0", "--socket", str(tmp_path / "s")]) != 0
    assert "--expose" in capsys.readouterr().err


def test_the_console_shows_a_running_campaigns_journal_in_words(web, tmp_path):
    """The journal the daemon names in its status (rig start --characterize writes it in the log
    folder), read by /api/journal: each event in words; one outside the log folder is refused."""
    folder = tmp_path / "trials" / "characterize-pig"
    folder.mkdir(parents=True)
    path = folder / "characterize-pig-20261128-101500.jsonl"
    events = [{"event": "start", "journal": str(path), "specimen": "pig", "model": "proposed"},
              {"event": "trial", "n": 1, "protocol": "first look", "why": "the surface by force", "size": {}},
              {"event": "ran", "n": 1, "outcome": "completed", "log": str(folder / "t1.mcap")},
              {"event": "fit", "trials": 1, "model": "hertz + relaxation", "adequate": False},
              {"event": "decision", "kind": "separate", "why": "relaxation and creep look alike"}]
    path.write_text("".join(json.dumps({"t": 1.8e9 + i, **e}) + "\n" for i, e in enumerate(events)))
    hub = web.web.hub
    hub.close()  # no daemon here: the status is what a characterizing daemon says
    camp = {"specimen": "pig", "user": "ann", "started": "10:15:00", "phase": "decided: separate", "trials": 1,
            "status": "running", "journal": str(path)}
    hub.status = {"ok": True, "state": "characterizing", "campaign": camp}
    auth = {"Authorization": f"token {web.opts.token}"}
    status, body = _http(f"http://127.0.0.1:{web.opts.port}/api/journal", headers=auth)
    j = json.loads(body)
    assert status == 200 and j["ok"] and j["events"] == 5, j
    assert [x["text"] for x in j["lines"]] == [
        "started: specimen pig, model proposed", "trial 1: first look (the surface by force)",
        "trial 1 ran: completed - log t1.mcap", "fitted 1 trials: hertz + relaxation (not adequate)",
        "decided: separate - relaxation and creep look alike"]
    assert j["campaign"]["phase"] == "decided: separate"
    if os.path.exists(CHROMIUM) and os.path.exists(CHROMEDRIVER):  # and on the console's page
        from selenium.webdriver.common.by import By

        driver = _browser()
        try:
            driver.get(f"http://127.0.0.1:{web.opts.port}/?token={web.opts.token}")
            items = _wait(lambda: driver.find_elements(By.CSS_SELECTOR, "#journal li"), 15, "the journal")
            assert [li.text for li in items][-1] == "decided: separate - relaxation and creep look alike"
            assert "specimen pig" in driver.find_element(By.ID, "campaign-head").text
        finally:
            driver.quit()
    hub.status = {"ok": True, "state": "characterizing", "campaign": {**camp, "journal": "/etc/passwd.jsonl"}}
    j = json.loads(_http(f"http://127.0.0.1:{web.opts.port}/api/journal", headers=auth)[1])
    assert not j["ok"] and "not in the log folder" in j["error"]


def test_history_exports_excel_and_a_trials_csv_and_compares_trials(web):
    """Two short logs written by the simulated rig in this process: the table as an Excel
    workbook (numbers as numbers), a trial's samples as `rig replay --csv` writes them, and
    both trials' data for one plot."""
    openpyxl = pytest.importorskip("openpyxl", reason="Excel export needs openpyxl (the web extra)")
    from rig.recording.logs import export_csv, read_log

    logs = _two_logs(web.opts.logs)
    base, auth = f"http://127.0.0.1:{web.opts.port}", {"Authorization": f"token {web.opts.token}"}
    status, body = _http(base + "/api/trials.xlsx", headers=auth)
    assert status == 200 and body[:2] == b"PK"
    import io

    ws = openpyxl.load_workbook(io.BytesIO(body)).active
    table = list(ws.values)
    assert table[0][:4] == ("started", "specimen", "protocol", "outcome") and len(table) == 3
    peak = table[0].index("peak force (N)")
    assert all(isinstance(r[peak], float) for r in table[1:]), table
    assert sorted(r[1] for r in table[1:]) == ["a", "b"]
    history = web.web.history
    history.rows = lambda: [{"specimen": '=HYPERLINK("http://evil.example")', "peak_force_N": 1.5}]
    ws = openpyxl.load_workbook(io.BytesIO(history.xlsx_bytes())).active
    assert ws["B2"].data_type == "s" and ws["B2"].value.startswith("=HYPERLINK") and ws["E2"].value == 1.5
    rel = logs[0].name
    status, body = _http(f"{base}/files/csv?file={rel}", headers=auth)
    export_csv(read_log(logs[0]), web.opts.logs / "replay.csv")
    assert status == 200 and body == (web.opts.logs / "replay.csv").read_bytes()
    status, body = _http(f"{base}/api/compare?file={logs[0].name}&file={logs[1].name}", headers=auth)
    got = json.loads(body)
    assert status == 200 and [t["label"].split()[0] for t in got["trials"]] == ["a", "b"]
    assert all(len(t["t_s"]) == len(t["indentation_mm"]) == len(t["force_N"]) > 10 for t in got["trials"])
    status, body = _http(f"{base}/api/compare?file=../../etc/passwd", headers=auth)
    assert status == 404


def _two_logs(out: Path) -> list[Path]:
    """Two short trials on the simulated rig in this process (no daemon, no wire)."""
    from rig.cli import main

    for name in ("a", "b"):
        assert main(["run", str(PROTOCOLS / "demo.yaml"), "--speed", "0", "--quiet", "--specimen", name,
                     "--out", str(out)]) == 0
    return sorted(out.glob("*.mcap"))


# ------------------------------------------------------------------ the browser
# an estop leaves the probe where it stopped (in the specimen: the tries start from there, as confirmed with
# from_contact): they go 2 mm out and 2 mm in by turns
FAST = ("name: ramp {to:g} mm\nsteps:\n  - ramp: {{to_mm: {to:g}, speed_mm_s: 0.5}}\n"
        "  - return: {{to_mm: 0, speed_mm_s: 5}}\n")


def _browser():
    if not (os.path.exists(CHROMIUM) and os.path.exists(CHROMEDRIVER)):
        pytest.skip("no chromium and chromedriver here (Debian: apt-get install chromium chromium-driver)")
    pytest.importorskip("selenium", reason="the browser tests drive chromium with selenium")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--window-size=1280,800",
                 "--disable-dev-shm-usage"):
        opts.add_argument(flag)
    os.environ.setdefault("SE_OFFLINE", "true")  # selenium-manager must not look for a driver online
    return webdriver.Chrome(options=opts, service=Service(CHROMEDRIVER))


def _wait(fn, timeout_s: float = 20.0, what="", every_s: float = 0.02) -> object:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(Exception):
            got = fn()
            if got:
                return got
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what() if callable(what) else what or fn}")


class WebProcess:
    """`rig web` as the lab runs it: its own process, a client of the daemon's socket."""

    def __init__(self, tmp: Path, socket_path: Path, tables: Path) -> None:
        env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp / "run"), "PYTHONUNBUFFERED": "1"}
        (tmp / "run").mkdir(mode=0o700, exist_ok=True)
        self.log = open(tmp / "web.log", "w+")  # noqa: SIM115 - closed in close()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rig", "web", "--port", "0", "--socket", str(socket_path), "--logs",
             str(tmp / "trials"), "--protocols", str(PROTOCOLS), "--tables", str(tables)],
            stdout=subprocess.PIPE, stderr=self.log, text=True, env=env, cwd=tmp)
        self.url = ""
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not self.url:
            line = self.proc.stdout.readline()
            if not line:
                break
            if line.startswith("open"):
                self.url = line.split()[1]
        if not self.url:
            self.close()
            raise AssertionError(f"rig web did not start: {(tmp / 'web.log').read_text()}")
        m = re.match(r"(http://[^/]+)/\?token=(\S+)", self.url)
        self.base, self.token = m.group(1), m.group(2)
        threading.Thread(target=self.proc.stdout.read, daemon=True, name="web-stdout").start()

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        self.log.close()


def _map_table(tmp: Path) -> Path:
    """A real batch table of a simulated 8x8 map (hertz, as the force-map tutorial asks)."""
    pytest.importorskip("afmformats", reason="the simulated map is written and read through afmformats")
    from rig.sim.afm_map import MapSpec, write_map

    from rig.analysis.batch.each import run_each
    from rig.analysis.batch.engine import BatchRequest

    maps = tmp / "tables"
    maps.mkdir()
    h5 = write_map(maps / "map8.h5", MapSpec(grid=(8, 8)), seed=2)
    table = maps / "map8.csv"
    req = BatchRequest(model="hertz", indenter="paraboloid:R=5um", segment="approach")
    run_each([str(h5)], req, table=str(table), workers=2, progress=False)
    return maps


ESTOP_TRIES = 8  # in the suite; tests/bench/test_bench_web.py makes the twenty of the figures


def test_the_console_in_a_browser_runs_the_demo_and_estops_it_within_100_ms(tmp_path):
    console_in_a_browser(tmp_path, ESTOP_TRIES)


def console_in_a_browser(tmp_path, tries: int) -> dict:
    """The console's whole path in chromium, ESTOP from the page `tries` times; the figures."""
    from selenium.webdriver.common.by import By

    driver = _browser()
    shots = ROOT / "docs" / "_static"
    figures: dict = {}
    try:
        tables = _map_table(tmp_path)
        d = RigProcess(tmp_path)
        with contextlib.ExitStack() as closing:
            closing.callback(d.close)
            web = WebProcess(tmp_path, d.sock, tables)
            try:
                driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride",  # the screenshots' size
                                       {"width": 1280, "height": 800, "deviceScaleFactor": 1, "mobile": False})
                driver.get(f"{web.base}/?token={web.token}")
                _wait(lambda: "OK" in driver.find_element(By.ID, "check").text, what="the check shown")
                assert "token" not in driver.current_url  # the cookie carries it from here
                driver.find_element(By.ID, "specimen").clear()
                driver.find_element(By.ID, "specimen").send_keys("pig-web")
                driver.find_element(By.ID, "operator").send_keys("ann")
                driver.find_element(By.ID, "btn-start").click()
                _wait(lambda: "running" in driver.find_element(By.ID, "banner").get_attribute("class"),
                      what="the trial running on the page")
                time.sleep(1.0)
                draws0 = driver.execute_script("return [window.rigLive.draws, performance.now()]")
                time.sleep(2.0)
                draws1 = driver.execute_script("return [window.rigLive.draws, performance.now()]")
                figures["updates_per_s"] = (draws1[0] - draws0[0]) / ((draws1[1] - draws0[1]) / 1000)
                took = sorted(driver.execute_script("return window.rigLive.drawMs"))
                figures["draw_ms_p50"] = took[len(took) // 2] if took else 0.0
                delays = driver.execute_script("return window.rigLive.delays.slice(-100)")
                figures["viewer_delay_p95_ms"] = sorted(delays)[int(0.95 * (len(delays) - 1))]
                _wait(lambda: driver.execute_script(  # in the specimen: a force worth seeing
                    "return Math.max(...document.getElementById('ts').data[0].y)") > 0.5, 10, "contact")
                shaded = driver.execute_script(  # the ramp shaded as a ramp (its colour), the tare as the tare
                    "return document.getElementById('ts').layout.shapes.filter(s => s.type === 'rect')"
                    ".map(s => s.fillcolor)")
                assert shaded[:2] == ["rgba(107,114,128,0.08)", "rgba(37,99,235,0.07)"], shaded
                driver.save_screenshot(str(shots / "web-console.png"))
                latencies = [_estop(driver, d)]
                st = d.wait_idle()
                _wait(lambda: "trial ended: estopped" in driver.find_element(By.ID, "banner").text,
                      what=f"the page saying estopped (it says {driver.find_element(By.ID, 'banner').text!r}; "
                           f"the daemon's last trial: {st['last']})")
                assert st["last"]["outcome"] == "estopped", st["last"]
                for i in range(tries - 1):  # each a trial of its own, stopped from the page while it moves
                    reply = d.req({"cmd": "start", "protocol_text": FAST.format(to=-2 * (-1) ** i),
                                   "protocol_path": "fast.yaml", "specimen": f"try-{i}", "from_contact": True})
                    assert reply["ok"], reply
                    _wait(lambda: (d.req({"cmd": "status"}).get("snapshot") or {}).get("step_kind") == "ramp",
                          5, "the ramp", every_s=0.05)
                    latencies.append(_estop(driver, d))
                    st = d.wait_idle()
                    assert st["last"]["outcome"] == "estopped", st["last"]
                latencies.sort()
                figures["estop_ms_p50"] = latencies[len(latencies) // 2]
                figures["estop_ms_p95"] = latencies[int(0.95 * (len(latencies) - 1))]
                figures["estop_ms_max"] = latencies[-1]
                # the history, a trial's page
                driver.get(f"{web.base}/history")
                _wait(lambda: driver.execute_script("return window.rigHistoryReady"), what="history")
                rows = driver.find_elements(By.CSS_SELECTOR, "#trials tbody tr")
                assert len(rows) == tries and "estopped" in rows[-1].text
                driver.save_screenshot(str(shots / "web-history.png"))
                link = driver.find_element(By.LINK_TEXT, rows[-1].find_element(By.TAG_NAME, "a").text)
                link.click()
                _wait(lambda: driver.execute_script("return window.rigTrialReady"), what="the trial's page")
                assert "pig-web" in driver.find_element(By.ID, "title").text
                href = driver.find_element(By.ID, "download").get_attribute("href")
                driver.save_screenshot(str(shots / "web-trial.png"))
                status, body = _http(href, headers={"Authorization": f"token {web.token}"})
                assert status == 200 and body[:8] == b"\x89MCAP0\r\n"
                href = driver.find_element(By.ID, "download-csv").get_attribute("href")
                status, body = _http(href, headers={"Authorization": f"token {web.token}"})
                assert status == 200 and body.startswith(b"t_s,position_mm,force_N,")
                # three trials of the history on one plot
                driver.get(f"{web.base}/history")
                _wait(lambda: driver.execute_script("return window.rigHistoryReady"), what="history")
                for box in driver.find_elements(By.CSS_SELECTOR, "#trials tbody input.pick")[-3:]:
                    box.click()
                driver.find_element(By.ID, "btn-compare").click()
                _wait(lambda: driver.execute_script("return window.rigCompareReady"), what="the comparison")
                names = driver.execute_script("return document.getElementById('fx').data.map(t => t.name)")
                assert len(names) == 3 and any("pig-web" in n for n in names), names
                driver.save_screenshot(str(shots / "web-compare.png"))
                # the maps: a batch table, and a pixel opened
                driver.get(f"{web.base}/maps")
                _wait(lambda: driver.execute_script("return window.rigMapsReady"), what="the maps")
                figures["map_open_ms"] = driver.execute_script("return window.rigMaps.mapMs")
                click_pixel(driver, "m-E", 5, 3)
                _wait(lambda: driver.execute_script("return window.rigMaps.curveMs"), what="the curve")
                figures["curve_open_ms"] = driver.execute_script("return window.rigMaps.curveMs")
                assert "adequate" in driver.find_element(By.ID, "verdict").text
                assert driver.find_element(By.ID, "curve-title").text.endswith("um: map8.h5")
                traces = driver.execute_script(
                    "return document.getElementById('curve').data.map(t => [t.name, t.x.length])")
                assert [t[0] for t in traces[:2]] == ["approach", "retract"] and traces[1][1] > 100, traces
                driver.find_element(By.CSS_SELECTOR, "input[name=xaxis][value=separation]").click()
                _wait(lambda: "separation" in driver.execute_script(
                    "return document.getElementById('curve').layout.xaxis.title.text"), what="the separation")
                driver.find_element(By.CSS_SELECTOR, "input[name=xaxis][value=indentation]").click()
                driver.save_screenshot(str(shots / "web-maps.png"))
            finally:
                web.close()
    finally:
        driver.quit()
    print(f"\nrig web in chromium: {json.dumps({k: round(v, 1) for k, v in figures.items()})}")
    assert figures["updates_per_s"] >= 10, figures
    assert figures["estop_ms_p95"] <= 100, (figures, latencies)
    assert figures["map_open_ms"] < 2000 and figures["curve_open_ms"] < 1000, figures
    return figures


SIM = """
import json, sys, time
from pathlib import Path

from rig.sim.params import SimParams
from rig.sim.server import WireSim

from rig.realtime import Realtime

sys.setswitchinterval(0.0005)
params = SimParams()
Realtime(params.realtime, 49).enter()  # one below the loop's, as `rig sim` runs it
rtu = sys.argv[2] == "rtu"
with WireSim(params, rtu=rtu) as sim, open(Path(sys.argv[1]) / "stops.txt", "a", buffering=1) as stops:
    slider = sim.drive.rig.slider
    real_stop = slider.stop

    def seen_stop(*a, **k):  # the simulated drive acting on the STOP bit it read off the wire
        stops.write(f"{time.time() * 1000:.3f}\\n")
        return real_stop(*a, **k)

    slider.stop = seen_stop
    print(json.dumps(sim.endpoints.as_dict()), flush=True)
    sys.stdin.read()
"""


class RigProcess:
    """The simulated rig (Modbus TCP drive, serial load cell) and `rig daemon` on it, each in its own
    process, as a lab runs them: the browser's driver shares no interpreter with the loop or the
    devices. The simulated drive writes the time it acts on each STOP to stops.txt."""

    def __init__(self, tmp: Path, transport: str = "tcp") -> None:
        import yaml

        from rig.service.client import request

        self.tmp, self.sock, self.request = tmp, tmp / "rigd.sock", request
        self.sim = subprocess.Popen([sys.executable, "-c", SIM, str(tmp), transport], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, text=True, cwd=ROOT)
        ep = json.loads(self.sim.stdout.readline())
        slider = {"profile": "oriental_az_sim", "comm_timeout_s": 0.3}
        if transport == "rtu":
            slider.update(backend="modbus-rtu", port=ep["modbus_rtu"])
        else:
            slider.update(backend="modbus-tcp", host="127.0.0.1", tcp_port=int(ep["modbus_tcp"].split(":")[1]))
        cfg = {"slider": slider, "loadcell": {"backend": "serial", "port": ep["loadcell"]},
               "loop": {"tare_s": 0.2}, "recorder": {"out_dir": str(tmp / "trials")}}
        if transport == "tcp":
            # this test shares two cores with a browser drawing 25 times a second: what it measures
            # is the way from the page to the drive, not the load cell's timing (test_safety's)
            cfg["limits"] = {"loadcell_stale_ms": 400}
        (tmp / "rig.yaml").write_text(yaml.safe_dump(cfg))
        self.log = open(tmp / "daemon.log", "w")  # noqa: SIM115 - closed in close()
        self.daemon = subprocess.Popen(
            [sys.executable, "-m", "rig", "daemon", "--config", str(tmp / "rig.yaml"),
             "--socket", str(self.sock)],
            stdout=self.log, stderr=self.log, cwd=tmp)
        _wait(lambda: self.sock.exists() and self.req({"cmd": "ping"})["ok"], 30, "the daemon")

    def req(self, obj: dict) -> dict:
        return self.request(self.sock, obj, 10.0)

    def stops_ms(self) -> list[float]:
        path = self.tmp / "stops.txt"
        return [float(x) for x in path.read_text().split()] if path.exists() else []

    def wait_idle(self, timeout_s: float = 30.0) -> dict:
        return _wait(lambda: (st := self.req({"cmd": "status"}))["state"] == "idle" and st, timeout_s, "idle",
                     every_s=0.1)

    def close(self) -> None:
        for proc, end in ((self.daemon, self.daemon.terminate), (self.sim, self.sim.stdin.close)):
            end()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        self.sim.stdout.close()
        self.log.close()


def click_pixel(driver, div: str, ix: int, iy: int) -> None:
    """A real click (the mouse, through plotly's own handling) on pixel (ix, iy) of a map."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    dx, dy = driver.execute_script("""
        const gd = document.getElementById(arguments[0]), L = gd._fullLayout, t = gd.data[0];
        const r = gd.getBoundingClientRect();
        const x = L.xaxis._offset + L.xaxis.l2p(t.x[arguments[1]]);
        const y = L.yaxis._offset + L.yaxis.l2p(t.y[arguments[2]]);
        return [x - r.width / 2, y - r.height / 2];""", div, ix, iy)
    ActionChains(driver).move_to_element_with_offset(driver.find_element(By.ID, div), round(dx), round(dy)) \
        .click().perform()


def _estop(driver, rig: RigProcess) -> float:
    """Click ESTOP; the time from the click (in the page) to the STOP on the simulated drive."""
    from selenium.webdriver.common.by import By

    seen = len(rig.stops_ms())
    driver.find_element(By.ID, "btn-estop").click()
    stops = _wait(lambda: (got := rig.stops_ms())[seen:] and got, 5, "the STOP on the drive")
    clicked = driver.execute_script("return window.rigClicks[window.rigClicks.length - 1].clicked_ms")
    return stops[seen] - clicked


# ------------------------------------------------------------------ ten viewers on a 100 Hz trial
VIEWED = ("name: viewed\nsteps:\n  - ramp: {to_mm: 4, speed_mm_s: 2}\n  - hold: {duration_s: 1.5}\n"
          "  - return: {to_mm: 0, speed_mm_s: 5}\n")
VIEWERS = 10
# The trial alone, over eleven runs of this test on two cores shared with other work (load average 5 to
# 11): 1 to 13 late ticks and 4 to 36 missed; at a load average of 1.3 to 3, none in six runs but for 2
# missed once (and 0 to 1 late, none missed, with the viewers). With ten viewers the counts stayed
# within that spread (at most 8 late and 28 missed more than the same run's trial alone, and as often
# fewer), so "no more than without" is asserted up to the spread the trial shows by itself from run
# to run.
LATE_SPREAD, MISSED_SPREAD = 12, 32


class Viewers(threading.Thread):
    """`n` plain websocket clients with the token (one event loop in a thread of this process, so
    the harness adds as little load as it can to the machine the loop shares): when each live
    sample arrives (time.time())."""

    def __init__(self, url: str, n: int) -> None:
        super().__init__(daemon=True, name="viewers")
        self.url, self.n = url, n
        self.got: list[list[tuple[float, float]]] = [[] for _ in range(n)]  # per viewer: (received, t_s)
        self.ended = [False] * n
        self.ready = threading.Event()
        self.start()
        assert self.ready.wait(10), "the viewers did not connect"

    def run(self) -> None:
        import asyncio

        asyncio.run(self._all())

    async def _all(self) -> None:
        import asyncio

        from websockets.asyncio.client import connect

        socks = [await connect(self.url, open_timeout=5) for _ in range(self.n)]
        for ws in socks:
            json.loads(await ws.recv())  # hello
        self.ready.set()
        await asyncio.gather(*(self._one(i, ws) for i, ws in enumerate(socks)))

    async def _one(self, i: int, ws) -> None:
        async with ws:
            async for text in ws:
                now = time.time()
                m = json.loads(text)
                if m["kind"] == "live":
                    self.got[i] += [(now, p[0]) for p in m.get("ps") or [m["p"]]]
                elif m["kind"] == "end":
                    self.ended[i] = True
                    return

    def wait_ended(self, timeout_s: float) -> bool:
        self.join(timeout_s)
        return all(self.ended)


def _cpu_s(pid: int) -> float:
    """A process's CPU time so far (user and system, all its threads)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _sample_clock(log_path: str) -> float:
    """The wall time of t_s = 0: each sample's log time (the tick's wall clock) minus its t_s."""
    import statistics

    from mcap.reader import make_reader

    from rig.recording.messages import SAMPLE_TOPIC

    offsets = []
    with open(log_path, "rb") as fh:
        for _, _, msg in make_reader(fh).iter_messages(topics=[SAMPLE_TOPIC]):
            offsets.append(msg.log_time / 1e9 - json.loads(msg.data)["t_s"])
            if len(offsets) == 200:
                break
    assert max(offsets) - min(offsets) < 1e-3, (min(offsets), max(offsets))  # one clock
    return statistics.median(offsets)


def test_ten_viewers_of_a_100_hz_trial_over_modbus_rtu_cost_it_no_ticks(tmp_path):
    """In one run, the same 100 Hz trial over Modbus RTU with no viewer, with ten websocket viewers
    (the token in the address), and with none again: late and missed ticks counted from each
    trial's log as `rig replay` counts them, and each viewer's delay from the sample's tick (its
    wall time in the log) to its arrival."""
    from rig.recording.logs import read_log
    from rig.views.replay import summarize

    d = RigProcess(tmp_path, transport="rtu")
    figures: dict = {}
    try:
        web = WebProcess(tmp_path, d.sock, tmp_path)
        try:
            url = f"ws://127.0.0.1:{web.base.rsplit(':', 1)[1]}/ws?token={web.token}"
            for label, n in (("alone", 0), ("viewed", VIEWERS), ("alone after", 0)):
                viewers = Viewers(url, n) if n else None
                cpu0 = (_cpu_s(web.proc.pid), _cpu_s(d.daemon.pid), _cpu_s(os.getpid()))
                r = d.req({"cmd": "start", "protocol_text": VIEWED, "protocol_path": "viewed.yaml",
                           "specimen": label.replace(" ", "-")})
                assert r["ok"], r
                st = d.wait_idle()
                assert st["last"]["outcome"] == "completed", st["last"]
                cpu1 = (_cpu_s(web.proc.pid), _cpu_s(d.daemon.pid), _cpu_s(os.getpid()))
                s = summarize(read_log(r["log"]))
                figures[label] = {"late": s["late_ticks"], "missed": s["missed_ticks"], "samples": s["samples"],
                                  "cpu_s": {k: round(b - a, 2) for k, a, b in zip(("web", "daemon", "viewers"),
                                                                                   cpu0, cpu1, strict=True)}}
                if viewers:
                    assert viewers.wait_ended(10), "a viewer was not told the trial ended"
                    zero = _sample_clock(r["log"])
                    delays = sorted(1000 * (got - (zero + t_s)) for v in viewers.got for got, t_s in v)
                    per_viewer = [len(v) for v in viewers.got]
                    figures["delivered"] = [min(per_viewer), max(per_viewer)]
                    figures["delay_ms"] = {"p50": round(delays[len(delays) // 2], 1),
                                           "p95": round(delays[int(0.95 * (len(delays) - 1))], 1),
                                           "max": round(delays[-1], 1)}
        finally:
            web.close()
    finally:
        d.close()
    print(f"\nten viewers on a 100 Hz trial over Modbus RTU: {json.dumps(figures)}")
    # the trial with viewers against the worse of the trials alone before and after it (the machine's
    # other work comes and goes), up to the trial's own spread from run to run
    viewed = figures["viewed"]
    alone = {k: max(figures["alone"][k], figures["alone after"][k]) for k in ("late", "missed")}
    assert viewed["late"] <= alone["late"] + LATE_SPREAD, figures
    assert viewed["missed"] <= alone["missed"] + MISSED_SPREAD, figures
    # every viewer saw the trial: the watch stream's 50 samples a second (of the loop's 100), from the
    # moment rig web saw it start (its idle poll: twice a second)
    assert figures["delivered"][0] >= 0.6 * viewed["samples"] / 2, figures
    assert figures["delay_ms"]["p95"] < 250, figures
