"""A record computed independently as a fractional Maxwell material (the exact Mittag-Leffler
modulus convolved with the indentation rate: tests/test_fractional_exact.py) is fitted to its
noise by the fractional branch: adequate, nothing to add, every parameter within two standard
errors of the truth.

The rate convolved is the one the analysis reads off the record's positions in contact
(rig.analysis.trials.data), so what is checked is the branch against its exact response, not how a
rate is estimated."""

from __future__ import annotations

import numpy as np

from rig.analysis.diagnosis.explain import explain
from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import prepare
from rig.models import CATALOGUE, build_model
from rig.records.record import Record
from rig.specs.frames import Frame
from tests.conftest import per_seed
from tests.test_fractional_exact import exact_force_N

TRUTH = {"k_f_N_per_m": 0.03, "tau_f_s": 0.05, "alpha_f": 0.3}
NOISE = 5e-12  # N


def _one_seed(seed: int) -> str:
    rng = np.random.default_rng(seed)
    dt = 1e-3
    t = np.arange(0.0, 6.2, dt)
    x = np.clip(1e-6 * (t - 0.2), 0.0, 1e-6)  # at the surface 0.2 s, then 1 um in 1 s, held 5 s
    m = prepare(Record("shape", "csv", t, x, np.zeros_like(t), Frame.SURFACE)).motion
    force = exact_force_N(np.where(m.x_m > 0, m.v_m_s, 0.0), dt, *TRUTH.values())  # the rate in contact
    tare = rng.normal(0.0, NOISE, 1000)
    rec = Record(f"fractional-{seed}", "mcap", t, x, force + rng.normal(0.0, NOISE, len(t)), Frame.SURFACE,
                 baseline_force_N=tare)
    res = fit(build_model("fractional_relaxation"), [prepare(rec)])
    problems = [] if res.adequate else [res.verdict()]
    for name, true in TRUTH.items():
        se = res.stderr[name]
        if not (se and abs(res.values[name] - true) <= 2 * se):
            problems.append(f"{name} = {res.values[name]:.5g} +/- {se}, truth {true}")
    ex = explain(res, dict(CATALOGUE))
    if ex.suggestions:
        problems.append(ex.summary)
    return f"seed {seed}: " + "; ".join(problems) if problems else ""


def test_an_exact_fractional_record_fits_to_its_noise():
    failed = [p for p in per_seed(_one_seed, range(5)) if p]
    assert not failed, failed
