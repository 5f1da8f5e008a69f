"""The paper's negative damping, reproduced: Voigt and Kelvin fitted to the same simulated
trial (the paper's tissue model, the paper's 0.75 mm/s protocol) give positive damping on the
whole ramp and hold, and negative damping on the record cut 10 s into the hold (a 50 s
record, like the paper's shortest figures); a contact behind the marked reference makes it
more negative still. The proposed model's damping stays positive on every record."""

from __future__ import annotations

import csv
import json

import pytest
from rig.sim.params import ContactOffsetParams

from rig.cli import main
from rig.specs.config import RigConfig
from tests.conftest import PROTOCOLS, calibration_seeds, run_sim

SEEDS = (1, 2, 3)
CUT_S = 10.0  # into the hold
BEHIND_MM = 3.0  # the tissue surface this far beyond the marked reference (the trial's zero)
TAU2 = RigConfig().sim.tissue.tau2_N_s_per_m2


def _records(tmp, seed: int, behind_mm: float, capsys) -> dict[str, str]:
    """The 0.75 mm/s paper trial as CSV (`rig replay --csv`), whole (ramp and hold, as the paper
    records a trial: the return is the way to the next one) and cut 10 s into the hold."""
    cfg = RigConfig()
    cfg.sim.seed = seed
    if behind_mm:
        cfg.sim.effects.contact_offset = ContactOffsetParams(x0_mm=behind_mm)
    log = run_sim(PROTOCOLS / "paper-0.75mm_s.yaml", cfg, tmp, name=f"{seed}-{behind_mm}.mcap").log_path
    full = tmp / f"{seed}-{behind_mm}.csv"
    assert main(["replay", str(log), "--csv", str(full)]) == 0
    capsys.readouterr()
    with open(full, newline="") as fh:
        rows = list(csv.reader(fh))
    head, body = rows[0], rows[1:]
    t, kind = head.index("t_s"), head.index("step_kind")
    ramp_end = max(float(r[t]) for r in body if r[kind] == "ramp")
    out = {}
    for name, keep in (("whole", lambda r: r[kind] != "return"),
                       ("cut", lambda r: r[kind] != "return" and float(r[t]) <= ramp_end + CUT_S)):
        path = tmp / f"{seed}-{behind_mm}-{name}.csv"
        with open(path, "w", newline="") as fh:
            csv.writer(fh).writerows([head, *[r for r in body if keep(r)]])
        out[name] = str(path)
    return out


def _fit(path: str, model: str, capsys) -> dict:
    assert main(["analyze", path, "--model", model, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def _damping(res: dict) -> float:
    """Voigt's eta; for Kelvin the paper's eta of f + (eta/E2) df/dt = E1 x + eta (1 + E1/E2) dx/dt,
    which is c - tau1 E1 for the lag form f + tau1 df/dt = E1 x + c dx/dt fitted here."""
    p = {k: v["value"] for k, v in res["parameters"].items()}
    return p["eta_N_s_per_m"] - p.get("tau1_s", 0.0) * p["k_N_per_m"]


@pytest.mark.parametrize("seed", calibration_seeds(SEEDS))
def test_negative_damping_comes_from_the_record_not_the_tissue(seed, tmp_path, capsys):
    marked = _records(tmp_path, seed, 0.0, capsys)
    behind = _records(tmp_path, seed, BEHIND_MM, capsys)
    for rec in (marked["whole"], behind["whole"]):  # the whole hold: positive, as on the paper's protocols
        for model in ("voigt", "kelvin"):
            res = _fit(rec, model, capsys)
            assert _damping(res) > 0, (rec, model, res["parameters"])
            assert res["parameters"]["eta_N_s_per_m"]["value"] > 0
            assert not any("negative" in w for w in res["warnings"]), res["warnings"]
    # 10 s into the hold: negative, and the fit says it is meaningless
    voigt_cut = []
    for rec in (marked["cut"], behind["cut"]):
        res = _fit(rec, "voigt", capsys)
        voigt_cut.append(_damping(res))
        assert voigt_cut[-1] < 0, res["parameters"]
        assert any(w.startswith("viscous.eta_N_s_per_m is negative") and "physically meaningless" in w
                   for w in res["warnings"]), res["warnings"]
        res = _fit(rec, "kelvin", capsys)
        assert _damping(res) < 0, res["parameters"]  # in the paper's form (E2 < 0: softer at once than relaxed)
    # the contact behind the mark adds a stretch of ramp without force: more negative still
    assert voigt_cut[1] < voigt_cut[0]
    # the model with a stiffening spring and relaxation keeps its damping positive on the same record
    tau2 = []
    for rec in (marked["cut"], behind["cut"]):
        res = _fit(rec, "proposed", capsys)
        tau2.append(res["parameters"]["tau2_N_s_per_m2"]["value"])
        # (its damping: the elastic cubic may be flagged on a 10 s cut, `rig.analysis.fitting.fit.physics`)
        said = res["warnings"]
        assert tau2[-1] > 0 and not any("tau2" in w and "negative" in w for w in said), said
    assert abs(tau2[0] / TAU2 - 1) < 0.1  # and, with the contact where it is marked, the simulator's own
