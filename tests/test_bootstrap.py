"""--bootstrap N: records redrawn from the fitted model and the measured noise, each analysed as
the record was (contact, noise, fit, verdict): bias, scatter against the reported error, how
often +/-1.96 SE held the value, how often the verdict stayed."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from rig.cli import main
from tests.test_material import hertz_curve


def test_a_clean_curve_keeps_its_verdict_and_its_errors_cover(tmp_path, capsys):
    path = hertz_curve(tmp_path / "hertz.csv", seed=3)
    assert main(["analyze", str(path), "--model", "hertz", "--indenter", "paraboloid:R=5um",
                 "--bootstrap", "40", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["adequate"] is True
    b = out["bootstrap"]
    assert b["draws"] == 40 and b["fitted"] == 40 and b["failed"] == []
    assert b["verdict_kept"] >= 0.9
    for name in ("E_Pa", "x_c_m", "offset_N"):
        p = b["parameters"][name]
        # 40 draws: the coverage of a 95 % interval is known to about +/-4 %
        assert 0.8 <= p["coverage_95"] <= 1.0, (name, p)
        assert 0.6 <= p["mean_stderr"] / p["sd"] <= 1.6, (name, p)
        assert abs(p["bias"]) < 0.5 * p["sd"], (name, p)
    # the contact is compared where the user reads it: in the record's travel
    assert b["parameters"]["x_c_m"]["value"] == pytest.approx(out["material"]["contact_point_m"][0], rel=1e-9)


def test_the_table_reads_as_a_person_reads_it(tmp_path):
    path = hertz_curve(tmp_path / "hertz.csv", seed=4)
    r = subprocess.run([sys.executable, "-m", "rig", "analyze", str(path), "--model", "hertz", "--indenter",
                        "paraboloid:R=5um", "--bootstrap", "10"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "bootstrap: 10 records redrawn from the fitted model and the measured noise" in r.stdout
    assert "verdict the same in" in r.stdout and "95% held" in r.stdout
    bad = subprocess.run([sys.executable, "-m", "rig", "analyze", str(path), "--bootstrap", "1.5"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--bootstrap: must be a whole number of draws, got 1.5" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_too_few_independent_residuals_per_parameter_are_said(tmp_path, capsys):
    """The paper's seven parameters (with the contact and the zero) on a short Hertz curve they do
    not describe leave one smooth misfit: a handful of independent residuals, too few to trust
    seven errors on; the right model leaves thousands."""
    path = hertz_curve(tmp_path / "hertz.csv", seed=5)
    assert main(["analyze", str(path), "--model", "proposed", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    said = [w for w in out["warnings"] if w.startswith("only ")]
    assert said and "fewer than 5 each" in said[0], out["warnings"]
    assert out["fit"]["residual_effective_samples"] < 5 * len(out["parameters"])
    assert main(["analyze", str(path), "--model", "hertz", "--indenter", "paraboloid:R=5um", "--json"]) == 0
    assert not [w for w in json.loads(capsys.readouterr().out)["warnings"] if w.startswith("only ")]
