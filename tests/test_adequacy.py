"""The adequacy rule on ordinary sensors: a perfect model is adequate and a misfit of 1.5x the
noise is caught, whatever the sensor does to its noise (quantised on a coarse lattice, filtered
by a first- or second-order low-pass or a 10-sample averaging ADC) and however little approach
the record has to measure it on.

Two kinds of record: an AFM curve written from the textbook Hertz law (a paraboloid, the surface
away from the position's zero; approach, hold, retract at 1 kHz), fitted with the `hertz` model;
and a trial as the rig logs it (100 Hz, from the surface, the load cell's tare before it; a
ramp and a 30 s hold of a standard linear solid, which relaxes slowly through the quantiser's
levels), fitted with `kelvin`, the model that wrote it."""

from __future__ import annotations

import numpy as np
import pytest

from rig.analysis.diagnosis.explain import _summary
from rig.analysis.fitting.fit import fit
from rig.analysis.fitting.result import FitResult
from rig.analysis.trials.data import prepare
from rig.models import CATALOGUE, build_model
from rig.models.catalogue import CONTACT, CONTACT_POINT, contact_effect
from rig.models.contact import parse_indenter
from rig.models.core import Motion
from rig.records.record import Record
from rig.specs.frames import Frame
from tests.conftest import per_seed

SIGMA = 5e-12  # N: the noise's standard deviation as the sensor delivers it
E_TRUE, R = 12e3, 5e-6
INDENTER = "paraboloid:R=5um"
SENSORS = ("quantised 2 sigma", "quantised 4 sigma", "first-order low-pass", "second-order low-pass",
           "10-sample boxcar", "short approach")


def sensor_noise(kind: str, n: int, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Noise of standard deviation SIGMA as `kind` delivers it, and its quantisation step."""
    w = rng.standard_normal(n + 2000)
    if kind == "first-order low-pass":  # time constant 5 samples
        x = _lowpass(w, 5.0)
    elif kind == "second-order low-pass":  # two such stages
        x = _lowpass(_lowpass(w, 3.0), 3.0)
    elif kind == "10-sample boxcar":
        x = np.convolve(w, np.ones(10) / 10, mode="same")
    else:
        x = w
    x = x[2000:]
    q = {"quantised 2 sigma": 2 * SIGMA, "quantised 4 sigma": 4 * SIGMA}.get(kind, 0.0)
    return SIGMA * x / np.std(x), q


def _lowpass(w: np.ndarray, tau: float) -> np.ndarray:
    a = np.exp(-1.0 / tau)
    out = np.empty_like(w)
    acc = 0.0
    for i, v in enumerate(w):
        acc = a * acc + (1 - a) * v
        out[i] = acc
    return out


def curve(kind: str, seed: int, misfit: float) -> Record:
    """Approach to 1.5 um past a surface 2.5 um (short: 0.75 um) into the travel, hold, retract;
    `misfit`: a smooth force the model lacks, of that many noise standard deviations (RMS)."""
    rng = np.random.default_rng(seed)
    dt, v = 1e-3, 2.5e-6
    surface = 0.75e-6 if kind == "short approach" else 2.5e-6  # 300 or 1000 samples of approach
    depth = surface + 1.5e-6
    t_in = depth / v
    t = np.arange(0.0, 2 * t_in + 0.6, dt)
    pos = np.where(t < t_in, v * t, np.where(t < t_in + 0.6, depth, depth - v * (t - t_in - 0.6)))
    d = np.clip(pos - surface, 0.0, None)
    force = 4.0 / 3.0 * E_TRUE / (1 - 0.5 ** 2) * np.sqrt(R) * d ** 1.5 + 0.2e-9
    if misfit:
        inside = d > 0
        bump = np.where(inside, np.sin(2 * np.pi * np.cumsum(inside) / inside.sum() * 2.0), 0.0)
        force = force + bump * misfit * SIGMA / np.sqrt(np.mean(bump ** 2))
    noise, q = sensor_noise(kind, len(t), rng)
    f = force + noise
    if q:
        f = q * np.round(f / q)
    return Record(f"{kind}-{seed}", "csv", t, pos + 3.1e-6, f)


KELVIN = {"k_N_per_m": 50.0, "eta_N_s_per_m": 400.0, "tau1_s": 4.0}


def trial(kind: str, seed: int, misfit: float) -> Record:
    """A ramp at 2 mm/s to 3 mm and a 30 s hold at 100 Hz, logged from the surface with 10 s
    (short: 3 s) of the load cell at rest before it; the force a standard linear solid's."""
    rng = np.random.default_rng(seed + 1000)
    dt = 0.01
    t = np.arange(0.0, 31.5, dt)
    x = np.minimum(2e-3 * t, 3e-3)
    v = np.gradient(x, dt)
    force = build_model("kelvin").predict(KELVIN, Motion(t, x, v, dt))
    force = force / float(np.max(force)) * 1000 * SIGMA  # the noise a thousandth of the peak
    if misfit:
        bump = np.sin(2 * np.pi * t / t[-1] * 3.0)
        force = force + bump * misfit * SIGMA / np.sqrt(np.mean(bump ** 2))
    tare = 300 if kind == "short approach" else 1000
    noise, q = sensor_noise(kind, len(t) + tare, rng)
    f = np.concatenate([np.zeros(tare), force]) + noise
    if q:
        f = q * np.round(f / q)
    return Record(f"{kind}-{seed}", "mcap", t, x, f[tare:], Frame.SURFACE, baseline_force_N=f[:tare])


def _verdicts(seed: int, kind: str, record: str) -> tuple[bool, bool, str]:
    if record == "afm":
        model = build_model("hertz", registry={**CATALOGUE, CONTACT: contact_effect(parse_indenter(INDENTER)),
                                               CONTACT_POINT.name: CONTACT_POINT})
        make = curve
    else:
        model, make = build_model("kelvin"), trial
    perfect = fit(model, [prepare(make(kind, seed, 0.0))])
    missed = fit(model, [prepare(make(kind, seed, 1.5))])
    return perfect.adequate, missed.adequate, perfect.verdict()


def check(kind: str, record: str, seeds: range, perfect_at_least: int, caught_at_least: int) -> None:
    out = per_seed(_verdicts, seeds, kind, record)
    perfect = sum(a for a, _, _ in out)
    caught = sum(not b for _, b, _ in out)
    said = sorted({v for a, _, v in out if not a})[:3]
    print(f"{record} {kind}: adequate {perfect}/{len(out)}, misfit caught {caught}/{len(out)}")
    assert perfect >= perfect_at_least and caught >= caught_at_least, (perfect, caught, said)


@pytest.mark.parametrize("record", ["afm", "rig"])
@pytest.mark.parametrize("kind", SENSORS)
def test_a_perfect_model_is_adequate_and_a_misfit_is_caught(kind, record):
    """Twelve seeds here (11 adequate, 10 caught at least); the forty of the specification, 38
    and 36, in tests/bench/test_bench_adequacy.py."""
    check(kind, record, range(12), 11, 10)


def _shortcut(seed: int, kind: str) -> list[tuple[bool, bool, bool]]:
    """For a perfect and a missing model's fit: whether the verdict came without simulating the
    limits, whether the simulated limits then say the same, and whether they are at or above the
    tolerances."""
    from rig.analysis.stats.adequacy import ADEQUATE_PHASE, ADEQUATE_RMSE, ADEQUATE_WHITE

    model = build_model("hertz", registry={**CATALOGUE, CONTACT: contact_effect(parse_indenter(INDENTER)),
                                           CONTACT_POINT.name: CONTACT_POINT})
    out = []
    for misfit in (0.0, 0.6, 1.5):
        res = fit(model, [prepare(curve(kind, seed, misfit))])
        adequate = res.adequate
        skipped = "limits" not in res.__dict__
        lim = res.limits
        noise = max(res.noise_N, 1e-300)
        by_limits = (res.overall.rmse_N / noise <= lim.rmse and res.whitened_L <= lim.white
                     and all(s.rmse_N / noise <= lim.phase.get(ph, ADEQUATE_PHASE)
                             for ph, s in res.phases.items() if s is not None))
        floors = (lim.rmse >= ADEQUATE_RMSE and lim.white >= ADEQUATE_WHITE
                  and all(v >= ADEQUATE_PHASE for v in lim.phase.values()))
        out.append((skipped, by_limits == adequate, floors))
    return out


def test_a_verdict_within_the_tolerances_skips_the_simulation_and_is_the_same():
    """A residual within the tolerances themselves passes whatever the simulated limits (they
    only widen them), so the verdict is given without them: on curves of white, quantised and
    filtered noise at four seeds, with and without a misfit, every verdict is the limits' own."""
    kinds = ("short approach", "quantised 2 sigma", "first-order low-pass")
    got = [row for kind in kinds for rows in per_seed(_shortcut, range(4), kind) for row in rows]
    assert all(same for _, same, _ in got), got
    assert all(floors for _, _, floors in got), got
    # the shortcut is taken, and not always: some verdicts still need the simulated tail
    assert 0 < sum(skipped for skipped, _, _ in got) < len(got), got


class _Failing:
    """A fit's verdict parts alone: the tests it fails, its overall error against the noise."""

    def __init__(self, failed: list[tuple[str, float, float]], rmse_over_noise: float) -> None:
        from types import SimpleNamespace

        self._failed = lambda: failed
        self.noise_N, self.overall = 1.0, SimpleNamespace(rmse_N=rmse_over_noise)
        self.adequate = not failed
        self.phases = {"ramp": SimpleNamespace(rmse_N=rmse_over_noise), "hold_early": None}

    inadequate_because = FitResult.inadequate_because

    def force_text(self, value_N: float) -> str:
        return f"{value_N:.4g} N"


def test_a_residual_within_the_noise_that_fails_says_what_fails():
    # a real AFM curve's clean model read "NOT adequate (RMSE 0.008652 nN vs noise 0.008977 nN)" in the
    # verdict of --explain: below the noise, and not adequate, with nothing said of why
    shape = _Failing([("correlation", 12.0, 3.0)], 0.96)
    said = FitResult.verdict(shape)
    assert said.startswith("NOT adequate (RMSE 0.96x the noise, but the residual is correlated over 12.0"), said
    assert shape.inadequate_because().endswith("a shape the model misses")
    verdict = _summary(shape, None, [], False)  # what --explain says of it
    assert verdict.startswith("the model is NOT adequate (RMSE 0.96 N vs noise 1 N; worst in ramp: 0.96 N; "
                              "the residual is correlated over 12.0 samples"), verdict
    phase = _Failing([("ramp", 1.9, 1.4)], 0.9)
    assert phase.inadequate_because() == "1.9x the noise in ramp, above 1.4x"
    said = FitResult.verdict(phase)
    assert said == "NOT adequate (RMSE 0.9x the noise overall, but 1.9x in ramp, above 1.4x)", said
    assert _Failing([("rmse", 3.0, 1.3), ("correlation", 12.0, 3.0)], 3.0).inadequate_because() == ""
    assert _Failing([], 0.9).inadequate_because() == ""
