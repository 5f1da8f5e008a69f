"""`rig web`'s maps on the simulated 64x64 map (4096 curves), measured in Debian's chromium:

    python -m pytest -p no:cacheprovider tests/bench/test_bench_web.py -s -q

- the map and its table are made as the force-map tutorial makes them (`rig sim-map --grid 64x64
  --seed 2`, then `rig analyze ... --model hertz --indenter paraboloid:R=5um --segment approach
  --each --table`): minutes on two cores, timed and printed. RIG_BENCH_WEB_MAP64=DIR takes a folder
  where they were made so already (map64.h5, map64.csv and its request file) instead;
- `rig web` in a process of its own (no daemon: the maps page reads files only); the maps page
  opened in chromium three times: the time from the page's navigation to the four maps drawn
  (E in kPa, contact height, RMSE over noise, verdict, on axes in um), and the maps alone (the
  table asked for and drawn: the first time read from its file); target: under 2 s, for the
  maps every time and for the page opened again (the first opening of all, plotly.js fetched
  and compiled by the browser, is printed beside it);
- twelve pixels clicked with the mouse, across the map: the time from the press to the curve
  drawn with its fit, residual and retract (performance.now() in the page); target: under 1 s each;
- the console's whole path with ESTOP from the page twenty times (the suite does it eight times):
  p95 of the click to the simulated drive's STOP under 100 ms.
"""

from __future__ import annotations

import json
import os
import statistics
import time
from pathlib import Path

import pytest

from tests.conftest import ROOT
from tests.test_web import WebProcess, _browser, _wait, click_pixel, console_in_a_browser

MAP_S, CURVE_S = 2.0, 1.0


@pytest.fixture(scope="module")
def map64(tmp_path_factory) -> Path:
    pytest.importorskip("afmformats", reason="the afm extra (afmformats) writes and reads the map")
    given = os.environ.get("RIG_BENCH_WEB_MAP64")
    if given:
        folder = Path(given)
        assert (folder / "map64.csv").is_file() and (folder / "map64.csv.request.json").is_file(), folder
        print(f"\nthe 64x64 map and its table from {folder} (made as the tutorial makes them)")
        return folder
    from rig.cli import main

    folder = tmp_path_factory.mktemp("map64")
    t0 = time.perf_counter()
    assert main(["sim-map", str(folder / "map64.h5"), "--grid", "64x64", "--seed", "2"]) == 0
    t1 = time.perf_counter()
    code = main(["analyze", str(folder / "map64.h5"), "--model", "hertz", "--indenter", "paraboloid:R=5um",
                 "--segment", "approach", "--each", "--table", str(folder / "map64.csv")])
    t2 = time.perf_counter()
    assert code in (0, *range(64, 256)), code
    print(f"\n64x64 map written in {t1 - t0:.0f} s, its table in {t2 - t1:.0f} s")
    return folder


def test_the_64x64_map_opens_in_2_s_and_a_pixel_in_1_s(map64, tmp_path):
    driver = _browser()
    web = WebProcess(tmp_path, tmp_path / "no-daemon.sock", map64)
    figures: dict = {"load_ms": [], "maps_ms": [], "plotly_js_ms": [], "scripts_run_ms": [], "curve_ms": []}
    try:
        driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride",
                               {"width": 1280, "height": 800, "deviceScaleFactor": 1, "mobile": False})
        driver.get(f"{web.base}/history?token={web.token}")  # the cookie; plotly.js not yet cached
        for _ in range(3):
            driver.get(f"{web.base}/maps?table=map64.csv")
            _wait(lambda: driver.execute_script("return window.rigMapsReady"), 60, "the maps")
            timing = driver.execute_script("return window.rigMaps")
            figures["load_ms"].append(round(timing["loadMs"]))
            figures["maps_ms"].append(round(timing["mapMs"]))
            # where the page's load went: plotly.js (3.6 MB) fetched, the page's scripts run
            figures["plotly_js_ms"].append(round(driver.execute_script(
                "const e = performance.getEntriesByType('resource')"
                ".find(r => r.name.endsWith('plotly.min.js')); return e ? e.responseEnd : 0")))
            figures["scripts_run_ms"].append(round(driver.execute_script(
                "return performance.getEntriesByType('navigation')[0].domContentLoadedEventEnd")))
        summary = driver.execute_script("return document.getElementById('summary').textContent")
        assert summary.startswith("4096 curves on 64 x 64"), summary
        unit = driver.execute_script("return document.getElementById('m-E').layout.xaxis.title.text")
        assert unit == "x (um)", unit
        for ix, iy in [(1, 1), (62, 62), (31, 5), (5, 40), (50, 20), (12, 60), (33, 33), (60, 3), (20, 25),
                       (45, 50), (2, 30), (40, 10)]:
            click_pixel(driver, "m-E", ix, iy)
            _wait(lambda: driver.execute_script("return window.rigMaps.curveMs"), 30, "the curve")
            figures["curve_ms"].append(round(driver.execute_script("return window.rigMaps.curveMs")))
            traces = driver.execute_script("return document.getElementById('curve').data.map(t => t.name)")
            assert traces[0] == "approach" and traces[1] == "retract" and traces[2].startswith("fit"), traces
        driver.save_screenshot(str(tmp_path / "map64.png"))
        driver_server = driver.execute_script("return window.rigMaps.server")
    finally:
        web.close()
        driver.quit()
    figures["curve_server_ms"] = driver_server
    c = sorted(figures["curve_ms"])
    figures["curve_ms_p50"], figures["curve_ms_max"] = statistics.median(c), c[-1]
    print(f"rig web, the 64x64 map in chromium: {json.dumps(figures)}")
    print(f"  (screenshot {tmp_path / 'map64.png'}; {ROOT.name})")
    # the table opened as maps (read from its file the first time, then from the server's cache), and
    # the page opened again (plotly.js cached by the browser); the page's very first load, plotly.js
    # fetched and compiled, is printed (1.3-2.5 s on this machine under load: most of it compiling)
    assert max(figures["maps_ms"]) < MAP_S * 1000 and max(figures["load_ms"][1:]) < MAP_S * 1000, figures
    assert c[-1] < CURVE_S * 1000, figures


def test_twenty_estops_from_the_console(tmp_path):
    figures = console_in_a_browser(tmp_path, 20)
    print(f"\ntwenty ESTOPs from the page: p50 {figures['estop_ms_p50']:.1f} ms, p95 "
          f"{figures['estop_ms_p95']:.1f} ms, max {figures['estop_ms_max']:.1f} ms")
