"""The simulated AFM force map (rig.sim.afm_map): written in afmformats' HDF5 format, read by
afmformats itself (curves, grid, positions, its QMap) and by rig's reader (list_curves,
iter_records, read_record); a Hertz fit through rig's analysis recovers the truth's modulus
and contact point on plain curves over several seeds; the hidden region's curves depart from
the plain law as their effect says and the others do not."""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys

import numpy as np
import pytest
from rig.sim.afm_map import COLUMNS, DIMITRIADIS, MapSpec, add_map_parser, truth_path, write_map

from rig.analysis.workflow.session import AnalyzeRequest, analyze
from rig.errors import RigError
from rig.records import ReadOptions, each_record, iter_records, list_curves, read_record

afmformats = pytest.importorskip("afmformats", reason="the simulated AFM map is written and read through "
                                                      "afmformats (the afm extra)")

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

SPEC = MapSpec(grid=(8, 8))
INDENTER = f"paraboloid:R={SPEC.radius_um:g}um"


def _write(tmp_path_factory, name: str, spec: MapSpec, seed: int):
    path = write_map(tmp_path_factory.mktemp("map") / f"{name}.h5", spec, seed=seed)
    return path, json.loads(truth_path(path).read_text())


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    return _write(tmp_path_factory, "plain", SPEC, 1)


@pytest.fixture(scope="module", params=["thin_layer", "drift", "tilt", "adhesion"])
def regional(request, tmp_path_factory):
    spec = MapSpec(grid=(8, 8), region=request.param)
    return (spec, *_write(tmp_path_factory, request.param, spec, 7))


def _hertz(spec: MapSpec, E: float, d: np.ndarray) -> np.ndarray:
    R = spec.radius_um * 1e-6
    return 4 / 3 * E / (1 - spec.poisson**2) * math.sqrt(R) * np.clip(d, 0, None) ** 1.5


def _curve(path, n: int):
    """afmformats' columns of curve n, as arrays."""
    d = next(c for c in afmformats.load_data(path) if c.enum == n)
    return {col: np.asarray(d[col]) for col in COLUMNS}


def _free(truth_curve: dict, travel: np.ndarray, margin_m: float = 0.2e-6) -> np.ndarray:
    """Samples well before contact."""
    return travel < truth_curve["contact_travel_m"] - margin_m


# -- afmformats reads it ------------------------------------------------------------------------


def test_afmformats_reads_every_curve_with_its_place_on_the_grid(plain):
    path, truth = plain
    data = afmformats.load_data(path)
    assert len(data) == 64 == len(truth["curves"])
    assert [d.enum for d in data] == list(range(64))
    for d, t in zip(data, truth["curves"], strict=True):
        md = d.metadata
        assert d.modality == md["imaging mode"] == "force-distance"
        assert sorted(d.columns) == sorted(COLUMNS)
        assert (md["grid index x"], md["grid index y"]) == tuple(t["grid_index"])
        assert (md["grid shape x"], md["grid shape y"]) == (8, 8)
        assert (md["position x"], md["position y"]) == pytest.approx(t["position_m"], abs=1e-12)
        assert md["spring constant"] == SPEC.spring_constant_N_per_m
        assert md["sensitivity"] == SPEC.sensitivity_m_per_V
        assert md["point count"] == len(d) == t["approach_samples"] + t["retract_samples"]
        # afmformats' own position-to-index mapping finds the same pixel
        for ax, i in (("x", 0), ("y", 1)):
            index = md._convert_position_to_index(md[f"position {ax}"], md[f"grid size {ax}"],
                                                  md[f"grid center {ax}"], md[f"grid shape {ax}"])
            assert index == t["grid_index"][i]
        seg = np.asarray(d["segment"])
        assert np.array_equal(np.unique(seg), [0, 1]) and np.all(np.diff(seg.astype(int)) >= 0)
        assert np.all(np.diff(np.asarray(d["time"])) > 0)
    qmap = afmformats.AFMQMap(path)
    assert qmap.shape == (8, 8)
    cx, cy = SPEC.center_um
    sx, sy = SPEC.size_um
    assert qmap.extent == pytest.approx((cx - sx / 2, cx + sx / 2, cy - sy / 2, cy + sy / 2))
    # raster order, x fastest: row y of the map holds curves 8y .. 8y + 7
    order = qmap.get_qmap("data: scan order", qmap_only=True)
    assert np.array_equal(order, np.arange(64).reshape(8, 8))


def test_the_heights_fall_on_the_approach_and_the_force_rises_by_the_setpoint(plain):
    path, truth = plain
    for n in (0, 37):
        c, t = _curve(path, n), truth["curves"][n]
        app = c["segment"] == 0
        piezo = c["height (piezo)"]
        assert np.all(np.diff(piezo[app]) < 0) and np.all(np.diff(piezo[~app]) > 0)
        assert np.allclose(c["height (measured)"] - piezo, SPEC.sensor_offset_um * 1e-6, atol=1e-10)
        rise = c["force"][app][-5:].mean() - c["force"][app][:50].mean()
        assert rise == pytest.approx(SPEC.setpoint_nN * 1e-9, rel=0.02)
        assert piezo[0] - piezo[app][-1] == pytest.approx(t["z_range_m"], abs=1e-10)


# -- rig reads it -------------------------------------------------------------------------------


def test_rig_lists_and_reads_every_curve(plain):
    path, truth = plain
    infos = list_curves(path)
    assert [i.enum for i in infos] == list(range(64))
    for info, t in zip(infos, truth["curves"], strict=True):
        assert (info.grid_x, info.grid_y) == tuple(t["grid_index"]) and info.grid_shape == (8, 8)
        assert (info.x_m, info.y_m) == pytest.approx(t["position_m"], abs=1e-12)
    records = list(iter_records(path))
    assert len(records) == 64
    for n in (0, 9, 63):
        rec = read_record(path, ReadOptions(curve=n))
        same = records[n]
        assert rec.meta["curve"] == same.meta["curve"] == n
        assert rec.meta["grid_index"] == tuple(truth["curves"][n]["grid_index"])
        assert rec.meta["spring_constant_N_per_m"] == SPEC.spring_constant_N_per_m
        assert rec.meta["instrument"] == "rig sim-map" and rec.meta["modality"] == "force-distance"
        assert np.array_equal(rec.force_N, same.force_N) and np.array_equal(rec.position_m, same.position_m)
        n_app = truth["curves"][n]["approach_samples"]
        assert list(rec.segment).count("approach") == n_app
        assert set(rec.segment) == {"approach", "retract"}
    # a batch's chunk reads only its own curves, and reads them as the whole file's reading does
    some = dict(each_record(path, None, {3, 9, 40}))
    assert sorted(some) == [3, 9, 40]
    for n, rec in some.items():
        whole = records[n]
        assert rec.meta == whole.meta and rec.notes == whole.notes
        for f in ("t_s", "position_m", "force_N"):
            assert np.array_equal(getattr(rec, f), getattr(whole, f))


def test_the_same_seed_writes_the_same_map(tmp_path):
    spec = MapSpec(grid=(3, 2), region="drift")
    a, b, c = (write_map(tmp_path / f"{name}.h5", spec, seed=s) for name, s in (("a", 5), ("b", 5), ("c", 6)))
    ta, tb, tc = (json.loads(truth_path(p).read_text()) for p in (a, b, c))
    for t in (ta, tb, tc):
        del t["file"]
    assert ta == tb and ta != tc
    for n in range(6):
        ca, cb = _curve(a, n), _curve(b, n)
        assert all(np.array_equal(ca[col], cb[col]) for col in COLUMNS)
    assert not np.array_equal(_curve(a, 0)["force"][:100], _curve(c, 0)["force"][:100])


# -- the truth is recovered ---------------------------------------------------------------------


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_a_hertz_fit_recovers_the_truths_modulus_and_contact(tmp_path, seed):
    path = write_map(tmp_path / "map.h5", SPEC, seed=seed)
    truth = json.loads(truth_path(path).read_text())["curves"]
    E = np.array([c["E_Pa"] for c in truth])
    # the softest, the stiffest and one between: the map spans the whole range
    picks = {int(np.argmin(E)), int(np.argmax(E)), int(np.argsort(E)[len(E) // 2])}
    assert E.max() / E.min() > 5
    for n in sorted(picks):
        req = AnalyzeRequest([str(path)], model="hertz", indenter=INDENTER, segment="approach", curve=n)
        res = analyze(req)
        m = res.json["material"]
        t = truth[n]
        err = m["E_Pa"] - t["E_Pa"]
        assert abs(err) < 4 * m["E_Pa_stat"], (seed, n, m["E_Pa"], m["E_Pa_stat"], t["E_Pa"])
        assert abs(err) < 0.03 * t["E_Pa"], (seed, n, m["E_Pa"], t["E_Pa"])
        assert m["contact_point_m"][0] == pytest.approx(t["contact_travel_m"], abs=20e-9)


def test_the_noise_is_the_level_asked_for_white_or_low_passed(tmp_path):
    for cutoff in (None, 50.0):
        spec = MapSpec(grid=(2, 2), noise_pN=15.0, noise_cutoff_Hz=cutoff)
        path = write_map(tmp_path / f"noise{cutoff}.h5", spec, seed=2)
        truth = json.loads(truth_path(path).read_text())["curves"]
        for n in range(4):
            c = _curve(path, n)
            travel = c["height (piezo)"][0] - c["height (piezo)"]
            free = _free(truth[n], travel) & (c["segment"] == 0)
            r = c["force"][free] - truth[n]["baseline_N"]
            assert np.std(r) == pytest.approx(15e-12, rel=0.25 if cutoff else 0.1)
            r1 = np.corrcoef(r[:-1], r[1:])[0, 1]
            # a first-order low-pass at 50 Hz of 2 kHz samples: lag-1 correlation exp(-2 pi 50 / 2000)
            assert r1 > 0.75 if cutoff else abs(r1) < 0.15


# -- the hidden region --------------------------------------------------------------------------


def test_the_hidden_region_departs_from_the_plain_law_as_its_effect_says(regional):
    spec, path, truth = regional
    curves = truth["curves"]
    inside = [c["enum"] for c in curves if c["in_region"]]
    assert inside == truth["region"]["curves"] and 0 < len(inside) < 64
    assert truth["region"]["effect"] == spec.region and truth["force_law_in_region"] is not None
    outside = [c["enum"] for c in curves if not c["in_region"]]
    for n in (inside[len(inside) // 2], outside[0], outside[-1]):
        t = curves[n]
        c = _curve(path, n)
        app = c["segment"] == 0
        travel = c["height (piezo)"][0] - c["height (piezo)"]
        free = _free(t, travel)
        F = c["force"] - t["baseline_N"]
        noise = spec.noise_pN * 1e-12
        {"thin_layer": _thin_layer, "drift": _drift, "tilt": _tilt, "adhesion": _adhesion}[spec.region](
            spec, t, c, app, travel, free, F, noise)


def _thin_layer(spec, t, c, app, travel, free, F, noise):
    # stiffer at depth, by Dimitriadis' factor; the tip's indentation from the piezo less the
    # cantilever's deflection
    d = travel - t["contact_travel_m"] - F / spec.spring_constant_N_per_m
    deep = app & (d > 0.8 * t["max_indentation_m"])
    ratio = F[deep] / _hertz(spec, t["E_Pa"], d[deep])
    if t["in_region"]:
        chi = np.sqrt(spec.radius_um * 1e-6 * d[deep]) / (spec.layer_thickness_um * 1e-6)
        bracket = 1 + sum(cn * chi ** (i + 1) for i, cn in enumerate(DIMITRIADIS[spec.layer_bonded]))
        assert np.median(ratio) > 1.3
        assert np.median(ratio / bracket) == pytest.approx(1.0, abs=0.02)
    else:
        assert np.median(ratio) == pytest.approx(1.0, abs=0.02)


def _slope(x, y):
    return np.polyfit(x, y, 1)[0]


def _drift(spec, t, c, app, travel, free, F, noise):
    rate = spec.drift_pN_per_s * 1e-12 if t["in_region"] else 0.0
    for part in (app & free, ~app & free):  # before contact and after the tip has left
        assert _slope(c["time"][part], F[part]) == pytest.approx(rate, abs=0.1 * spec.drift_pN_per_s * 1e-12)


def _tilt(spec, t, c, app, travel, free, F, noise):
    per_m = spec.tilt_pN_per_um * 1e-6 if t["in_region"] else 0.0
    for part in (app & free, ~app & free):
        assert _slope(travel[part], F[part]) == pytest.approx(per_m, abs=0.1 * spec.tilt_pN_per_um * 1e-6)
    # in contact too: at the turn, the contact force plus the travel's share
    turn = np.nonzero(app)[0][-1]
    assert F[turn] == pytest.approx(t["max_force_N"] + per_m * travel[turn], abs=5 * noise)


def _adhesion(spec, t, c, app, travel, free, F, noise):
    ret = ~app
    length = spec.adhesion_length_nm * 1e-9
    past = t["contact_travel_m"] - travel  # the piezo's travel above the contact point
    stuck = ret & (past > 0.1 * length) & (past < 0.9 * length)
    gone = ret & (past > length + 10e-9) & (past < length + 300e-9)
    pull = -spec.adhesion_pN * 1e-12 * past / length if t["in_region"] else np.zeros_like(F)
    # stuck, the force falls with the travel down to the adhesion force; then the tip lets go
    for part in (stuck, gone):
        r = F[part] - (pull[part] if part is stuck else 0.0)
        assert abs(np.mean(r)) < 4 * noise / math.sqrt(part.sum()) and np.std(r) < 1.4 * noise
    if t["in_region"]:
        assert np.min(F[ret]) < -spec.adhesion_pN * 1e-12 + 4 * noise
    # the approach has no adhesion either way
    assert np.min(F[app]) > -6 * noise


# -- settings and the command line --------------------------------------------------------------


@pytest.mark.parametrize(("change", "says"), [
    ({"region": "bubbles"}, "region must be one of"),
    ({"grid": (0, 4)}, "grid"),
    ({"E_range_Pa": (5e3, 1e3)}, "E_range_Pa"),
    ({"region": "thin_layer", "poisson": 0.3}, "incompressible"),
    ({"noise_cutoff_Hz": 5000.0}, "noise_cutoff_Hz"),
])
def test_bad_settings_are_refused_in_one_line(tmp_path, change, says):
    with pytest.raises(RigError, match=says):
        write_map(tmp_path / "m.h5", MapSpec(**change))
    assert not list(tmp_path.iterdir())


def _parser():
    parser = argparse.ArgumentParser(prog="rig")
    add_map_parser(parser.add_subparsers(dest="command"))
    return parser


def test_the_command_line_writes_a_map_and_its_truth(tmp_path, capsys):
    out = tmp_path / "cli.h5"
    args = _parser().parse_args(["sim-map", str(out), "--grid", "3x2", "--region", "adhesion", "--seed", "4",
                                 "--noise-pN", "5"])
    assert args.func(args) == 0
    said = capsys.readouterr().out
    assert "6 curves" in said and "region adhesion" in said and str(truth_path(out)) in said
    truth = json.loads(truth_path(out).read_text())
    assert truth["seed"] == 4 and truth["spec"]["grid"] == [3, 2] and truth["spec"]["noise_pN"] == 5.0
    assert [i.enum for i in list_curves(out)] == list(range(6))


@pytest.mark.parametrize("argv", [["--grid", "8y8"], ["--region", "bubbles"]])
def test_the_command_line_refuses_bad_arguments(tmp_path, argv, capsys):
    with pytest.raises(SystemExit):
        _parser().parse_args(["sim-map", str(tmp_path / "m.h5"), *argv])
    assert "sim-map" in capsys.readouterr().err


def test_the_command_line_parser_costs_no_numpy_import():
    # rig's parser is built on every command, and rig.cli imports numpy only where used
    code = "import sys, rig.sim.afm_map; print('numpy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "False", out.stderr


def test_a_long_write_says_how_far_it_is_on_stderr(tmp_path, capsys, monkeypatch):
    """A map that takes longer than a moment (256x256 takes minutes) says the curves written, the
    rate and the time left, each tenth of the way, on stderr: the summary on stdout stays as it
    is. A map written within the moment says nothing (a page shows the command's output)."""
    import rig.sim.afm_map as afm_map

    def run(name: str) -> tuple[str, str]:
        args = _parser().parse_args(["sim-map", str(tmp_path / name), "--grid", "5x4"])
        assert args.func(args) == 0
        return capsys.readouterr()

    monkeypatch.setattr(afm_map, "PROGRESS_AFTER_S", 0.0)
    out, err = run("long.h5")
    lines = err.splitlines()
    assert "(20 curves" in out and "curves written" not in out
    assert len(lines) == 10, lines  # each tenth, the last with no time left
    first = lines[0]
    assert first.startswith("  2/20 curves written, ") and ", about " in first and first.endswith(" left")
    assert lines[-1].startswith("  20/20 curves written, ") and "left" not in lines[-1]
    monkeypatch.setattr(afm_map, "PROGRESS_AFTER_S", 600.0)
    assert run("quick.h5")[1] == ""
