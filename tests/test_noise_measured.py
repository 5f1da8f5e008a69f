"""The noise is measured where the record shows it alone: the quiet part of the approach, never
what a contact estimate later calls baseline; quantisation is found and allowed for; the two
estimates (approach and residual) are compared and a disagreement is said.

Synthetic curves are written here from a power law of the depth (F ~ d^n past a surface away from
the position's zero, white noise of known size) and fitted with `power_elastic`, its exponent
free, the contact point and the zero fitted as for any position-only record."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rig.analysis.fitting.fit import fit
from rig.analysis.stats import noise as noise_module
from rig.analysis.stats.noise import from_baseline, from_residual
from rig.analysis.trials.data import prepare
from rig.cli import main
from rig.models import build_model
from rig.records.record import Record
from tests.conftest import per_seed

SIGMA = 5e-12  # N
REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
CREEP = ["polymergel-creep.jpk-force", "brain-creep.jpk-force"]


def power_curve(n_exp: float, seed: int, sigma: float = SIGMA) -> tuple[Record, float]:
    """10 um of approach, then 4 um into a specimen whose force grows as the depth to the n, 2 nN
    at the deepest; the position from an arbitrary zero. Returns the record and the surface in its
    travel from the first sample."""
    rng = np.random.default_rng(seed)
    t = np.arange(3000) * 1e-3
    zero = 3.7e-6 + 1e-6 * seed
    pos = zero + 14e-6 * t / t[-1]
    d = np.maximum(pos - (zero + 10e-6), 0.0)
    force = 2e-9 * (d / 4e-6) ** n_exp + 1e-10 + rng.normal(0.0, sigma, len(t))
    return Record(f"power-{n_exp}-{seed}", "csv", t, pos, force), 10e-6


def _power_fit(seed: int, n_exp: float) -> tuple[float, float, float]:
    rec, _ = power_curve(n_exp, seed)
    res = fit(build_model("power_elastic"), [prepare(rec)])
    return res.values["n"], res.stderr["n"], res.noise_N


@pytest.mark.parametrize("n_exp", [1.5, 2.0, 3.0])
def test_the_exponent_within_two_errors_and_the_noise_within_ten_percent(n_exp):
    """A late contact estimate would count the first touch as noise (21.6 pN of 5 for n = 1.5, and
    the exponent 22 standard errors off): the fitted contact and the quiet approach do not."""
    for seed, (n, se, noise) in zip(range(5), per_seed(_power_fit, range(5), n_exp), strict=True):
        assert abs(n - n_exp) <= 2 * se, (seed, n, se)
        assert noise == pytest.approx(SIGMA, rel=0.1), (seed, noise)


def test_the_quiet_part_leaves_out_a_slow_rise_before_contact():
    """Drag or long-range forces lift the force before the touch; that rise is signal, not noise."""
    rec, _ = power_curve(1.5, 3)
    t = rec.t_s
    rise = 3e-10 * np.clip((t - 0.9) / 1.2, 0.0, None) ** 2  # from 0.9 s to the touch at 2.1 s
    rec = Record(rec.name, rec.source, t, rec.position_m, rec.force_N + rise)
    trial = prepare(rec)
    # it ends before the rise reaches twice the noise (at 1119 samples): barely a noise's worth in
    assert 600 <= trial.baseline_n <= 1119
    assert trial.baseline_noise_N == pytest.approx(SIGMA, rel=0.1)


@pytest.mark.parametrize("step_sigmas", [2.0, 4.0])
def test_a_quantised_force_is_found_and_its_error_added(step_sigmas):
    rng = np.random.default_rng(int(step_sigmas))
    q = step_sigmas * SIGMA
    at_rest = q * np.round((0.37 * q + rng.normal(0.0, SIGMA, 1500)) / q)
    quantum = noise_module.quantum  # what the lattice's step is read by
    assert quantum(at_rest) == pytest.approx(q, rel=1e-6)
    est = from_baseline([at_rest])
    assert est.quantum_N == pytest.approx(q, rel=1e-6)
    assert est.gauss_std_N == pytest.approx(SIGMA, rel=0.15)
    # what a residual shows once the force moves through the levels: the noise and the rounding
    assert est.std_N == pytest.approx(np.sqrt(SIGMA ** 2 + q ** 2 / 12), rel=0.1)
    assert quantum(rng.normal(0.0, SIGMA, 1500)) == 0.0


@pytest.mark.parametrize("seed", range(3))
def test_an_averaging_adc_is_read_from_the_residual_without_a_clip(seed):
    """A 10-sample boxcar (no record at rest): an AR(1) read of lags 1 and 2 clips at rho = 0.98 and
    calls the noise 2.2x its size; the residual's structure over a few dozen lags does not."""
    rng = np.random.default_rng(seed)
    w = rng.normal(0.0, 1.0, 6009)
    noise = np.convolve(w, np.ones(10) / 10, mode="valid")
    noise *= SIGMA / np.std(noise)
    t = np.linspace(0.0, 1.0, len(noise))
    misfit = 3 * SIGMA * np.sin(2 * np.pi * 1.5 * t)  # a smooth model error larger than the noise
    est = from_residual([noise + misfit])
    assert est.std_N == pytest.approx(SIGMA, rel=0.15)
    assert est.scale_samples == pytest.approx(10.0, rel=0.35)


needs_creep = pytest.mark.skipif(not all((REALDATA / r).is_file() for r in CREEP),
                                 reason=f"the real measurements are not at {REALDATA}")


@needs_creep
@pytest.mark.parametrize("record", CREEP)
def test_real_creep_records_read_the_noise_of_their_quiet_approach(record, capsys):
    """The brain and gel creep records: the approach shows about 5 pN; 18.8 and 25.8 pN came from
    counting the first touch as baseline."""
    pytest.importorskip("afmformats", reason="reading JPK files needs the afm extra (afmformats)")
    assert main(["analyze", str(REALDATA / record), "--model", "kelvin", "--form", "force", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert 3e-12 < out["fit"]["noise_N"] < 7e-12, out["fit"]
    assert out["fit"]["noise_source"] == "the force at rest before contact"


def test_a_disagreement_between_the_two_estimates_is_said():
    """The approach quiet at 5 pN, the contact noisier (a sensor that changes in contact): the
    report says what the residual's short-lag structure reads."""
    rec, _ = power_curve(1.5, 4)
    rng = np.random.default_rng(9)
    noisy = np.where(rec.position_m - rec.position_m[0] > 10e-6, rng.normal(0.0, 4 * SIGMA, rec.n), 0.0)
    rec = Record(rec.name, rec.source, rec.t_s, rec.position_m, rec.force_N + noisy)
    res = fit(build_model("power_elastic"), [prepare(rec)])
    said = [w for w in res.warnings if w.startswith("noise: the residual's short-lag structure reads")]
    assert said, res.warnings
    clean, _ = power_curve(1.5, 4)
    quiet = fit(build_model("power_elastic"), [prepare(clean)])
    assert not [w for w in quiet.warnings if w.startswith("noise:")]
