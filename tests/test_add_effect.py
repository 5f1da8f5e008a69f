"""`rig analyze --add EFFECT`: the model with the effect added contains the model without it,
so the error it reports never rises, whatever optimum a start from the catalogue would find
(seen: proposed + relaxation2 on a plain simulated trial ended at 2.9x the base's error)."""

from __future__ import annotations

import json

import pytest

from rig.cli import main
from rig.recording.logs import export_csv, read_log
from rig.specs.config import RigConfig
from tests.conftest import PROTOCOLS, calibration_seeds, run_sim


@pytest.mark.parametrize("seed", calibration_seeds((1, 2, 3)))
def test_adding_an_effect_never_raises_the_error(seed, tmp_path, capsys):
    cfg = RigConfig()
    cfg.sim.seed = seed
    log = run_sim(PROTOCOLS / "paper-0.75mm_s.yaml", cfg, tmp_path).log_path
    csv = tmp_path / "trial.csv"
    export_csv(read_log(log), csv)
    for effect in ("relaxation2", "friction"):
        assert main(["analyze", str(csv), "--add", effect, "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        before, after = out["before_add"]["fit"]["rmse_N"], out["fit"]["rmse_N"]
        assert after <= before * (1 + 1e-9), (effect, before, after)
        assert main(["analyze", str(csv), "--add", effect]) == 0
        assert "error rises" not in capsys.readouterr().out
