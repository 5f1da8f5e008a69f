"""The position's frames: a protocol with an approach step read, analysed and replayed from the
surface the approach found, never from where the trial started."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from rig.control.sequencer import Sequencer
from rig.recording.logs import export_csv, read_log
from rig.records import read_record
from rig.specs.config import RigConfig
from rig.specs.frames import Frame, Frames
from rig.specs.protocol import parse_protocol
from rig.views.replay import format_summary, summarize
from tests.conftest import run_sim

SURFACE_MM = 3.0
RAMP = ("  - ramp: {to_mm: 6, speed_mm_s: 1}\n  - hold: {duration_s: 20}\n"
        "  - return: {speed_mm_s: 5}\n")
APPROACH = "  - approach: {speed_mm_s: 0.5, contact_N: 0.03, max_mm: 10}\n"


def _config(surface_mm: float) -> RigConfig:
    cfg = RigConfig()
    cfg.sim.tissue.surface_mm = surface_mm
    cfg.sim.tissue.k3_N_per_m = 500.0  # stiff enough that contact is seen near the surface
    cfg.sim.tissue.tau1_s = 0.5
    cfg.sim.loadcell.noise_N = 0.01
    return cfg


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """The same tissue: found by an approach from 3 mm away, and touched at the start."""
    tmp = tmp_path_factory.mktemp("frames")
    approach = run_sim("name: a\nsteps:\n" + APPROACH + RAMP, _config(SURFACE_MM), tmp, name="approach.mcap")
    plain = run_sim("name: p\nsteps:\n" + RAMP, _config(0.0), tmp, name="plain.mcap")
    assert approach.outcome == plain.outcome == "completed"
    return approach.log_path, plain.log_path


def _contact_mm(log) -> float:
    return [e for e in log.events if e["kind"] == "step_start"][1]["data"]["zero_mm"]


def test_frames_convert_between_zeros():
    f = Frames(start_mm=2.0)
    assert f.working is Frame.TRIAL and f.zero_mm(Frame.SURFACE) == 2.0
    f = f.at_contact(5.0)
    assert f.working is Frame.SURFACE
    assert f.convert(1.0, Frame.SURFACE, Frame.SLIDER) == 6.0
    assert f.convert(6.0, Frame.SLIDER, Frame.TRIAL) == 4.0


def test_sequencer_moves_its_zero_only_at_contact():
    proto = parse_protocol("name: a\nsteps:\n" + APPROACH + RAMP, "<test>")
    seq = Sequencer(proto, start_mm=1.0, accel_mm_s2=50, tare_s=0.0, tolerance_mm=0.01, rate_Hz=100)
    seq.tick(0.0, 1.0, 0.0, False)
    assert seq.frames == Frames(1.0) and seq.zero_mm == 1.0
    for i in range(5):
        seq.tick(0.01 * (i + 1), 4.0, 1.0, True)
    seq.tick(0.1, 4.02, 1.0, False)  # standing still after the STOP: the surface is here
    assert seq.frames == Frames(1.0, 4.02) and seq.zero_mm == 4.02 and seq.start_mm == 1.0
    assert seq.target_mm == pytest.approx(4.02 + 6.0)


def test_log_reader_measures_the_approach_from_the_surface(logs):
    log = read_log(logs[0])
    contact = _contact_mm(log)
    assert SURFACE_MM < contact < SURFACE_MM + 0.5
    kinds = np.array(log.step_kind)
    x = log.position_mm(Frame.SURFACE)
    approach = kinds == "approach"
    # the approach's travel, out of contact, is negative indentation; it started 'contact' mm out
    assert np.all(x[approach] <= 0.02)
    assert x[approach][0] == pytest.approx(-contact, abs=0.02)
    assert np.allclose(x[kinds == "hold"], 6.0, atol=0.02)
    assert np.allclose(log.position_mm(Frame.SLIDER), x + contact)
    assert np.allclose(log.position_mm(Frame.TRIAL), x + contact)  # the trial started at 0
    # the commanded position too
    assert np.allclose(log.position_cmd_mm(Frame.SURFACE)[kinds == "hold"], 6.0, atol=1e-9)


def test_a_log_without_slider_mm_reads_the_same(logs, tmp_path):
    """Logs written before `slider_mm` derive it from the step_start events' zero_mm."""
    from mcap.writer import Writer

    log = read_log(logs[0], keep_raw=True)
    old = tmp_path / "old.mcap"
    with open(old, "wb") as fh:
        w = Writer(fh)
        w.start()
        ids = {}
        for topic in log.raw_messages:
            sid = w.register_schema(topic, "jsonschema", json.dumps(log.schemas.get(topic, {})).encode())
            ids[topic] = w.register_channel(topic, "json", sid)
        for topic, rows in log.raw_messages.items():
            for row in rows:
                row = {k: v for k, v in row.items() if k != "slider_mm"}
                w.add_message(ids[topic], 0, json.dumps(row).encode(), 0)
        w.finish()
    again = read_log(old)
    assert "slider_mm" not in again.samples
    for frame in Frame:
        assert np.allclose(again.position_mm(frame), log.position_mm(frame), atol=1e-9)


def test_record_and_csv_export_count_indentation_from_the_surface(logs, tmp_path):
    rec = read_record(logs[0])
    approach = rec.steps == "approach"
    assert rec.frame is Frame.SURFACE
    assert np.all(rec.position_m[approach] <= 2e-5)
    csv = tmp_path / "a.csv"
    export_csv(read_log(logs[0]), csv)
    again = read_record(csv)
    assert np.allclose(again.position_m, rec.position_m, atol=1e-9)


def _analyze(path) -> dict:
    out = subprocess.run([sys.executable, "-m", "rig", "analyze", "--json", str(path)],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_analyze_fits_an_approach_log_as_the_same_tissue_touched_at_the_start(logs):
    with_approach, plain = _analyze(logs[0]), _analyze(logs[1])
    fit = with_approach["fit"]
    # before: the approach's 3 mm at zero force fitted as indentation, RMSE 25x the noise
    assert fit["rmse_N"] < 2.0 * fit["noise_N"]
    for name in ("tau1_s", "tau2_N_s_per_m2"):
        a, p = with_approach["parameters"][name]["value"], plain["parameters"][name]["value"]
        assert a == pytest.approx(p, rel=0.1), name
    # the contact the approach found lies a little past the surface: the fitted linear
    # stiffness is within 50 % (before: negative)
    k3 = with_approach["parameters"]["k3_N_per_m"]["value"]
    assert k3 == pytest.approx(plain["parameters"]["k3_N_per_m"]["value"], rel=0.5)


@pytest.mark.parametrize("stiff", [True, False])
def test_replay_reproduces_the_estimator_on_an_approach_log(logs, stiff, tmp_path):
    if stiff:
        path = logs[0]
    else:  # the default soft tissue: the estimator updates on the tick contact is found
        cfg = RigConfig()
        cfg.sim.tissue.surface_mm = SURFACE_MM
        cfg.sim.loadcell.noise_N = 0.01
        text = ("name: a\nsteps:\n  - approach: {speed_mm_s: 0.5, contact_N: 0.05, max_mm: 10}\n" + RAMP)
        path = run_sim(text, cfg, tmp_path).log_path
    d = summarize(read_log(path))
    assert d["estimator"]["reproduced"], d["estimator"]
    assert "the estimator reproduces" in format_summary(d)
