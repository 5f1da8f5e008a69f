"""Material properties: E in Pa from the indenter's geometry, the contact point fitted.

Synthetic force curves are written here from the textbook Hertz law (not from rig.models.contact,
which has its own checks against Sneddon's integrals), with the surface away from the position's
zero and a baseline offset, then read back through the CSV reader and `rig analyze` as a user
runs it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rig.analysis.workflow.session import AnalyzeRequest, analyze
from rig.errors import RigError

ROOT = Path(__file__).resolve().parent.parent
REALDATA = ROOT.parent / "shared" / "realdata"
CHIARO = REALDATA / "afm-fd" / "fmt-chiaro-txt_AEBP1_Indentation_002.txt"

E_TRUE = 12e3  # Pa
R = 5e-6  # m
SURFACE = 1.3e-6  # m of travel from the record's start
NOISE = 5e-12  # N
OFFSET = 0.2e-9  # N


def hertz_curve(path: Path, seed: int, surface_m: float = SURFACE) -> Path:
    """An approach at 2 um/s over 3 um, the paraboloid's force past the surface, white noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, 1.5, 1e-3)
    pos = 2e-6 * t
    d = np.clip(pos - surface_m, 0.0, None)
    f = 4.0 / 3.0 * E_TRUE / (1 - 0.5 ** 2) * np.sqrt(R) * d ** 1.5 + OFFSET + rng.normal(0, NOISE, len(t))
    rows = "\n".join(f"{a:.6f},{b * 1e6:.9f},{c * 1e9:.9f}" for a, b, c in zip(t, pos, f, strict=True))
    path.write_text("t_s,position_um,force_nN\n" + rows + "\n")
    return path


@pytest.mark.parametrize("seed", range(5))
def test_hertz_recovers_the_modulus_and_the_contact_point(tmp_path, seed):
    path = hertz_curve(tmp_path / f"hertz-{seed}.csv", seed)
    out = analyze(AnalyzeRequest([str(path)], model="hertz", indenter="paraboloid:R=5um")).json
    m = out["material"]
    assert m["indenter"] == "paraboloid:R=5um" and m["poisson"] == 0.5
    E, se = m["E_Pa"], m["E_Pa_stat"]
    assert 0 < se < 0.05 * E_TRUE, m
    assert abs(E - E_TRUE) < 2 * se, (E, se)
    (cp,), cp_se = m["contact_point_m"], m["contact_point_m_stat"]
    assert 0 < cp_se < 0.05e-6 and abs(cp - SURFACE) < 2 * cp_se, (cp, cp_se)
    assert out["adequate"], out["fit"]
    # the plateau check reads flat on a true paraboloid
    assert abs(m["modulus_drift"]) < 0.1 and len(m["modulus_vs_depth"]) >= 4


def test_the_report_says_the_modulus_the_geometry_and_the_plateau(tmp_path):
    path = hertz_curve(tmp_path / "hertz.csv", 7)
    r = subprocess.run([sys.executable, "-m", "rig", "analyze", str(path), "--model", "hertz", "--indenter",
                        "paraboloid:R=5um"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    line = next(x for x in r.stdout.splitlines() if x.startswith("material"))
    assert "kPa +/-" in line and "paraboloid, R = 5 µm, from --indenter; Poisson's ratio 0.5" in line, line
    assert "(a plateau)" in r.stdout and "contact    at 1.3" in r.stdout, r.stdout
    j = subprocess.run([sys.executable, "-m", "rig", "analyze", str(path), "--model", "hertz", "--indenter",
                        "paraboloid:R=5um", "--json"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    params = json.loads(j.stdout)["parameters"]
    assert params["E_Pa"]["unit"] == "Pa" and params["E_Pa"]["stderr"] > 0


def test_a_wrong_geometry_is_not_adequate_and_the_right_one_recovers_e(tmp_path):
    """A cone fitted as a paraboloid misses the curve (the fitted contact point absorbs part of
    the wrong exponent, so the verdict, not the modulus by depth, is what shows it); fitted as
    the cone it is, E comes back."""
    rng = np.random.default_rng(3)
    t = np.arange(0, 1.5, 1e-3)
    pos = 2e-6 * t
    d = np.clip(pos - SURFACE, 0.0, None)
    f = 2 / np.pi * E_TRUE / 0.75 * np.tan(np.radians(35)) * d ** 2 + rng.normal(0, NOISE, len(t))
    path = tmp_path / "cone.csv"
    path.write_text("t_s,position_um,force_nN\n" + "\n".join(
        f"{a:.6f},{b * 1e6:.9f},{c * 1e9:.9f}" for a, b, c in zip(t, pos, f, strict=True)) + "\n")
    out = analyze(AnalyzeRequest([str(path)], model="hertz", indenter="paraboloid:R=5um"))
    assert not out.json["adequate"] and "NOT adequate" in out.text
    cone = analyze(AnalyzeRequest([str(path)], model="hertz", indenter="cone:half_angle=35deg")).json
    assert abs(cone["material"]["E_Pa"] / E_TRUE - 1) < 0.02 and abs(cone["material"]["modulus_drift"]) < 0.1


@pytest.mark.parametrize(("kw", "message"), [
    ({}, "the hertz model needs the indenter's geometry, which the record does not name: give --indenter"),
    ({"indenter": "sphre:R=1um"},
     "--indenter: indenter 'sphre:R=1um': unknown shape 'sphre' (did you mean 'sphere'"),
    ({"indenter": "cone"}, "--indenter: indenter 'cone': missing parameter half_angle"),
    ({"indenter": "paraboloid:R=5um", "poisson": 0.7}, "--poisson 0.7: Poisson's ratio lies in (-1, 0.5]"),
])
def test_what_is_missing_or_wrong_is_said(tmp_path, kw, message):
    path = hertz_curve(tmp_path / "h.csv", 1)
    with pytest.raises(RigError) as err:
        analyze(AnalyzeRequest([str(path)], model="hertz", **kw))
    assert message in str(err.value) and "\n" not in str(err.value)


def test_the_cli_refuses_bad_arguments_in_one_line(tmp_path):
    path = hertz_curve(tmp_path / "h.csv", 1)
    for args, said in ((["--spring-constant", "-1"], "must be >= 0"), (["--spring-constant", "0"], "> 0"),
                       (["--segment", "retract"], "invalid choice: 'retract'")):
        r = subprocess.run([sys.executable, "-m", "rig", "analyze", str(path), "--model", "hertz", *args],
                           capture_output=True, text=True, cwd=ROOT, timeout=60)
        assert r.returncode == 2 and said in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_hertz_fits_one_curve_at_a_time(tmp_path):
    """Each curve has its own contact point: two curves in one hertz fit are refused, not forced
    onto one contact."""
    a, b = hertz_curve(tmp_path / "a.csv", 1), hertz_curve(tmp_path / "b.csv", 2, surface_m=0.4e-6)
    with pytest.raises(RigError, match=r"fits one curve at a time .* pick one curve of a map with --curve"):
        analyze(AnalyzeRequest([str(a), str(b)], model="hertz", indenter="paraboloid:R=5um"))
    with pytest.raises(RigError, match="fits one curve at a time"):
        analyze(AnalyzeRequest([str(a)], holdout=[str(b)], model="hertz", indenter="paraboloid:R=5um"))


def test_records_that_name_different_indenters_are_refused(tmp_path, monkeypatch):
    import rig.analysis.workflow.inputs as an
    from rig.records import read_record

    paths = [hertz_curve(tmp_path / "a.csv", 1), hertz_curve(tmp_path / "b.csv", 2)]
    named = {"a.csv": "sphere:R=5um", "b.csv": "cone:half_angle=35deg"}

    def read(path, *args, **kwargs):  # the records as an instrument that names its tip gives them
        rec = read_record(path)
        rec.meta["indenter"] = named[rec.name]
        return rec

    monkeypatch.setattr(an, "read_record", read)
    with pytest.raises(RigError, match=r"the records name different indenters \(a.csv: sphere:R=5um, "
                                       r"b.csv: cone:half_angle=35deg\)"):
        an.load_inputs([str(p) for p in paths], [], [])


def test_without_an_indenter_the_models_stay_lumped(tmp_path):
    path = hertz_curve(tmp_path / "h.csv", 2)
    out = analyze(AnalyzeRequest([str(path)], model="hunt_crossley")).json
    assert "material" not in out and "E_Pa" not in out["parameters"]
    compared = analyze(AnalyzeRequest([str(path)], compare=True)).json["compare"]
    assert "hertz" not in [r["model"] for r in compared]


@pytest.mark.skipif(not CHIARO.exists(), reason=f"the shared real records are absent ({CHIARO})")
def test_the_chiaro_modulus_agrees_with_the_instruments_own_fit():
    """The Optics11 Chiaro header names its probe (27.5 um) and its own Hertz fit: the same law with
    the header's radius agrees with it to 3 %; the header's sphere, solved exactly, is stiffer
    at these depths (d/R ~ 0.4) and gives a higher E, and the report says where E came from."""
    from rig.records import read_record

    own = read_record(CHIARO).meta["instrument_result"]["E_Pa"]
    out = analyze(AnalyzeRequest([str(CHIARO)], model="hertz", indenter="paraboloid", segment="approach"))
    m = out.json["material"]
    assert m["indenter"] == "paraboloid:R=27.5um"
    assert m["indenter_from"] == f"--indenter, its radius from the header of {CHIARO.name}"
    assert abs(m["E_Pa"] / own - 1) < 0.03, (m["E_Pa"], own)
    assert "its own fit gives E = 117 Pa (Hertz, Poisson 0.5)" in out.text
    sphere = analyze(AnalyzeRequest([str(CHIARO)], model="hertz", segment="approach")).json["material"]
    assert sphere["indenter"] == "sphere:R=27.5um" and sphere["E_Pa"] > m["E_Pa"]


@pytest.mark.skipif(not CHIARO.exists(), reason=f"the shared real records are absent ({CHIARO})")
def test_a_misfit_in_contact_is_not_taken_for_a_drifting_noise():
    """The Chiaro curve's sphere fit leaves a smooth misfit in contact (6.5x the noise). Read over
    the whole record as a random walk, it made E 124 +/- 98.5 Pa; the approach at rest shows no
    walk, so none is assumed: E's error is a fraction of E, and no drift is claimed."""
    out = analyze(AnalyzeRequest([str(CHIARO)], model="hertz", segment="approach"))
    m = out.json["material"]
    assert not out.json["adequate"]
    assert m["E_Pa_stat"] < 0.25 * m["E_Pa"], (m["E_Pa"], m["E_Pa_stat"])
    assert not any("random-walk drift" in w for w in out.json["warnings"]), out.json["warnings"]


def test_a_rig_config_names_its_probe_and_the_log_carries_it(tmp_path):
    cfg = tmp_path / "rig.yaml"
    cfg.write_text(f"probe: cylinder:R=2mm\nrecorder: {{out_dir: {tmp_path}}}\n")
    proto = ROOT / "protocols" / "demo.yaml"
    r = subprocess.run([sys.executable, "-m", "rig", "run", str(proto), "--config", str(cfg), "--speed", "0"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    log = next(tmp_path.glob("*.mcap"))
    out = analyze(AnalyzeRequest([str(log)], model="hertz")).json
    m = out["material"]
    assert m["indenter"] == "cylinder:R=2mm" and m["indenter_from"] == f"the config in {log.name}"
    assert m["E_Pa"] > 0


def test_a_bad_probe_in_the_config_is_refused_where_it_stands(tmp_path):
    cfg = tmp_path / "rig.yaml"
    cfg.write_text("name: bench\nprobe: cylinder:R=-2mm\n")
    r = subprocess.run([sys.executable, "-m", "rig", "check", str(ROOT / "protocols" / "demo.yaml"), "--config",
                        str(cfg)], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 2 and f"{cfg}:2:8" in r.stderr and "probe" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_a_hertz_fit_cannot_be_saved_and_says_why_before_fitting(tmp_path):
    path = hertz_curve(tmp_path / "h.csv", 3)
    said = r"--save: effect\(s\) elastic_contact hold the indenter's geometry, which a saved"
    with pytest.raises(RigError, match=said):
        analyze(AnalyzeRequest([str(path)], model="hertz", indenter="paraboloid:R=5um",
                               save=str(tmp_path / "m.json")))
    assert not (tmp_path / "m.json").exists()


QI = REALDATA / "afm-fd" / "fmt-jpk-fd_2020.02.07-16.29.05.036.jpk-qi-data"


@pytest.mark.skipif(not QI.exists(), reason=f"no {QI.name} in {QI.parent}")
@pytest.mark.parametrize("curve", range(4))
def test_a_verdict_never_contradicts_its_reason(curve, capsys):
    """A QI curve whose overall error is below the noise but whose return is not: the verdict
    says which test failed, not only an RMSE that reads as passing."""
    from rig.analysis.stats.adequacy import ADEQUATE_RMSE
    from rig.cli import main

    assert main(["analyze", str(QI), "--curve", str(curve), "--model", "hertz",
                 "--indenter", "paraboloid:R=10um", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert main(["analyze", str(QI), "--curve", str(curve), "--model", "hertz",
                 "--indenter", "paraboloid:R=10um"]) == 0
    line = next(s for s in capsys.readouterr().out.splitlines() if s.startswith("fit "))
    if out["adequate"]:
        assert line.endswith("adequate") and "NOT" not in line
    elif out["fit"]["rmse_over_noise"] <= ADEQUATE_RMSE:
        assert "x the noise overall, but " in line or "the residual is correlated over" in line, line
    else:
        assert f"NOT adequate (RMSE {out['fit']['rmse_over_noise']:.1f}x the noise)" in line, line
