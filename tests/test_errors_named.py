"""Errors that say what they are: the statistical error (the noise's, given the model) and the
systematic one (how far the fit's own choices move a value beyond their noise), in the text,
the JSON and the table; the physics a fit breaks; the defaults an AFM researcher expects.

Synthetic curves are written from the textbook Hertz law, optionally times (1 + a d/d_max): a
smooth misfit no standard error can show. The truths a misfit's interval must hold are the same
model's fits to the noiseless curve over the whole approach and cut at 50 % and 75 % of the
peak force."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rig.analysis.fitting.fit import fit
from rig.analysis.intervals.systematic import DEPTH_SHARES, cut, interval, systematic
from rig.analysis.workflow.inputs import load_inputs
from rig.analysis.workflow.session import AnalyzeRequest, analyze
from rig.models.catalogue import build_model

ROOT = Path(__file__).resolve().parent.parent
REALDATA = ROOT.parent / "shared" / "realdata"
AFM = REALDATA / "afm-fd"
SPOT3 = AFM / "fmt-jpk-fd_spot3-0192.jpk-force"
CHIARO = AFM / "fmt-chiaro-txt_AEBP1_Indentation_002.txt"
WORKSHOP = AFM / "fmt-afm-workshop-fd_single_2021-10-22_14.16.csv"
GEL = REALDATA / "polymergel-creep.jpk-force"
BRAIN = REALDATA / "brain-creep.jpk-force"

E_TRUE, R_M, NOISE_N = 12e3, 5e-6, 50e-12
PRE, CONTACT = 1300, 1700  # samples before and after the surface, 1 nm each


def curve(path: Path, misfit: float, seed: int | None) -> Path:
    """An approach at 1 um/s, 1 kHz: the paraboloid's force times (1 + misfit d/d_max), white
    noise of NOISE_N (none when `seed` is None)."""
    t = np.arange(PRE + CONTACT) * 1e-3
    pos = 1e-6 * t
    d = np.clip(pos - PRE * 1e-9, 0.0, None)
    f = 4.0 / 3.0 * E_TRUE / 0.75 * np.sqrt(R_M) * d ** 1.5 * (1 + misfit * d / d.max())
    if seed is not None:
        f = f + np.random.default_rng(seed).normal(0.0, NOISE_N, len(t))
    rows = "\n".join(f"{a:.6f},{b * 1e6:.9f},{c * 1e9:.12f}" for a, b, c in zip(t, pos, f, strict=True))
    path.write_text("t_s,position_um,force_nN\n" + rows + "\n")
    return path


def hertz_fit(path: Path):
    inp = load_inputs([str(path)], [], [], indenter="paraboloid:R=5um")
    return fit(build_model("hertz", registry=inp.registry), inp.trials)


def noiseless_targets(tmp: Path, misfit: float) -> list[float]:
    """E of the same model fitted to the noiseless curve: whole, and to 50 % and 75 % of the peak."""
    res = hertz_fit(curve(tmp / f"clean-{misfit}.csv", misfit, None))
    found = systematic(res)
    cuts = [c.values["E_Pa"] for c in found.choices if "% of peak" in c.name]
    assert len(cuts) == len(DEPTH_SHARES)
    return [res.values["E_Pa"], *cuts]


@pytest.mark.parametrize("misfit", [0.05, 0.20])
def test_a_misfit_widens_the_interval_to_hold_what_every_fit_range_gives(tmp_path, misfit):
    """Before, the +/- was the noise's alone: E to 50 % of the peak lay hundreds of standard
    errors from the whole approach's E, outside every interval printed."""
    targets = noiseless_targets(tmp_path, misfit)
    held, ratio = [], []
    for seed in range(4):
        out = analyze(AnalyzeRequest([str(curve(tmp_path / f"m{seed}.csv", misfit, seed))], model="hertz",
                                     indenter="paraboloid:R=5um"))
        m = out.json["material"]
        assert m["E_Pa_sys"] > 10 * m["E_Pa_stat"], m  # the misfit is far beyond the noise
        lo, hi = m["E_Pa_interval"]
        held.append(all(lo <= t <= hi for t in targets))
        ratio.append(m["E_Pa_stat"])
        assert "(stat)" in out.text and "(sys)" in out.text and "95 % interval" in out.text
        # the JSON says which error is which, per parameter too
        assert out.json["parameters"]["E_Pa"]["sys"] == m["E_Pa_sys"]
        assert out.json["systematic"]["choices"]
    assert all(held), (targets, held)
    # one regime: the statistical error is the noise's on every seed, not 10-2000x apart
    assert max(ratio) < 3 * min(ratio), ratio


def test_a_model_that_fits_gets_no_systematic_error(tmp_path):
    """Where the model is right, the refits move E within their noise: sys is nought on most
    seeds (a choice counts by chance at 3 sd), and the interval is the statistical one."""
    sys_zero, widths = 0, []
    for seed in range(8):
        res = hertz_fit(curve(tmp_path / f"p{seed}.csv", 0.0, seed))
        found = systematic(res)
        sys_zero += found.error["E_Pa"] == 0.0
        lo, hi = interval(res.values["E_Pa"], res.stderr["E_Pa"], found.error["E_Pa"])
        widths.append((hi - lo) / (2 * 1.96 * res.stderr["E_Pa"]))
    assert sys_zero >= 7, sys_zero
    assert np.mean(widths) < 1.25, widths


def test_a_cut_trial_keeps_its_own_baseline(tmp_path):
    res = hertz_fit(curve(tmp_path / "c.csv", 0.0, 1))
    t = res.trials[0]
    part = cut(t, 100, t.n)
    assert part.n == t.n - 100 and part.quiet_n == t.quiet_n - 100
    assert part.contact_m == pytest.approx(t.contact_m + float(t.motion.x_m[100] - t.motion.x_m[0]))


def test_the_table_names_both_errors(tmp_path):
    src = curve(tmp_path / "m.csv", 0.2, 3)
    table = tmp_path / "t.csv"
    run = subprocess.run([sys.executable, "-m", "rig", "analyze", str(src), "--model", "hertz", "--indenter",
                          "paraboloid:R=5um", "--each", "--table", str(table)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    head = table.read_text().splitlines()[0].split(",")
    for col in ("E_Pa_stat", "E_Pa_sys", "contact_point_m_stat", "contact_point_m_sys", "segment", "caveats"):
        assert col in head, head
    assert "E_Pa_stderr" not in head


real = pytest.mark.skipif(not SPOT3.exists(), reason=f"the shared real records are absent ({AFM})")


@real
def test_an_afm_curve_fits_its_approach_by_default_and_says_so():
    """Before, the default fitted approach and retract with an elastic law: spot3 16.5 kPa
    against 14.7 kPa on the approach, nothing said."""
    default = analyze(AnalyzeRequest([str(SPOT3)], model="hertz", indenter="paraboloid:R=10um"))
    approach = analyze(AnalyzeRequest([str(SPOT3)], model="hertz", indenter="paraboloid:R=10um",
                                      segment="approach"))
    whole = analyze(AnalyzeRequest([str(SPOT3)], model="hertz", indenter="paraboloid:R=10um", segment="all"))
    assert default.json["material"]["E_Pa"] == approach.json["material"]["E_Pa"]
    assert default.json["material"]["segment"] == "approach" and whole.json["material"]["segment"] == "all"
    assert "fitted on  the approach" in default.text
    assert whole.json["material"]["E_Pa"] > 1.05 * default.json["material"]["E_Pa"]


@real
def test_a_real_curve_whose_e_moves_with_the_fit_range_says_so_in_its_error():
    """spot3: E to 50 % of the peak force is 17 % below the whole approach's, 40 standard errors;
    the interval now holds every refit's value."""
    out = analyze(AnalyzeRequest([str(SPOT3)], model="hertz", indenter="paraboloid:R=10um"))
    m = out.json["material"]
    lo, hi = m["E_Pa_interval"]
    assert m["E_Pa_sys"] > 10 * m["E_Pa_stat"]
    assert all(lo <= r["E_Pa"] <= hi for r in m["E_Pa_refits"]), m["E_Pa_refits"]
    assert "refits     to 50 % of peak" in out.text


@real
def test_a_lower_sample_rate_keeps_the_systematic_error_or_says_why_not(tmp_path):
    """spot3 at half its sample rate had fewer than 40 samples in contact to half its peak force:
    no depth refit was made, and the material line read "+/- 0 (sys)" with an interval nine times
    narrower than at the full rate. Now the refits are made down to 20 samples in contact (sys
    2.4 kPa against 3.0), and a refit not made is named, with why."""
    subprocess.run([sys.executable, "-m", "rig", "import", str(SPOT3), "--csv", str(tmp_path / "full.csv")],
                   check=True, capture_output=True)
    head, *rows = (tmp_path / "full.csv").read_text().splitlines()
    out = {}
    for every in (1, 2, 4):
        path = tmp_path / f"every{every}.csv"
        path.write_text("\n".join([head, *rows[::every]]) + "\n")
        out[every] = analyze(AnalyzeRequest([str(path)], model="hertz", indenter="paraboloid:R=10um",
                                            segment="approach"))
    full, half, quarter = (out[k].json["material"] for k in (1, 2, 4))
    assert full["E_Pa_sys"] > 0 and 0.5 < half["E_Pa_sys"] / full["E_Pa_sys"] < 2.0, (full, half)
    assert not full["E_Pa_sys_not_made"] and not half["E_Pa_sys_not_made"]
    assert quarter["E_Pa_sys_not_made"] and "samples in contact, fewer than" in quarter["E_Pa_sys_not_made"][0]
    assert "not refitted to 50 % of peak (" in out[4].text and "sys leaves that choice out" in out[4].text


@real
def test_caveats_a_reader_recorded_are_in_the_text_and_the_row():
    out = analyze(AnalyzeRequest([str(WORKSHOP)], model="hertz", indenter="paraboloid:R=10um"))
    caveat_lines = [ln for ln in out.text.splitlines() if ln.startswith("CAVEAT")]
    assert any("no spring constant" in ln for ln in caveat_lines), out.text
    assert any("sample number" in ln for ln in caveat_lines), out.text
    assert out.json["material"]["caveats"]
    chiaro = analyze(AnalyzeRequest([str(CHIARO)], model="hertz"))
    assert "CAVEAT     the instrument fitted Hertz's paraboloid" in chiaro.text


@pytest.mark.skipif(not GEL.exists(), reason=f"the shared real records are absent ({GEL})")
@pytest.mark.parametrize("record", [GEL, BRAIN], ids=["gel", "brain"])
def test_an_elastic_term_that_pulls_is_flagged(record):
    """In creep form the paper's model fitted the gel and the brain with a cubic negative over
    two thirds of the indentation, the no-pull clamp acting as the contact point: not a word."""
    out = analyze(AnalyzeRequest([str(record)], model="proposed"))
    said = [w for w in out.json["warnings"] if w.startswith("physics: poly_elastic")]
    assert said and "no-pull clamp makes the contact" in said[0], out.json["warnings"]
    assert "WARNING    physics: poly_elastic" in out.text


@pytest.mark.skipif(not GEL.exists(), reason=f"the shared real records are absent ({GEL})")
def test_parameters_that_trade_off_are_reported_as_what_is_determined():
    out = analyze(AnalyzeRequest([str(GEL)], model="kelvin"))
    said = [w for w in out.json["warnings"] if "trade off" in w]
    assert said and said[0].startswith("eta_N_s_per_m and tau1_s trade off"), out.json["warnings"]
    assert "the records determine eta_N_s_per_m - " in said[0]


@real
def test_profile_any_parameter_on_request():
    run = subprocess.run([sys.executable, "-m", "rig", "analyze", str(SPOT3), "--model", "hertz", "--indenter",
                          "paraboloid:R=10um", "--profile", "E_Pa", "--json"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    prof = json.loads(run.stdout)["profile"]
    assert list(prof) == ["E_Pa"] and prof["E_Pa"]["low"] < prof["E_Pa"]["value"] < prof["E_Pa"]["high"]
    bad = subprocess.run([sys.executable, "-m", "rig", "analyze", str(SPOT3), "--model", "hertz", "--indenter",
                          "paraboloid:R=10um", "--profile", "E_pa"], capture_output=True, text=True)
    assert bad.returncode == 2 and "did you mean 'E_Pa'" in bad.stderr and "Traceback" not in bad.stderr


@real
def test_the_map_report_carries_the_caveats_and_names_the_errors(tmp_path):
    """A batch of a file that lacks its calibration: the caveat a reader recorded is in the batch's
    report.md, and the report says which error is which."""
    src = WORKSHOP
    run = subprocess.run([sys.executable, "-m", "rig", "analyze", str(src), "--model", "hertz", "--indenter",
                          "paraboloid:R=10um", "--each", "--table", str(tmp_path / "t.csv"), "--report",
                          str(tmp_path / "rep")], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "| caveat | curves |" in md and "no spring constant" in md, md[:2000]
    assert "E_Pa_sys systematic" in md
