"""What makes a map's curves fast to analyse gives the same numbers as what it replaced: the lean
prediction (rig.analysis.lean) against the model's own, the contact point's scan in one pass
against one point at a time, the adequacy limits' shared draws, the AR orders chosen and the
draws whitened all at once against one row at a time, and an afmformats HDF5 map listed from its
place attributes against afmformats' full load; all on simulated maps over several seeds."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rig.sim.afm_map import MapSpec, write_map

from rig.analysis import adequacy, separable
from rig.analysis.analyze import load_inputs
from rig.analysis.draws import Draws
from rig.analysis.fit import fit, with_record_params
from rig.analysis.lean import predictor
from rig.analysis.noise import ar_fit_rows, autocovariance, integral_scales, whiten
from rig.models.catalogue import build_model
from rig.records import ReadOptions, each_record, list_curves
from rig.records.afm import HDF5, _list_hdf5, _load, count_curves

pytest.importorskip("afmformats", reason="the simulated AFM map is written and read through afmformats")
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module", params=[1, 2, 3])
def small_map(request, tmp_path_factory):
    return write_map(tmp_path_factory.mktemp("map") / f"m{request.param}.h5", MapSpec(grid=(3, 3)),
                     seed=request.param)


def _trials(path, curve: int, indenter: str, add=()):
    (_, rec), = each_record(path, ReadOptions(), {curve})
    inputs = load_inputs([str(path)], [], [], ReadOptions(), indenter=indenter, poisson=0.5, segment="approach",
                         records=[rec])
    model = with_record_params(build_model("hertz", list(add), inputs.registry), inputs.trials)
    return model, inputs.trials


@pytest.mark.parametrize("indenter", ["paraboloid:R=5um", "sphere:R=5um", "cone:half_angle=20deg"])
def test_the_lean_prediction_is_the_models_to_the_bit(small_map, indenter):
    rng = np.random.default_rng(7)
    for curve in (0, 4, 8):
        model, trials = _trials(small_map, curve, indenter)
        m = trials[0].motion
        at = {"E_Pa": 1e3, "x_c_m": 0.0, "offset_N": 0.0}
        predict = predictor(model, [m], at)
        assert predict != model.predict  # this model's form is the lean one's
        travel = np.ptp(m.x_m)
        for _ in range(20):
            values = {"E_Pa": float(10 ** rng.uniform(1, 6)) * rng.choice([1, -1]),
                      "x_c_m": float(np.min(m.x_m) + rng.uniform(-0.1, 1.1) * travel),
                      "offset_N": float(rng.normal(0, 1e-9))}
            assert np.array_equal(predict(values, m), model.predict(values, m))


def test_a_model_of_another_form_keeps_its_own_prediction(small_map):
    model, trials = _trials(small_map, 0, "paraboloid:R=5um", add=["drift"])
    assert predictor(model, [trials[0].motion], dict.fromkeys(model.param_names, 0.0)) == model.predict


def test_the_scan_in_one_pass_lands_where_one_point_at_a_time_does(small_map, monkeypatch):
    solve = separable.solve
    for curve in (1, 5, 7):
        model, trials = _trials(small_map, curve, "paraboloid:R=5um")
        fast = fit(model, trials)
        monkeypatch.setattr(separable, "solve", lambda *a, **k: solve(*a[:7]))  # no predict_many
        slow = fit(model, trials)
        monkeypatch.setattr(separable, "solve", solve)
        assert fast.values == slow.values
        assert fast.stderr == slow.stderr
        assert fast.adequate == slow.adequate


def test_the_limits_draws_are_shared_and_the_same(small_map):
    model, trials = _trials(small_map, 2, "paraboloid:R=5um")
    res = fit(model, trials)
    adequacy._SPECTRA.clear()
    first = adequacy.limits(res.noise, res.predictions, [t.phase for t in trials], ("approach",))
    assert adequacy._SPECTRA  # kept for the next curve
    again = adequacy.limits(res.noise, res.predictions, [t.phase for t in trials], ("approach",))
    assert first == again
    # and the shared transform is the transform of the stream's own draws, the stream moved past them
    (key, spectrum), = list(adequacy._SPECTRA.items())[:1]
    rng = Draws(0)
    assert key[0] == rng.position
    assert np.array_equal(spectrum, np.fft.rfft(rng.standard_normal(key[1:]), axis=1))
    cached = Draws(0)
    adequacy._white_spectrum(cached, *key[1:])
    assert cached.position == rng.position


def _ar_fit_rows_one_by_one(gamma: np.ndarray, n: int, max_order: int = 24) -> list[np.ndarray]:
    """The order selection as it was written first: each row's best copied as it improves."""
    rows = gamma.shape[0]
    order = min(max_order, gamma.shape[1] - 1, max(n // 10, 1))
    v = np.where(gamma[:, 0] > 0, gamma[:, 0], 1.0)
    phi = np.zeros((rows, 0))
    best_crit = n * np.log(v)
    best = [np.zeros(0)] * rows
    alive = gamma[:, 0] > 0
    for k in range(1, order + 1):
        acc = gamma[:, k] - np.einsum("ij,ij->i", phi, gamma[:, k - 1:0:-1]) if k > 1 else gamma[:, 1].copy()
        refl = acc / v
        phi = np.column_stack([phi - refl[:, None] * phi[:, ::-1], refl])
        v = v * (1.0 - refl ** 2)
        alive &= v > 0
        crit = n * np.log(np.where(alive, v, 1.0)) + k * math.log(n)
        better = alive & (crit < best_crit)
        for i in np.flatnonzero(better):
            best[i] = phi[i].copy()
        best_crit = np.where(better, crit, best_crit)
    return best


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_ar_orders_and_whitening_all_at_once_are_one_at_a_time(seed):
    rng = np.random.default_rng(seed)
    n = 600
    # filtered noise of several colours, so that the orders chosen differ from row to row
    x = rng.standard_normal((24, n + 50))
    rows = np.array([np.convolve(x[i], np.ones(1 + i % 7) / (1 + i % 7), mode="same")[:n] for i in range(24)])
    gamma = autocovariance(rows, 24)
    got, want = ar_fit_rows(gamma, n), _ar_fit_rows_one_by_one(gamma, n)
    assert len({len(a) for a in got}) > 1
    assert all(np.array_equal(a, b) for a, b in zip(got, want, strict=True))
    p = max(len(a) for a in got)
    one_by_one = np.array([whiten(rows[k], a)[-(n - p):] if len(a) else rows[k][-(n - p):]
                           for k, a in enumerate(got)])
    assert np.array_equal(adequacy._whitened_scales(rows, got), integral_scales(one_by_one))


def test_a_map_listed_from_its_place_attributes_is_listed_as_afmformats_loads_it(small_map):
    data, _ = _load(small_map, HDF5, ReadOptions())
    full = sorted(int(d.enum) for d in data)
    listed = _list_hdf5(small_map, ReadOptions())
    assert [c.enum for c in listed] == full
    assert listed == list_curves(small_map)
    assert count_curves(small_map) == len(full) == 9
    for c, d in zip(listed, sorted(data, key=lambda d: int(d.enum)), strict=True):
        md = d.metadata
        assert (c.x_m, c.y_m) == (md["position x"], md["position y"])
        assert (c.grid_x, c.grid_y) == (md["grid index x"], md["grid index y"])
