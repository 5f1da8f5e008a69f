"""A hidden effect added to a real measurement is named first by --explain.

Each shared record is first explained as well as the catalogue allows: the model `--auto`
builds on the clean record. One effect is then hidden in the record, sized from the record's
own range (a tenth of its peak force of drift over the record or of offset, a twentieth of
it of Coulomb friction, a delay of a twentieth of its loading time), and taken out of the
model if `--auto` had put it in. `--explain` must name it first."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from rig.analysis.diagnosis.explain import auto, explain
from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import TrialData, load_trial
from rig.cli import main
from rig.models import CATALOGUE, build_model
from rig.models.core import Model
from rig.records.csvfile import write_trial_csv

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
RECORDS = ["polymergel-creep.jpk-force", "brain-creep.jpk-force"]
SIZES = {"drift": 0.1, "offset": 0.1, "friction": 0.05, "delay": 0.05}
# the eight cases (four effects in each record) run with the benchmarks, a minute or two each
# (tests/bench/test_bench_realdata_explain.py); the default run keeps the command-line case

pytestmark = pytest.mark.skipif(not all((REALDATA / r).is_file() for r in RECORDS),
                                reason=f"the real measurements are not at {REALDATA}")
pytest.importorskip("afmformats", reason="reading JPK files needs the afm extra (afmformats)")


def hide(t: TrialData, effect: str) -> TrialData:
    """The record with one effect added, sized from its own force and time scales."""
    m, size = t.motion, SIZES[effect]
    F, f = t.scales.force_N, t.force_N.copy()
    if effect == "drift":
        f += size * F * (m.t_s - m.t_s[0]) / (m.t_s[-1] - m.t_s[0])
    elif effect == "offset":
        f += size * F
    elif effect == "friction":  # the guide's friction, its sign rounded over 2 % of the speed
        f += size * F * np.tanh(m.v_m_s / (0.02 * m.speed_m_s))
    elif effect == "delay":  # the force read late
        f = np.interp(m.t_s - size * t.scales.time_s, m.t_s, f, left=f[0])
    return dataclasses.replace(t, force_N=f, name=f"{t.name}+{effect}")


def explain_cleanly(record: str) -> tuple[TrialData, object]:
    """The record (in force form: the effects are hidden in its force), and the fit of the model
    `--auto` builds on it."""
    trial = load_trial(REALDATA / record, form="force")
    steps = auto(fit(build_model("proposed"), [trial]), dict(CATALOGUE))
    return trial, steps[-1]["fit"]


def check_named_first(explained: tuple, effect: str) -> None:
    """`effect` hidden in the record explained cleanly (`explain_cleanly`) is named first."""
    trial, clean = explained
    base_model = Model([e for e in clean.model.effects if e.name != effect])
    base = fit(base_model, [hide(trial, effect)], starts=1, initial=clean.values)
    ex = explain(base, dict(CATALOGUE))
    assert ex.suggestions, ex.summary
    assert ex.suggestions[0].effect == effect, [(s.effect, round(s.delta_bic, 1)) for s in ex.ranked[:4]]
    assert ex.summary.startswith(f"most likely missing: {effect}")
    assert ex.suggestions[0].rmse_drop > 0.2  # it explains a good part of the error


def test_hidden_friction_through_the_command_line(tmp_path, capsys):
    trial = load_trial(REALDATA / RECORDS[0])
    csv = tmp_path / "gel+friction.csv"
    write_trial_csv(hide(trial, "friction"), csv)
    assert main(["analyze", str(csv), "--add", "relaxation2", "--explain", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["suggestions"][0]["effect"] == "friction", out["diagnosis"]
    assert out["diagnosis"]["best"] == "friction"
    assert out["diagnosis"]["text"].startswith("most likely missing: friction")
    assert out["adequate"] is False and out["fit"]["rmse_over_noise"] > 1.2


def test_an_offset_from_the_first_sample_is_the_records_zero(tmp_path, capsys):
    """A record that does not say where its surface is does not say what its force reads at rest
    either: an offset present from its first sample is its zero, fitted with it, not an effect
    to name."""
    trial = load_trial(REALDATA / RECORDS[0])
    runs = []
    for name, t in (("gel", trial), ("gel+offset", hide(trial, "offset"))):
        csv = tmp_path / f"{name}.csv"
        write_trial_csv(t, csv)
        assert main(["analyze", str(csv), "--add", "relaxation2", "--explain", "--json"]) == 0
        runs.append(json.loads(capsys.readouterr().out))
    clean, shifted = runs
    assert "offset" not in [s["effect"] for s in shifted["suggestions"]]
    (zero_clean,), (zero_shifted,) = ([r["zero_N"] for r in run["records"]] for run in runs)
    added = SIZES["offset"] * trial.scales.force_N
    assert zero_shifted - zero_clean == pytest.approx(added, rel=1e-3)
    assert shifted["fit"]["rmse_N"] == pytest.approx(clean["fit"]["rmse_N"], rel=1e-3)


OOCYTE13 = REALDATA / "oocyte-cell1" / "cell1-0013.jpk-force"


@pytest.mark.skipif(not OOCYTE13.is_file(), reason=f"the real measurement is not at {OOCYTE13}")
def test_a_drift_the_base_model_bent_to_follow_is_still_named():
    """A drift hidden in an oocyte relaxation, explained from a clean model --auto built on the record.
    The base's own effects bend to follow the drift: refitted from the base's values with a drift
    added, the fit stayed where they held it (6 % of the error taken away, and a contact offset
    ranked first); from a fresh start the drift takes more than half, as it does from the clean
    record's values."""
    trial = load_trial(OOCYTE13, form="force")
    names = ["poly_elastic", "relaxation", "relaxation2", "fractional_relaxation", "hc_damping"]
    # a clean model --auto built on this record, where its stepwise search left it
    at = {"k1_N_per_m3": -6.5366e8, "k2_N_per_m2": 18617.4, "k3_N_per_m": -0.10613, "tau1_s": 8.15905,
          "k_m_N_per_m": 0.0081212, "tau_m_s": 2.31334, "k_f_N_per_m": 0.00556993, "tau_f_s": 0.476097,
          "alpha_f": 0.907566, "b_N_s_per_m_n1": 2.31099e10, "n": 2.34875}
    base = fit(Model([CATALOGUE[n] for n in names]), [hide(trial, "drift")], starts=1, initial=at)
    ex = explain(base, dict(CATALOGUE))
    assert ex.best == "drift", [(s.effect, round(s.delta_bic, 1), round(s.rmse_drop, 2)) for s in ex.ranked[:4]]
    assert ex.summary.startswith("most likely missing: drift"), ex.summary
    assert ex.suggestions[0].rmse_drop > 0.5, ex.summary
