"""A search that can swap, not only add: a candidate that explains the residual but turns an
effect already in the model significantly negative is offered with that effect dropped, and
`--auto` takes the swap as one step.

The record: a spring with a drift of the load cell, fitted with a damping (Voigt) that the record
does not need. The drift biases the fitted damping positive; with the drift added, the damping
comes out significantly negative (the record's own damping is below zero, as another term's
misfit pulls an unneeded effect of a real model). Before, `--explain` rejected the drift as
"physically meaningless" and named an offset, which leaves half the error."""

from __future__ import annotations

import numpy as np
import pytest

from rig.analysis.diagnosis.explain import auto, explain, format_auto
from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import prepare
from rig.cli import main
from rig.models import CATALOGUE, build_model
from rig.records.csvfile import write_trial_csv
from rig.records.record import Frame, Record


def record(seed: int) -> list:
    """2 s at rest 1 mm above the surface, a ramp to 3 mm deep at 2 mm/s, a hold, the return at
    12 s, rest to 30 s (100 Hz, the position from the surface): a spring of 50 N/m with a damping
    of -3 N s/m, a drift of -2 mN/s, noise of 10 mN."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 30.0, 0.01)
    x = -1e-3 + np.clip(2e-3 * (t - 2.0), 0.0, 4e-3) - np.clip(2e-3 * (t - 12.0), 0.0, 4e-3)
    depth = np.maximum(x, 0.0)
    f = 50.0 * depth - 3.0 * np.gradient(depth, t) - 0.002 * t + 0.01 * rng.normal(size=len(t))
    return [prepare(Record(f"spring-{seed}", "csv", t, x, f, frame=Frame.SURFACE))]


def test_a_candidate_that_makes_an_effect_unphysical_is_offered_with_it_dropped():
    for seed in range(6):
        base = fit(build_model("voigt"), record(seed))
        assert base.values["eta_N_s_per_m"] > 0, base.values  # the drift hides the damping's sign
        ex = explain(base, dict(CATALOGUE))
        drift = next(s for s in ex.suggestions if s.effect == "drift")
        # offered, not rejected: the model without the damping is physical and passes
        assert drift.dropped == ("viscous",) and not drift.meaningless, (seed, drift.why)
        assert not drift.fit.model.has("viscous") and drift.fit.model.has("drift")
        assert "with viscous dropped" in drift.why
        assert drift.rmse_drop > 0.25, drift.rmse_drop
        assert ex.best == "drift", ex.summary
        assert ex.summary.startswith("most likely missing: drift, with viscous dropped"), ex.summary
        assert drift.rmse_N < 1.05 * 0.01, drift.rmse_N  # the swap leaves about the noise


def test_auto_moves_by_a_swap():
    for seed in (0, 1):
        steps = auto(fit(build_model("voigt"), record(seed)), dict(CATALOGUE))
        moves = [(s["added"], s["removed"]) for s in steps]
        assert moves[1] == ("drift", "viscous"), moves
        final = steps[-1]["fit"].model
        assert final.has("drift") and not final.has("viscous"), final.effect_names
        assert "+drift/-viscous" in format_auto(steps)


def test_the_swap_through_the_command_line(tmp_path, capsys):
    csv = tmp_path / "spring.csv"
    write_trial_csv(record(0)[0], csv)
    assert main(["analyze", str(csv), "--model", "voigt", "--explain"]) == 0
    out = capsys.readouterr().out
    assert "=> most likely missing: drift, with viscous dropped" in out, out


def test_a_delay_starts_from_the_data():
    """A delay's cost has a minimum at each ramp corner's echo; the fit starts from the delay, on a
    grid from a sample to the loading time, that best explains the misfit (from the default start
    the solver settled at half a hidden 50 ms on an oocyte record, and a damping was named)."""
    from rig.models.catalogue import _delay, _delay_guess

    trial = record(0)[0]
    m = trial.motion
    model_N = 50.0 * np.maximum(m.x_m, 0.0)
    for delay_s in (0.02, 0.05, 0.2, 0.6):
        misfit = _delay(m, model_N, delay_s) - model_N
        got = _delay_guess(m, misfit, {}, model_N)["delay_s"]
        assert got == pytest.approx(delay_s, rel=0.1), (delay_s, got)
    assert _delay_guess(m, np.zeros_like(model_N), {}, model_N) == {}  # nothing to explain: no start
