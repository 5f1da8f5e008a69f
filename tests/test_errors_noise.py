"""The noise the errors rest on, where it is and as it is: a misfit is not read as a noise, a
louder noise in contact is not read as a misfit, a drift the rest shows is not called a misfit,
and nothing jumps at a sample count. Synthetic Hertz curves of known truth through the whole
pipeline (tests/bench/errors_harness.py; its 200-seed figures are in the closing benchmark).
Six to eight seeds a case here: each assertion is one the code before failed on most seeds."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest

from rig.analysis.workflow.session import AnalyzeRequest, analyze
from tests.bench.errors_harness import curve, hertz, noise, one_seed, write
from tests.conftest import per_seed


def seeds(kind: str, arg: float, misfit: float, pre: int, n: int) -> list[dict]:
    with tempfile.TemporaryDirectory() as tmp:
        return per_seed(one_seed, range(n), kind, arg, misfit, pre, tmp)


@pytest.mark.parametrize("pre", [100, 1300])
def test_a_smooth_misfit_is_not_read_as_a_noise(pre):
    """Hertz times (1 + 0.05 d/d_max), white noise: before, with 100 samples before contact every
    seed read the misfit as a walk and its statistical error was 44-289x the estimates' scatter;
    with 1300 the two regimes were 10-2000x apart. Now one regime, the noise's, and the interval
    (with the systematic error) holds each of the noiseless curve's three fits."""
    rows = seeds("white", 0.0, 0.05, pre, 6)
    E = np.array([r["E"] for r in rows])
    stat = np.array([r["stat"] for r in rows])
    # the scatter of six estimates is itself uncertain (about +/-30 %): the noise-only error against it
    assert np.all(stat < 2.5 * np.std(E)) and stat.max() < 3 * stat.min(), (stat, np.std(E))
    # the specification's 80 % of seeds for each of the three (200 seeds in the benchmark)
    assert all(sum(h) >= 5 for h in zip(*[r["held"] for r in rows], strict=True)), [r["held"] for r in rows]


@pytest.mark.parametrize("kind,arg", [("loud-white", 0.0), ("loud-ar1", 0.95)])
def test_a_noise_louder_in_contact_is_counted_where_it_is(kind, arg):
    """Exact Hertz, the noise twice as loud in contact (white; and white at rest, an AR(1) at 0.95
    in contact): read as a misfit, the errors were the quiet rest's, 0.55x and 0.08x the estimates'
    scatter. Now they are the noise's where it is."""
    rows = seeds(kind, arg, 0.0, 1300, 8)
    E = np.array([r["E"] for r in rows])
    ratio = np.median([r["stat"] for r in rows]) / np.std(E)
    assert 0.5 < ratio < 1.6, ratio


def test_the_louder_noise_is_said():
    t, pos, f, loud = curve(1300, 0.0)
    with tempfile.TemporaryDirectory() as tmp:
        path = write(Path(tmp) / "loud.csv", t, pos, f + noise("loud-white", 0.0, len(t), 1, loud))
        out = analyze(AnalyzeRequest([str(path)], model="hertz", indenter="paraboloid:R=5um"))
    said = " ".join(out.json["warnings"])
    assert "noisier in contact" in said and "the errors use that there" in said, said
    assert "errors     +/- below: statistical, the noise's given the model" in out.text
    assert out.json["fit"]["stderr_noise_model"].startswith("the noise where it is")


@pytest.mark.parametrize("kind,arg", [("ar1", 0.99), ("walk", 10.0)])
def test_a_perfect_model_under_a_slow_noise_is_adequate(kind, arg):
    """Before: NOT adequate on 15 % of seeds under an AR(1) at 0.99 and on 70 % under a walk of ten
    times the noise over the record (the walk the rest showed was not in the simulated noise)."""
    rows = seeds(kind, arg, 0.0, 1300, 8)
    assert sum(r["adequate"] for r in rows) >= 7, [r["verdict"] for r in rows]


def test_a_slow_noise_read_on_a_short_rest_is_not_called_a_misfit():
    """An AR(1) at 0.99 (correlated over 199 samples) whose quiet rest ends after 350-600 samples,
    where the slow noise first left a line: the rest reads it at 0.4 of its level and 27 samples
    of correlation, and a perfect model was NOT adequate on 3 of these 40 seeds (10 of 200), its
    residual twice the noise. The limits now allow the slowest noise such a rest cannot rule out:
    the specification's 38 of 40."""
    with tempfile.TemporaryDirectory() as tmp:
        rows = per_seed(one_seed, range(40, 80), "ar1", 0.99, 0.0, 1300, tmp)
    assert sum(r["adequate"] for r in rows) >= 38, [r["verdict"] for r in rows if not r["adequate"]]


def test_the_slowest_noise_a_rest_allows():
    """The noise's slowest root moves up by its bias and three standard errors of the rest's
    samples: far for a short rest of a slow noise, hardly for a long one, not at all for white
    noise or a noise measured on the residual."""
    from rig.analysis.stats.adequacy import slowest_allowed
    from rig.analysis.stats.noise import AT_REST, Noise, integral_scale_ar

    def rest(rho: float, n: int, source: str = AT_REST) -> Noise:
        ar = (rho,) if rho else ()
        return Noise(1.0, integral_scale_ar(ar), source, ar, 1.0, samples=n)

    assert slowest_allowed(rest(0.0, 400)) == rest(0.0, 400)
    assert slowest_allowed(rest(0.93, 400, "the residual's short-lag structure")).ar == (0.93,)
    short, long = slowest_allowed(rest(0.93, 400)), slowest_allowed(rest(0.93, 100_000))
    assert 0.99 < short.ar[0] < 0.999 and short.scale_samples > 200, short
    assert 0.93 < long.ar[0] < 0.934, long
    # an AR(2) keeps its other root; its slowest one moves
    two = slowest_allowed(Noise(1.0, 1.0, AT_REST, (1.3, -0.4), 1.0, samples=400))
    roots = np.sort(np.abs(np.roots([1.0, -two.ar[0], -two.ar[1]])))
    assert roots[0] == pytest.approx(0.5, abs=1e-9) and roots[1] > 0.85, roots


def test_no_cliff_at_two_hundred_samples_before_contact():
    """The oocyte record with 201 samples before contact had its noise from them; with 199, from
    the residual (0.068 against 1.42 nN, and standard errors 880x apart). A misfitting curve with
    190 and 210 samples before contact now gets its noise at rest both times, and errors alike."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for pre in (190, 210):
            t, pos, f, _ = curve(pre, 0.2)
            y = f + noise("white", 0.0, len(t), 3, None)
            res = hertz(write(Path(tmp) / f"c{pre}.csv", t, pos, y))
            out[pre] = (res.noise_source, res.stderr["E_Pa"], res.noise_N)
    assert out[190][0] == out[210][0] == "the force at rest before contact", out
    assert 0.5 < out[190][1] / out[210][1] < 2.0 and 0.8 < out[190][2] / out[210][2] < 1.25, out


def test_the_bootstrap_says_when_its_coverage_cannot_be_checked():
    t, pos, f, _ = curve(1300, 0.2)
    with tempfile.TemporaryDirectory() as tmp:
        path = write(Path(tmp) / "m.csv", t, pos, f + noise("white", 0.0, len(t), 2, None))
        out = analyze(AnalyzeRequest([str(path)], model="hertz", indenter="paraboloid:R=5um", bootstrap=3))
    assert not out.json["adequate"]
    assert "this coverage cannot be checked on this record" in out.text
    assert "the draws' noise: the force at rest before contact" in out.text


def _against_the_true_noise(seed: int, tmp: str) -> float:
    """One curve, white at rest and an AR(1) at 0.95 twice as loud in contact: the reported
    standard error of E over the one the sandwich gives with the noise's true covariance."""
    import rig.analysis.fitting.fit as fitting
    seen = {}
    real = fitting.hac_covariance

    def spy(J, r, lengths, *args, **kwargs):
        cov = real(J, r, lengths, *args, **kwargs)
        seen.setdefault("J", J)
        seen.setdefault("cov", cov)
        seen.setdefault("r", r)
        return cov

    fitting.hac_covariance = spy
    try:
        t, pos, f, loud = curve(1300, 0.0)
        res = hertz(write(Path(tmp) / f"c{seed}.csv", t, pos, f + noise("loud-ar1", 0.95, len(t), seed, loud)))
    finally:
        fitting.hac_covariance = real
    J = seen["J"]
    n = len(J)
    inside = loud[-n:]
    sigma = float(np.std(seen["r"][:300]))  # the noise at rest, in the residual's own unit
    i = np.arange(n)
    lag = np.abs(i[:, None] - i[None, :])
    true = np.where(inside[:, None] & inside[None, :], 4 * sigma ** 2 * 0.95 ** lag, 0.0)
    true += np.diag(np.where(inside, 0.0, sigma ** 2))
    bread = np.linalg.pinv(J.T @ J)
    truth = bread @ J.T @ true @ J @ bread
    k = list(res.values).index("E_Pa")
    return float(np.sqrt(seen["cov"][k, k] / truth[k, k]))


def test_a_noise_more_correlated_in_contact_is_measured_there():
    """White at rest, an AR(1) at 0.95 twice as loud in contact: the residual's short lags past the
    rest read it at 0.48-0.80 of the error its true covariance gives (median 0.62, 16 seeds), and the
    rows between the rest and the contact (white) were averaged in with it. Now the contact's noise
    is measured on the contact's rows, a smooth misfit taken out: each seed against the sandwich
    with the true noise, which needs no scatter over seeds to judge. A seed's ratio ranges 0.6-1.3
    (the noise measured on 1700 samples of a noise correlated over 39); the median of sixteen,
    0.96-1.04 over four sets of sixteen."""
    with tempfile.TemporaryDirectory() as tmp:
        ratios = per_seed(_against_the_true_noise, range(16), tmp)
    assert 0.85 < np.median(ratios) < 1.2 and min(ratios) > 0.5, ratios
