"""A look-alike check between a refitted leader and a candidate known only from the screen
(fitted on the decimated copy): compared on every sample, not crashed on unequal lengths."""

from __future__ import annotations

from rig.analysis.diagnosis.explain import Suggestion, _indistinguishable
from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import decimate, load_trial
from rig.models import CATALOGUE, build_model
from rig.specs.config import RigConfig
from tests.conftest import run_sim

PROTO = ("name: ramp\nsteps:\n  - ramp: {to_mm: 30, speed_mm_s: 3}\n  - hold: {duration_s: 10}\n"
         "  - return: {to_mm: 0, speed_mm_s: 5}\n")


def test_screened_candidate_is_compared_on_every_sample(tmp_path):
    trials = [load_trial(run_sim(PROTO, RigConfig(), tmp_path).log_path)]
    model = build_model("proposed") + CATALOGUE["offset"]
    full = fit(model, trials, starts=1, polish=False)
    coarse = fit(model, [decimate(t, 4) for t in trials], starts=1, initial=full.values, polish=False)
    assert len(coarse.predictions[0]) < len(full.predictions[0])
    a = Suggestion("offset", full.overall.rmse_N, 0.1, -50.0, "", full)
    b = Suggestion("offset_again", full.overall.rmse_N, 0.1, -49.0, "", coarse)
    pair = _indistinguishable([a, b], trials)  # the same model: the same curve on every sample
    assert pair and pair[0]["effects"] == ["offset", "offset_again"]
    shifted = dict(coarse.values, offset_N=coarse.values["offset_N"] + 2 * full.noise_N)
    b.fit.values = shifted  # another curve by two noise levels: not a look-alike
    assert _indistinguishable([a, b], trials) == []
