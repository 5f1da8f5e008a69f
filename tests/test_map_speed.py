"""What makes a map's curves fast to analyse gives the same numbers as what it replaced: the lean
prediction (rig.analysis.fitting.lean) against the model's own, the contact fit from sums
(rig.analysis.fitting.contact_fit) against the general variable projection, the contact point's scan in
one pass against one point at a time, the quiet approach judged a stretch at a time against block
by block, the adequacy limits' shared draws, the AR orders chosen and the
draws whitened all at once against one row at a time, and an afmformats HDF5 map listed from its
place attributes against afmformats' full load; all on simulated maps over several seeds."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from rig.sim.afm_map import MapSpec, write_map

from rig.analysis.fitting import contact_fit, separable
from rig.analysis.fitting.fit import fit, with_record_params
from rig.analysis.fitting.lean import predictor
from rig.analysis.stats import adequacy
from rig.analysis.stats.draws import Draws
from rig.analysis.stats.noise import (
    MIN_BASELINE,
    QUIET_SIGMAS,
    ar_fit_rows,
    autocovariance,
    integral_scales,
    quiet_length,
    whiten,
)
from rig.analysis.workflow.inputs import load_inputs
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
    monkeypatch.setattr(contact_fit, "solve", lambda *a, **k: None)  # the general variable projection
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


def _both_ways(model, trials, monkeypatch):
    """The fit from sums (checked to be the one that ran) and the general path's."""
    used = []
    solve = contact_fit.solve

    def spy(*a, **k):
        got = solve(*a, **k)
        used.append(got is not None)
        return got

    monkeypatch.setattr(contact_fit, "solve", spy)
    fast = fit(model, trials)
    monkeypatch.setattr(contact_fit, "solve", lambda *a, **k: None)
    general = fit(model, trials)
    monkeypatch.setattr(contact_fit, "solve", solve)
    return fast, general, used


def _same_fit(fast, general) -> None:
    """The same optimum: no higher a cost, every parameter within a thousandth of its standard error
    (where the contact point's kink stops the general path's Newton steps, the sums' Gauss-Newton
    steps go on: on a real map's curve, E 2e-7 apart at a lower cost), the same errors and verdict."""
    assert np.sum(fast.residuals[0] ** 2) <= np.sum(general.residuals[0] ** 2) * (1 + 1e-12)
    for k, v in general.values.items():
        assert abs(fast.values[k] - v) <= 1e-3 * general.stderr[k]
        assert fast.stderr[k] == pytest.approx(general.stderr[k], rel=1e-4)
    assert fast.overall.rmse_N == pytest.approx(general.overall.rmse_N, rel=1e-12)
    assert fast.noise_N == pytest.approx(general.noise_N, rel=1e-12)
    assert fast.adequate == general.adequate
    assert fast.verdict() == general.verdict() or "RMSE" in general.verdict()


@pytest.mark.parametrize("indenter", ["paraboloid:R=5um", "sphere:R=5um", "cone:half_angle=20deg",
                                      "cylinder:R=1um"])
def test_the_fit_from_sums_lands_where_the_general_path_does(small_map, indenter, monkeypatch):
    for curve in (0, 4, 8):
        model, trials = _trials(small_map, curve, indenter)
        fast, general, used = _both_ways(model, trials, monkeypatch)
        assert used == [True]
        _same_fit(fast, general)


REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "afm-fd"


@pytest.mark.parametrize("name, curve", [("fmt-jpk-fd_spot3-0192.jpk-force", 0),
                                         ("fmt-jpk-fd_map2x2_extracted.jpk-force-map", 3),
                                         ("fmt-igor-fd_U3_3_p10004.ibw", 0)])
def test_the_fit_from_sums_lands_where_the_general_path_does_on_real_curves(name, curve, monkeypatch):
    path = REALDATA / name
    if not path.exists():
        pytest.skip(f"{path} is absent (the shared real data sit beside the project)")
    (_, rec), = each_record(path, ReadOptions(), {curve}) if "map" in name else [(0, None)]
    inputs = load_inputs([str(path)], [], [], ReadOptions(), indenter="paraboloid:R=10um", poisson=0.5,
                         segment="approach", records=[rec] if rec is not None else None)
    model = with_record_params(build_model("hertz", [], inputs.registry), inputs.trials)
    fast, general, used = _both_ways(model, inputs.trials, monkeypatch)
    assert used == [True]
    _same_fit(fast, general)


def test_the_fit_from_sums_hands_back_what_it_does_not_solve(small_map, monkeypatch):
    # a curve whose force falls with the indentation: the modulus sits on its bound (zero), which
    # the general path reports
    model, trials = _trials(small_map, 2, "paraboloid:R=5um")
    t = trials[0]
    trials = [replace(t, force_N=2 * t.force_N[0] - t.force_N)]
    fast, general, used = _both_ways(model, trials, monkeypatch)
    assert used == [False]
    assert fast.values == general.values
    # nor a model of another form
    model, trials = _trials(small_map, 2, "paraboloid:R=5um", add=["drift"])
    fast, general, used = _both_ways(model, trials, monkeypatch)
    assert used == [False]
    assert fast.values == general.values


def _quiet_length_block_by_block(y: np.ndarray) -> int:
    """The quiet approach as it was written first: one block, and the one after it, at a time."""
    n = len(y)
    head = max(n // 4, min(n, MIN_BASELINE // 2))
    if head < 32:
        return n
    block = max(8, head // 8)
    i = np.arange(n, dtype=float)

    def scatter(end):
        coef = np.polyfit(i[:end], y[:end], 1)
        r = y[:end] - np.polyval(coef, i[:end])
        means = r[: end // block * block].reshape(-1, block).mean(axis=1)
        return coef, float(np.sqrt(np.mean(means ** 2)))

    end = head
    coef, s = scatter(end)
    if s == 0.0:
        return n
    while end + block <= n:
        off = [abs(float((y[a:a + block] - np.polyval(coef, i[a:a + block])).mean())) > QUIET_SIGMAS * s
               for a in (end, end + block) if a + block <= n]
        if all(off):
            break
        end += block
        if end % (4 * block) == 0:
            coef, s_new = scatter(end)
            s = max(s, s_new) if s_new > 0 else s
    return end if n - end >= block else n


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_quiet_approach_judged_a_stretch_at_a_time_is_judged_block_by_block(seed):
    rng = np.random.default_rng(seed)
    for k in range(300):
        n = int(rng.integers(20, 3000))
        y = rng.normal(size=n) * rng.uniform(0.1, 3)
        start = int(rng.integers(0, n))
        if k % 4 == 1:  # a contact: the force rising from somewhere
            y[start:] += np.linspace(0, rng.uniform(1, 50), n - start) ** rng.uniform(1, 2)
        elif k % 4 == 2:  # a tilted baseline
            y += np.linspace(0, rng.uniform(-5, 5), n)
        elif k % 4 == 3:  # a step, on a coarse lattice
            y[start:] += rng.uniform(0.5, 3)
            y = np.round(2 * y) / 2
        assert quiet_length(y) == _quiet_length_block_by_block(y)


def test_a_batch_places_each_curve_as_the_file_lists_it(small_map, tmp_path):
    import h5py

    from rig.analysis.batch.engine import BatchRequest, analyze_chunk, plan

    broken = tmp_path / "broken.h5"
    broken.write_bytes(small_map.read_bytes())
    with h5py.File(broken, "r+") as h5:
        del h5["4"]["force"]  # curve 4 cannot be read; its row still says where it was taken
    req = BatchRequest(model="hertz", indenter="paraboloid:R=5um", segment="approach")
    curves = plan([str(broken)], req)
    assert all(c.x_m is None for c in curves)  # the plan lists numbers only: the workers place them
    rows = analyze_chunk(curves, req)
    listed = {c.enum: c for c in list_curves(small_map)}
    assert [r["curve"] for r in rows] == sorted(listed)
    for r in rows:
        c = listed[r["curve"]]
        assert (r["x_m"], r["y_m"], r["grid_x"], r["grid_y"]) == (c.x_m, c.y_m, c.grid_x, c.grid_y)
    assert [bool(r["error"]) for r in rows] == [c == 4 for c in sorted(listed)]
    assert "force" in rows[4]["error"]


def _refits(res):
    """The parts of `res`'s one trial that the systematic error refits (rig.analysis.intervals.systematic)."""
    from rig.analysis.intervals.systematic import _choices, cut

    return [cut(res.trials[0], start, end) for _, start, end in _choices(res)]


def test_a_refits_estimates_are_the_full_fits_values_and_errors(small_map):
    from rig.analysis.fitting.fit import fit_estimates

    parts = 0
    for curve in (0, 3, 6):
        model, trials = _trials(small_map, curve, "paraboloid:R=5um")
        res = fit(model, trials)
        for part in _refits(res):
            full = fit(res.model, [part], starts=1, initial=res.values)
            lean = fit_estimates(res.model, [part], starts=1, initial=res.values)
            assert lean.values == full.values
            assert lean.stderr == full.stderr
            parts += 1
    assert parts >= 6  # the depth cuts and the halved baseline, on each curve


def test_a_tared_records_refit_counts_its_zeros_error_as_the_full_fit_does(paper_075_log):
    """A record tared before its push (the rig's own trials) carries its zero's error in the
    covariance, which needs the noise: the lean refit measures it as the full fit does."""
    from rig.analysis.fitting.fit import fit_estimates, noise_blocks
    from rig.analysis.trials.data import load_trial
    from rig.models.catalogue import CATALOGUE
    from rig.models.core import Model

    trial = load_trial(paper_075_log.log_path)
    assert any(noise_blocks([trial])[3])  # a tared record: the zero's error counts
    model = Model([CATALOGUE["linear_elastic"]])
    full = fit(model, [trial], starts=1)
    lean = fit_estimates(model, [trial], starts=1)
    assert lean.values == full.values
    assert lean.stderr == full.stderr
    assert full.zero_variance  # the zero's share is in those errors


def test_the_fast_writer_writes_the_map_afmformats_export_writes(tmp_path, monkeypatch):
    """`rig sim-map` writes each curve's group itself (sim_device.afm_map._exporter): the same
    datasets, filters, chunks, attributes and attribute types as afmformats' own export, and
    afmformats loads the same curves and metadata from both."""
    import h5py
    import rig.sim.afm_map as afm_map
    from afmformats.mod_force_distance import AFMForceDistance

    spec = MapSpec(grid=(3, 2), region="drift")
    fast = write_map(tmp_path / "fast.h5", spec, seed=4)

    def theirs(h5):
        return lambda meta, cols: AFMForceDistance(data=cols, metadata=meta).export_data(h5, fmt="hdf5")

    monkeypatch.setattr(afm_map, "_exporter", theirs)
    slow = write_map(tmp_path / "slow.h5", spec, seed=4)
    with h5py.File(fast) as a, h5py.File(slow) as b:
        assert dict(a.attrs) == dict(b.attrs)
        assert list(a) == list(b) == [str(i) for i in range(6)]
        for g in a:
            ga, gb = a[g], b[g]
            assert sorted(ga.attrs) == sorted(gb.attrs)
            for k in ga.attrs:
                ia, ib = ga.attrs.get_id(k), gb.attrs.get_id(k)
                assert ia.dtype == ib.dtype and ia.shape == ib.shape, k
                assert ia.get_type().get_class() == ib.get_type().get_class(), k
                if k != "path":  # each file's own name
                    assert ga.attrs[k] == gb.attrs[k], k
            assert list(ga) == list(gb)
            for d in ga:
                x, y = ga[d], gb[d]
                assert (x.dtype, x.chunks, x.compression, x.compression_opts, x.fletcher32) == \
                    (y.dtype, y.chunks, y.compression, y.compression_opts, y.fletcher32), d
                assert dict(x.attrs) == dict(y.attrs)
                assert np.array_equal(x[()], y[()])
    mine, their = afmformats_load(fast), afmformats_load(slow)
    for c, d in zip(mine, their, strict=True):
        assert {k: v for k, v in c.metadata.items() if k != "path"} == \
            {k: v for k, v in d.metadata.items() if k != "path"}
        for col in c.columns:
            assert np.array_equal(c[col], d[col])


def afmformats_load(path: Path) -> list:
    import afmformats

    return list(afmformats.load_data(path))
