"""The first hour, continued (issue 45): what a new technician and a new researcher expected to
type back, to find kept with a trial, and to read off a day's trials; each with its check."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from rig.cli import main

AFM = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "afm-fd"
SPOT = AFM / "fmt-jpk-fd_spot3-0192.jpk-force"


def _rmse(text: str) -> str:
    return re.search(r"^fit +RMSE (\S+ \S+),", text, re.M).group(1)


# --- 1. the model the tool prints can be typed back ----------------------------------------------

def test_the_model_a_fit_prints_builds_the_same_model():
    from rig.models.catalogue import build_model

    printed = "poly_elastic+nonlinear_damping+relaxation+fractional_relaxation+viscous+contact_point+offset"
    typed = build_model(printed)
    assert typed.effect_names == ["poly_elastic", "nonlinear_damping", "relaxation", "fractional_relaxation",
                                  "viscous", "contact_point", "offset"]
    assert typed.name == printed
    assert build_model("proposed", ["contact_point"]).effect_names[-1] == "contact_point"
    # a named model at the head, an effect it already holds named again: the same model
    assert build_model("hooke+linear_elastic+drift").effect_names == ["linear_elastic", "drift"]


@pytest.mark.skipif(not SPOT.exists(), reason="the shared AFM curves are not beside the project")
def test_auto_s_final_model_typed_back_gives_the_same_fit(capsys):
    args = [str(SPOT), "--segment", "approach"]
    assert main(["analyze", *args, "--auto"]) == 0
    out = capsys.readouterr().out
    final = re.search(r"^final model (\S+):", out, re.M).group(1)
    assert "+contact_point+offset" in final  # the record's own contact and zero, as printed
    assert main(["analyze", *args, "--model", final]) == 0
    again = capsys.readouterr().out
    assert re.search(r"^model +(\S+)", again, re.M).group(1) == final
    auto_rmse = re.findall(r"^\d+ +\S+ +(\S+)", out, re.M)[-1]
    assert _rmse(again) == f"{auto_rmse} nN"
    # and its parts typed one by one (the first as --model, each other with --add; the record's own
    # contact and zero come with it): the same again. --auto may have swapped a part of the start
    # model out, so the start model with additions is not always it
    parts = [x for x in final.split("+") if x not in ("contact_point", "offset")]
    extra = [a for x in parts[1:] for a in ("--add", x)]
    assert main(["analyze", *args, "--model", parts[0], *extra]) == 0
    assert _rmse(capsys.readouterr().out) == f"{auto_rmse} nN"


# --- 2. the simulator's hidden relaxation2 and the fit's speak of the same parameters ------------

def test_the_simulated_relaxation2_is_configured_under_the_fitted_names():
    from rig.models.catalogue import CATALOGUE
    from rig.specs.config import parse_config
    from rig.specs.yamlspec import DeprecatedKey

    fitted = [p.name for p in CATALOGUE["relaxation2"].params]
    assert fitted == ["k_m_N_per_m", "tau_m_s"]
    cfg = parse_config("sim: {effects: {relaxation2: {k_m_N_per_m: 60, tau_m_s: 40}}}\n")
    assert (cfg.sim.effects.relaxation2.k_m_N_per_m, cfg.sim.effects.relaxation2.tau_m_s) == (60, 40)
    # the old names still read, with a warning naming the new ones and where the old stand
    with pytest.warns(DeprecatedKey) as caught:
        old = parse_config("sim:\n  effects:\n    relaxation2: {k_N_per_m: 60, tau_s: 40}\n", "old.yaml")
    assert old.sim.effects.relaxation2 == cfg.sim.effects.relaxation2
    said = [str(w.message) for w in caught]
    assert any("old.yaml:3: sim.effects.relaxation2.k_N_per_m is deprecated" in m and "'k_m_N_per_m'" in m
               for m in said), said
    from rig.errors import SpecError

    with pytest.raises(SpecError, match="'tau_s' is the old name of 'tau_m_s': give one of them"):
        parse_config("sim: {effects: {relaxation2: {tau_s: 40, tau_m_s: 40}}}\n")



# --- 5. a day's trials as a table --------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "protocols" / "demo.yaml"


@pytest.fixture(scope="module")
def day(tmp_path_factory):
    """Two trials of the demo on the simulated rig, on the virtual clock."""
    out = tmp_path_factory.mktemp("day")
    for specimen in ("pig-07", "pig-08"):
        assert main(["run", str(ROOT / "protocols" / "demo.yaml"), "--speed", "0", "--quiet", "--out", str(out),
                     "--specimen", specimen]) == 0
    return out


def test_logs_table_writes_one_row_per_trial_as_csv(day, tmp_path, capsys):
    import csv

    from rig.recording.logs import read_log
    from rig.views.replay import log_figures

    capsys.readouterr()
    assert main(["logs", "--dir", str(day), "--table", str(tmp_path / "day.csv")]) == 0
    assert "2 trials" in capsys.readouterr().out
    with open(tmp_path / "day.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["specimen"] for r in rows] == ["pig-08", "pig-07"]  # newest first, as rig logs lists them
    assert set(rows[0]) >= {"specimen", "protocol", "outcome", "peak_force_N", "hold_end_stiffness_N_per_m",
                            "estimator_error_rms_N", "duration_s", "calibration_date"}
    for r in rows:
        figs = log_figures(read_log(day / r["file"]))
        assert r["outcome"] == "completed" and r["protocol"].startswith("demo")
        assert float(r["peak_force_N"]) == pytest.approx(figs["peak_force_N"])
        assert float(r["hold_end_stiffness_N_per_m"]) == pytest.approx(figs["hold_end_stiffness_N_per_m"])
        assert float(r["estimator_error_rms_N"]) == pytest.approx(figs["estimator_error_rms_N"])
        assert 10 < float(r["duration_s"]) < 13
        assert r["calibration_date"] == ""  # the simulated rig's config holds no calibration


def test_logs_table_writes_parquet(day, tmp_path):
    pq = pytest.importorskip("pyarrow.parquet")
    assert main(["logs", "--dir", str(day), "--table", str(tmp_path / "day.parquet")]) == 0
    t = pq.read_table(tmp_path / "day.parquet").to_pylist()
    assert [r["specimen"] for r in t] == ["pig-08", "pig-07"]
    assert all(isinstance(r["peak_force_N"], float) and r["peak_force_N"] > 0 for r in t)


# --- 4. the specimen's dimensions kept with the trial, used where they matter --------------------

MATERIAL = ("probe: paraboloid:R=5mm\nsim:\n  tissue:\n    material:\n      indenter: paraboloid:R=5mm\n"
            "      E0_Pa: 20000\n      E_inf_Pa: 20000\n")
RAMP = "name: ramp-hold\nsteps:\n  - ramp: {to_mm: 2, speed_mm_s: 2}\n  - hold: {duration_s: 2}\n" \
       "  - return: {to_mm: 0, speed_mm_s: 2}\n"


@pytest.fixture(scope="module")
def sized(tmp_path_factory):
    """A ramp-hold on the simulated material, its thickness and area given; and the same without."""
    out = tmp_path_factory.mktemp("sized")
    (out / "rig.yaml").write_text(MATERIAL)
    (out / "p.yaml").write_text(RAMP)
    logs = {}
    for name, size in (("given", ["--thickness-mm", "8", "--area-mm2", "50"]), ("plain", [])):
        d = out / name
        assert main(["run", str(out / "p.yaml"), "--config", str(out / "rig.yaml"), "--speed", "0", "--quiet",
                     "--out", str(d), "--specimen", name, *size]) == 0
        (logs[name],) = d.glob("*.mcap")
    return logs


def test_run_keeps_thickness_and_area_in_the_log_header(sized):
    from rig.recording.logs import read_log

    trial = read_log(sized["given"]).trial
    assert (trial["thickness_mm"], trial["area_mm2"]) == ("8", "50")
    assert "thickness_mm" not in read_log(sized["plain"]).trial


def test_replay_reports_stress_and_strain_from_the_dimensions(sized, capsys):
    from rig.recording.logs import read_log
    from rig.specs.frames import Frame

    capsys.readouterr()
    assert main(["replay", str(sized["given"]), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    z = d["specimen_size"]
    assert z["peak_stress_Pa"] == pytest.approx(d["peak_force_N"] / 50e-6)
    depth = float(np.max(read_log(sized["given"]).position_mm(Frame.SURFACE)))
    assert 1.9 < depth < 2.1 and z["peak_strain"] == pytest.approx(depth / 8.0)
    assert main(["replay", str(sized["given"])]) == 0
    text = capsys.readouterr().out
    assert "size       thickness 8 mm, area 50 mm^2" in text
    assert f"stress     peak {z['peak_stress_Pa'] / 1e3:.4g} kPa (peak force / area)" in text
    assert "strain     peak 0.2" in text
    assert main(["replay", str(sized["plain"])]) == 0
    assert "stress" not in capsys.readouterr().out


def test_the_bottom_effect_takes_the_thickness_from_the_log(sized, capsys):
    """With the thickness in the header the bottom effect is the specimen's (h not fitted, the
    modulus the only parameter it shares); without it, h_m is fitted as before."""
    capsys.readouterr()
    for name, has_h in (("given", False), ("plain", True)):
        assert main(["analyze", str(sized[name]), "--model", "hertz", "--add", "bottom_effect", "--json"]) == 0
        got = json.loads(capsys.readouterr().out)
        assert ("h_m" in got["parameters"]) is has_h, (name, list(got["parameters"]))
        assert got["parameters"]["E_Pa"]["value"] > 0


def test_the_daemon_s_start_refuses_a_thickness_that_is_not_a_positive_number():
    from rig.service.daemon import RequestError, _dimensions

    assert _dimensions({"thickness_mm": 3, "area_mm2": 12.5}) == {"thickness_mm": "3", "area_mm2": "12.5"}
    assert _dimensions({}) == {}
    for bad in (0, -1, "3", True, float("inf")):
        with pytest.raises(RequestError, match='"thickness_mm" must be a positive number'):
            _dimensions({"thickness_mm": bad})


def test_rig_start_sends_the_dimensions_with_the_start(monkeypatch, tmp_path, capsys):
    import rig.service.client as client

    sent = []

    def fake(sock, req, *a, **k):
        sent.append(req)
        return {"ok": True, "protocol": "demo", "log": "x.mcap"}

    monkeypatch.setattr(client, "request", fake)
    assert main(["start", str(ROOT / "protocols" / "demo.yaml"), "--socket", str(tmp_path / "s"),
                 "--thickness-mm", "4.5", "--area-mm2", "20"]) == 0
    assert (sent[0]["thickness_mm"], sent[0]["area_mm2"]) == (4.5, 20.0)
    with pytest.raises(SystemExit):
        main(["start", str(ROOT / "protocols" / "demo.yaml"), "--thickness-mm", "-1"])


# --- 3. the load cell's calibration: from readings, and its warnings -----------------------------

def test_a_calibration_from_readings_taken_elsewhere_fits_the_line(tmp_path, capsys):
    """Readings on a line of slope 0.98 with a known 10 mN bend at 500 g: the sensitivity, the
    offset and the linearity come back (no cell is opened)."""
    g = 9.80665
    lines = [(m, 0.98 * m * 1e-3 * g + 0.05 + (0.01 if m == 500 else 0.0)) for m in (0, 250, 500, 750, 1000)]
    (tmp_path / "r.txt").write_text("".join(f"{m} {r:.6f} 0.001 100\n" for m, r in lines))
    cfg = tmp_path / "rig.yaml"
    assert main(["calibrate", "--readings", str(tmp_path / "r.txt"), "--config", str(cfg), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["sensitivity"] == pytest.approx(0.98, rel=2e-3)
    assert out["offset_N"] == pytest.approx(0.052, abs=3e-3)
    assert out["linearity_N"] == pytest.approx(0.008 / 0.98, rel=0.05)  # the bend, less the line's share of it
    assert out["linearity_pct"] == pytest.approx(100 * out["linearity_N"] / g, rel=1e-6)
    from rig.specs.config import load_config

    assert load_config(cfg).calibration.sensitivity == pytest.approx(out["sensitivity"], rel=1e-7)


def _calibrated(tmp_path, date: str, top_N: float, max_age: float = 365) -> Path:
    cfg = tmp_path / "rig.yaml"
    cfg.write_text(f"recorder: {{out_dir: {tmp_path / 'trials'}}}\ncalibration:\n  date: \"{date}\"\n"
                   f"  sensitivity: 1.0\n  range_N: [0, {top_N}]\n  max_age_days: {max_age}\n")
    return cfg


def test_an_old_calibration_is_warned_about_at_check_and_in_the_log(tmp_path, capsys):
    from rig.recording.logs import read_log

    cfg = _calibrated(tmp_path, "2025-01-02T10:00:00+00:00", 50.0, max_age=180)
    assert main(["check", str(ROOT / "protocols" / "demo.yaml"), "--config", str(cfg)]) == 0
    said = capsys.readouterr().out
    assert "WARNING   the load cell's calibration is" in said
    assert "beyond calibration.max_age_days (180)" in said
    assert main(["run", str(DEMO), "--config", str(cfg), "--speed", "0", "--quiet"]) == 0
    (log,) = (tmp_path / "trials").glob("*.mcap")
    log = read_log(log)
    assert "days old" in log.metadata["calibration"]["warnings"]
    assert [e["kind"] for e in log.events if e["kind"].startswith("calibration")] == ["calibration_warning"]


def test_a_force_beyond_the_calibrated_range_is_warned_about_at_check_and_in_the_log(tmp_path, capsys):
    """The demo's ramp reaches about 1 N; calibrated up to 0.5 N, the log says when it passed it."""
    from datetime import UTC, datetime

    from rig.recording.logs import read_log

    cfg = _calibrated(tmp_path, datetime.now(UTC).isoformat(), 0.5)
    assert main(["check", str(ROOT / "protocols" / "demo.yaml"), "--config", str(cfg)]) == 0
    assert "the force limit 20 N is beyond the calibrated range (0-0.5 N)" in capsys.readouterr().out
    assert main(["run", str(DEMO), "--config", str(cfg), "--speed", "0", "--quiet"]) == 0
    (path,) = (tmp_path / "trials").glob("*.mcap")
    log = read_log(path)
    (ev,) = [e for e in log.events if e["kind"].startswith("calibration")]
    assert ev["kind"] == "calibration_range" and ev["data"]["force_N"] > 0.5
    first = int(np.argmax(np.abs(log.samples["force_N"]) > 0.5))
    assert ev["t_s"] == pytest.approx(log.samples["t_s"][first], abs=0.011)
    capsys.readouterr()
    assert main(["replay", str(path)]) == 0
    assert "NOTICE     force" in capsys.readouterr().out


# --- 6. a quality rating per curve, and a filter on it ------------------------------------------

def _analysis(*, cp_u=1e-9, cp_sys=0.0, depth=1e-7, r=1.0, touched=500, samples=1000, caveats=(), notes=(),
              warnings=(), contact=True):
    rec = {"samples": samples, "notes": list(notes)}
    if contact:
        rec.update(contact_point_m=1e-6, contact_point_m_stderr=cp_u)
    return {"records": [rec], "material": {"caveats": list(caveats), "contact_point_m_sys": cp_sys},
            "scales": {"length_m": depth}, "fit": {"rmse_over_noise": r},
            "phases": {"ramp": {"n": touched}, "hold_early": None}, "warnings": list(warnings)}


def test_the_quality_rating_follows_its_documented_rule():
    from rig.analysis.batch.quality import rate

    assert rate(_analysis()) == (10.0, {"contact": 3.0, "fit": 4.0, "baseline": 2.0, "artefacts": 1.0})
    # each part at its other end
    assert rate(_analysis(cp_u=3e-8))[1]["contact"] == 0.0  # 30 % of the indentation
    assert rate(_analysis(cp_u=1e-9, cp_sys=3e-8))[1]["contact"] == 0.0  # the systematic error counts
    assert rate(_analysis(r=5.0))[1]["fit"] == 0.0
    assert rate(_analysis(touched=960))[1]["baseline"] == 0.0  # 4 % out of contact ...
    assert rate(_analysis(touched=960))[1]["contact"] == 0.0  # ... and the contact point not seen
    assert rate(_analysis(touched=5))[1]["baseline"] == 0.0  # 99.5 % out of contact: barely indented
    assert rate(_analysis(caveats=["no spring constant"]))[1]["artefacts"] == 0.5
    assert rate(_analysis(caveats=["a"], warnings=["physics: a law that pulls"]))[1]["artefacts"] == 0.0
    assert rate(_analysis(), effect="power_elastic")[1]["artefacts"] == 0.5
    assert rate(_analysis(contact=False))[1]["contact"] == 3.0  # the record knows its surface
    # between the ends: log-linear (contact, fit), linear (baseline)
    parts = rate(_analysis(cp_u=math.sqrt(0.01 * 0.30) * 1e-7, r=math.sqrt(1.1 * 5.0), touched=825))[1]
    assert parts["contact"] == pytest.approx(1.5) and parts["fit"] == pytest.approx(2.0)
    assert parts["baseline"] == pytest.approx(2 * (0.175 - 0.05) / 0.25)


@pytest.mark.skipif(not AFM.exists(), reason="the shared AFM curves are not beside the project")
def test_batch_tables_rate_every_curve_and_min_quality_filters_the_summary_and_report(tmp_path, capsys):
    import csv

    args = ["analyze", str(AFM / "fmt-jpk-fd_map2x2_extracted.jpk-force-map"), "--model", "hertz", "--indenter",
            "paraboloid:R=10um", "--segment", "approach", "--workers", "2"]
    assert main([*args, "--table", str(tmp_path / "all.csv")]) == 0
    capsys.readouterr()
    with open(tmp_path / "all.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    q = {int(r["curve"]): float(r["quality"]) for r in rows}
    assert all(0 <= v <= 10 for v in q.values()) and all("contact" in r["quality_parts"] for r in rows)
    # a cut between two distinct ratings (the table's ratings are rounded, so two curves can tie)
    v = sorted(set(q.values()))
    assert len(v) >= 2, f"the four curves rate alike ({q}): nothing to filter"
    cut = round((v[0] + v[1]) / 2, 3)
    kept = sorted(c for c, x in q.items() if x >= cut)
    n = len(kept)
    assert main([*args, "--table", str(tmp_path / "cut.csv"), "--min-quality", f"{cut:g}", "--report",
                 str(tmp_path / "rep")]) == 0
    said = capsys.readouterr().out
    assert f"quality >= {cut:g} (of 10): {n} of 4 curves kept" in said
    assert f"({n} curves)" in said and "(4 curves)" not in said  # the parameters' statistics: the kept ones
    with open(tmp_path / "cut.csv", newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 4  # the table keeps every curve
    assert (tmp_path / "rep" / "map1_quality.png").exists()
    assert f"{n} of 4 curves kept" in (tmp_path / "rep" / "report.md").read_text()
    assert 1 <= n <= 3
    assert main(["analyze", str(SPOT), "--min-quality", "5"]) != 0
    assert "--min-quality is for a batch" in capsys.readouterr().err
