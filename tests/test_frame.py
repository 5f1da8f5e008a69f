"""Frame compliance: the force solve where contact starts at speed (tests/test_realdata.py:
a fit with a frame does not depend on what was fitted before it on the same motion)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from rig.models import CATALOGUE, Motion, build_model
from rig.models.frame import NotConverged, contact_rate

DT = 0.01
SPEED = 1e-3  # m/s


def ramp_hold(t_contact: float, n: int = 600) -> Motion:
    """1 mm/s into the specimen from `t_contact` for 2 s, a hold, and back at the same speed."""
    t = np.arange(n) * DT
    x = np.clip(SPEED * (t - t_contact), 0.0, 2e-3) - np.clip(SPEED * (t - 4.0), 0.0, None)
    x = np.where(t < t_contact, SPEED * (t - t_contact), x)
    return Motion(t, x, np.gradient(x, DT), DT)


@pytest.mark.parametrize("offset", [0.03, 0.3, 0.97])
def test_the_force_solves_where_a_dashpot_meets_the_specimen_mid_sample(offset):
    # a dashpot far stiffer than the frame over one sample: taken at full speed in the sample
    # where contact starts, no force satisfies that sample (the solve cycled and gave up)
    m = ramp_hold(1.0 + offset * DT)
    model = build_model("voigt") + CATALOGUE["compliance"]
    values = {"k_N_per_m": 500.0, "eta_N_s_per_m": 400.0, "k_frame_N_per_m": 2000.0}
    with warnings.catch_warnings():
        warnings.simplefilter("error", NotConverged)
        f = model.predict(values, m)
    xc = m.x_m - f / values["k_frame_N_per_m"]
    vc = contact_rate(xc, np.gradient(xc, DT), DT)
    inside = xc > 0
    tissue = np.where(inside, values["k_N_per_m"] * np.maximum(xc, 0) + values["eta_N_s_per_m"] * vc, 0.0)
    assert np.max(np.abs(f - np.maximum(tissue, 0.0))) <= 1e-9 * np.max(f)
    first = int(np.argmax(m.x_m > 0))
    # the frame's spring takes that sample's travel: the force starts from the frame, not a jump
    assert f[first] <= values["k_frame_N_per_m"] * m.x_m[first] * (1 + 1e-9)
    # then the force rises as a spring and a dashpot in series do, with time constant eta / k_frame
    assert f[first + 60] > 0.9 * values["eta_N_s_per_m"] * SPEED


def test_the_rate_is_held_to_the_indentation_only_where_contact_is_shallower_than_a_sample():
    xc = np.array([-1e-6, 0.0, 2e-6, 5e-6, 1e-5, 2e-5])
    vc = np.full(6, 1e-3)  # 1e-5 m per sample
    assert np.allclose(contact_rate(xc, vc, DT), [0.0, 0.0, 2e-4, 5e-4, 1e-3, 1e-3], rtol=1e-12, atol=0)
    assert np.allclose(contact_rate(xc, -vc, DT), [0.0, 0.0, -2e-4, -5e-4, -1e-3, -1e-3], rtol=1e-12, atol=0)
