"""Creep form measured (tests/test_creep_form.py runs one seed):

    python -m pytest -p no:cacheprovider tests/bench/test_bench_creep_form.py -s -q

- a simulated creep trial (position into contact, then the force held at three levels) fitted by
  the paper's model, five seeds: every parameter within two standard errors of the simulator's;
- the brain and polymer-gel creep records fitted by kelvin and the paper's model: every rate
  inside its bounds, the RMSE over the noise printed;
- drift, frame compliance and a second relaxation hidden in simulated creep trials named first by
  --explain in 5/5 seeds each; clean creep controls name nothing;
- every catalogue effect can be fitted in creep form."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rig.sim import params as P

from rig.analysis.diagnosis.explain import explain
from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import load_trial
from rig.models import CATALOGUE, build_model
from tests.conftest import per_seed, run_sim
from tests.test_creep_form import PROTOCOL, TRUE, creep_config

REALDATA = Path(__file__).resolve().parents[3] / "shared" / "realdata"
RECORDS = ["brain-creep.jpk-force", "polymergel-creep.jpk-force"]
SEEDS = (1, 2, 3, 4, 5)

# the hidden effects, as mechanisms of the simulator, sized for these trials: the drift 0.1 N over
# the trial (2.5x the noise), the frame's give at the held 1.6 N 3.2 mm (a tenth of the travel; at
# 2000 N/m, 0.8 mm, the paper's model without it was adequate on 2 of 3 seeds), a second branch as
# stiff as the tissue at depth, with a 20 s time constant and a last hold of 60 s to show it
# against the tissue's own 8 s (over 25 s it tied with a damping and a contact offset: within 0.3 %
# of each other's error, and its fitted time constant 10-12 s, the tissue's own)
HIDDEN = {"drift": P.DriftParams(rate_N_per_s=0.004), "compliance": P.ComplianceParams(k_frame_N_per_m=500.0),
          "relaxation2": P.Relaxation2Params(k_m_N_per_m=100.0, tau_m_s=20.0)}
LONG_HOLD = """name: creep at two forces, the last held long
steps:
  - ramp: {to_mm: 10, speed_mm_s: 5}
  - ramp_force: {to_N: 0.8, rate_N_s: 1.0, max_mm: 35}
  - hold_force: {force_N: 0.8, duration_s: 8, max_mm: 35}
  - ramp_force: {to_N: 1.6, rate_N_s: 1.0, max_mm: 35}
  - hold_force: {force_N: 1.6, duration_s: 60, max_mm: 35}
  - return: {speed_mm_s: 10}
"""


def _recover(seed: int, tmp: Path) -> list[tuple[str, float, float, float]]:
    trial = load_trial(run_sim(PROTOCOL, creep_config(seed), tmp, name=f"recover{seed}.mcap").log_path)
    res = fit(build_model("proposed"), [trial])
    return [(k, v, res.values[k], res.stderr[k]) for k, v in TRUE.items()]


def test_a_simulated_creep_trial_recovers_its_parameters_five_seeds(tmp_path):
    rows = per_seed(_recover, SEEDS, tmp_path)
    bad = []
    for seed, fitted in zip(SEEDS, rows, strict=True):
        for k, true, value, se in fitted:
            z = (value - true) / se
            print(f"seed {seed} {k:<18} true {true:<10.4g} fitted {value:<11.4g} +/- {se:<9.3g} z {z:+.2f}")
            if not abs(z) <= 2.0:
                bad.append((seed, k, z))
    assert not bad, bad


@pytest.mark.parametrize("record", RECORDS)
@pytest.mark.parametrize("name", ["kelvin", "proposed"])
def test_real_creep_records_in_creep_form_keep_every_rate_inside_its_bounds(record, name):
    if not (REALDATA / record).is_file():
        pytest.skip(f"the real measurement is not at {REALDATA / record}")
    pytest.importorskip("afmformats", reason="reading JPK files needs the afm extra (afmformats)")
    trial = load_trial(REALDATA / record)
    assert trial.creep
    res = fit(build_model(name), [trial])
    print(f"\n{record} {name}: RMSE {res.overall.rmse_N / res.noise_N:.3g}x the noise; "
          + ", ".join(f"{k} = {v:.4g}" for k, v in res.values.items()))
    rates = [p.name for e in res.model.effects if e.stage in ("lag", "branch")
             for p in e.params if p.unit == "s"]
    assert rates
    at_bound = [w for w in res.warnings if ("bound" in w or "integrator" in w) and any(r in w for r in rates)]
    assert not at_bound, at_bound


def _explained(seed: int, case: str, tmp: Path) -> str:
    """The verdict's best effect on one seed (None: nothing named)."""
    cfg = creep_config(100 + seed)
    protocol = PROTOCOL
    if case in HIDDEN:
        setattr(cfg.sim.effects, case, HIDDEN[case])
        protocol = LONG_HOLD if case == "relaxation2" else PROTOCOL
    trial = load_trial(run_sim(protocol, cfg, tmp, name=f"{case}{seed}.mcap").log_path)
    base = fit(build_model("proposed"), [trial])
    ex = explain(base, dict(CATALOGUE))
    ranked = [(s.effect, round(s.delta_bic, 1), round(s.rmse_drop, 3)) for s in ex.ranked[:3]]
    print(f"{case} seed {seed}: base {base.overall.rmse_N / base.noise_N:.2f}x the noise, adequate "
          f"{base.adequate}; named {ex.best}; ranked {ranked}")
    return str(ex.best)


@pytest.mark.parametrize("case", [*HIDDEN, "clean"])
def test_hidden_effects_in_creep_trials_are_named_first(case, tmp_path):
    named = per_seed(_explained, SEEDS, case, tmp_path)
    expected = case if case in HIDDEN else "None"
    assert named.count(expected) == len(SEEDS), named


def test_every_catalogue_effect_fits_in_creep_form(tmp_path):
    """From the model's own fit, as --add and --explain start an added effect. (From the catalogue's
    starting values alone a fit can sit where no position solves the held force: measured with
    friction added, 20 evaluations, it never left its start.)"""
    trial = load_trial(run_sim(PROTOCOL, creep_config(1), tmp_path).log_path)
    base = fit(build_model("proposed"), [trial])
    for name in ("drift", "compliance", "relaxation2", "offset", "delay", "friction", "contact_offset",
                 "fractional_relaxation"):
        res = fit(build_model("proposed") + CATALOGUE[name], [trial], starts=1, initial=base.values,
                  max_nfev=20, polish=False)
        assert np.isfinite(res.overall.rmse_N), name
