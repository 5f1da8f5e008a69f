"""--compare ranks every model by one likelihood with one noise: BIC on the records' effective
sample count (rig.analysis.stats.criterion). The ranking and every difference are the same whatever
unit the forces are in, since a unit adds the same constant to every model's BIC."""

from __future__ import annotations

import json

import pytest
from rig.sim.params import DriftParams

from rig.analysis.trials.data import load_trial
from rig.cli import main
from rig.records.csvfile import write_trial_csv
from rig.specs.config import RigConfig
from tests.conftest import PROTOCOLS, run_sim


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """A paper trial on the simulated rig with a drift no named model has, written as `rig import`
    writes it, and the same numbers with every force 1e12 times larger (pN read as N)."""
    tmp = tmp_path_factory.mktemp("criterion")
    cfg = RigConfig()
    cfg.sim.seed = 7
    cfg.sim.effects.drift = DriftParams(rate_N_per_s=0.002)
    trial = load_trial(run_sim(PROTOCOLS / "paper-3mm_s.yaml", cfg, tmp).log_path)
    si = tmp / "si.csv"
    write_trial_csv(trial, si)
    lines = si.read_text().splitlines()
    scaled = [lines[0]] + [",".join([*row.split(",")[:2], repr(float(row.split(",")[2]) * 1e12)])
                           for row in lines[1:]]
    pn = tmp / "pn.csv"
    pn.write_text("\n".join(scaled) + "\n")
    return si, pn


def _ranking(path, capsys) -> dict:
    assert main(["analyze", str(path), "--compare", "--json"]) == 0
    return json.loads(capsys.readouterr().out)["compare_ranking"]


def test_the_ranking_and_every_difference_stay_the_same_in_any_force_unit(records, capsys):
    si, pn = (_ranking(p, capsys) for p in records)
    assert [r["model"] for r in si["ranking"]] == [r["model"] for r in pn["ranking"]]
    for a, b in zip(si["ranking"], pn["ranking"], strict=True):
        assert b["delta_bic"] == pytest.approx(a["delta_bic"], rel=1e-6, abs=1e-6)
        assert b["effective_samples"] == pytest.approx(a["effective_samples"], rel=1e-9)
    # the JSON says which likelihood and which noise
    assert si["criterion"].startswith("N_eff ln(RSS / N) + k ln(N_eff)")
    assert "one count for every model" in si["criterion"]
    assert pn["noise_N"] == pytest.approx(si["noise_N"] * 1e12, rel=1e-6)
    assert si["ranking"][0]["delta_bic"] == 0.0 and all(r["delta_bic"] > 0 for r in si["ranking"][1:])


def test_the_table_says_the_criterion(records, capsys):
    assert main(["analyze", str(records[0]), "--compare"]) == 0
    text = capsys.readouterr().out
    assert "dBIC" in text and "ranked by BIC = N_eff ln(RSS / N) + k ln(N_eff)" in text
