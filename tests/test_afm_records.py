"""AFM force curves from six instruments (../shared/realdata/afm-fd, the afmformats test data),
read through afmformats: curves numbered as the instrument numbers them, positions on maps,
the cantilever's calibration asked for when the file lacks it, the Chiaro's own probe and fit,
damaged files in one line, and the relaxation and creep records read exactly as before."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rig.analysis.trials.data import prepare
from rig.cli import main
from rig.errors import SpecError
from rig.records import CurveInfo, ReadOptions, iter_records, list_curves, read_record
from rig.records.afm import FORMATS, chiaro_header, describe_numbers, detect_afm
from tests.conftest import ROOT

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
AFM = REALDATA / "afm-fd"

pytestmark = [
    pytest.mark.skipif(not AFM.is_dir(), reason=f"the real AFM curves are not at {AFM}"),
    pytest.mark.filterwarnings("ignore::DeprecationWarning"),
]
afmformats = pytest.importorskip("afmformats", reason="reading AFM files needs the afm extra (afmformats)")

NTMDT_OPTIONS = ReadOptions(spring_constant_N_per_m=0.055, sensitivity_m_per_V=61.0)  # README: not in the file
WORKSHOP_MAP_OPTIONS = ReadOptions(spring_constant_N_per_m=20.0, sensitivity_m_per_V=1e-8)


def _file(prefix: str) -> Path:
    return next(AFM.glob(prefix + "*")) if AFM.is_dir() else AFM / prefix


# per file: instrument, Record.source, the curves' numbers (afmformats' enum), the options the
# user gives, the force rise on the approach (nN, as the file writes it), the spring constant
# (N/m), and the grid index (x, y) of each curve on a map
EXPECT = {
    "fmt-jpk-fd_spot3-0192": ("JPK", "jpk", [0], None, 3.97, 0.0435, None),
    "fmt-jpk-fd_flipsign": ("JPK", "jpk", [0], None, 3.95, 0.0187, None),
    "fmt-jpk-fd_map2x2_extracted": ("JPK", "jpk", [0, 1, 2, 3], None, 2.0, 0.0155,
                                    [(0, 0), (9, 0), (9, 9), (0, 9)]),
    "fmt-jpk-fd_map-data-reference-points": ("JPK", "jpk", [109, 129, 416], None, 4.0, 0.01095,
                                             [(9, 4), (20, 5), (16, 16)]),
    "fmt-jpk-fd_2020.02.07": ("JPK", "jpk", [0, 1, 2, 3], None, 0.105, 0.0301,
                              [(0, 0), (1, 0), (2, 0), (3, 0)]),
    "fmt-jpk-fd_qi-data-2021": ("JPK", "jpk", [0], None, 990.0, 35.03, None),
    "fmt-igor-fd_U3_3": ("Asylum", "asylum", [1], None, 181.0, 0.3145, None),
    "fmt-ntmdt-txt-fd": ("NT-MDT", "ntmdt", [0], NTMDT_OPTIONS, 8.6, 0.055, None),
    "fmt-afm-workshop-fd_single": ("AFM Workshop", "afm-workshop", [1], None, 0.0185, None, None),
    "fmt-afm-workshop-fd_mapping_16": ("AFM Workshop", "afm-workshop", list(range(1, 17)), WORKSHOP_MAP_OPTIONS,
                                       105.0, 20.0, [(i % 4, i // 4) for i in range(16)]),
    "fmt-chiaro-txt": ("Optics11 Chiaro", "chiaro", [0], None, 49.3, 0.019, None),
}
GRID_SHAPE = {"fmt-jpk-fd_map2x2_extracted": (10, 10), "fmt-jpk-fd_map-data-reference-points": (25, 25),
              "fmt-jpk-fd_2020.02.07": (128, 128), "fmt-afm-workshop-fd_mapping_16": (4, 4)}
FILES = [_file(k) for k in EXPECT]


def _rise_N(rec) -> float:
    """The force's rise on the approach above its level at the start."""
    f = rec.force_N
    base = float(np.median(f[: max(len(f) // 20, 5)]))
    return float(np.max(f[rec.segment == "approach"]) - base)


def test_every_file_in_the_folder_is_in_the_table():
    if not AFM.is_dir():
        pytest.skip(f"no {AFM}")
    assert sorted(p.name for p in AFM.iterdir()) == sorted(p.name for p in FILES)


@pytest.mark.parametrize("key", list(EXPECT), ids=list(EXPECT))
def test_every_afm_file_reads_with_its_curves_positions_and_meta(key):
    instrument, source, enums, options, rise_nN, k, grid = EXPECT[key]
    path = _file(key)
    curves = list_curves(path, options)
    assert [c.enum for c in curves] == enums
    assert all(isinstance(c, CurveInfo) for c in curves)
    rec = read_record(path, options)
    assert rec.source == source and rec.meta["instrument"] == instrument
    assert rec.meta["curve"] == enums[0] and rec.meta["curves_in_file"] == len(enums)
    assert rec.meta["modality"] == "force-distance"
    if k is None:
        assert rec.meta["spring_constant_N_per_m"] is None
        assert any("no spring constant" in n for n in rec.notes), rec.notes
    else:
        assert rec.meta["spring_constant_N_per_m"] == pytest.approx(k, rel=2e-3)
        assert any("indentation = travel - deflection" in n for n in rec.notes), rec.notes
    if len(enums) > 1:
        assert rec.notes[0] == (f"the file holds {len(enums)} curves (numbered {describe_numbers(enums)}): "
                                f"this is curve {enums[0]}, the first; pick another with --curve N")
    else:
        assert not any("pick another" in n for n in rec.notes)
    # every curve, from one load of the file
    records = list(iter_records(path, options))
    assert [r.meta["curve"] for r in records] == enums
    for r, c in zip(records, curves, strict=True):
        assert r.n > 100 and np.all(np.diff(r.t_s) > 0)
        assert np.all(np.isfinite(r.position_m)) and np.all(np.isfinite(r.force_N))
        assert abs(r.position_m[0]) < 0.01 * np.max(r.position_m)  # from where the probe started
        assert r.length_unit == "µm" and r.force_unit == "nN"
        # approach first, then the retract; the travel goes in on the approach
        assert r.segment is not None and len(r.segment) == r.n
        assert set(r.segment) == {"approach", "retract"}
        first_retract = int(np.argmax(r.segment == "retract"))
        assert np.all(r.segment[:first_retract] == "approach")
        assert np.all(r.segment[first_retract:] == "retract")
        assert np.max(r.position_m[:first_retract]) > 0.5 * np.max(r.position_m)
        assert _rise_N(r) == pytest.approx(rise_nN * 1e-9, rel=0.25), (r.meta["curve"], _rise_N(r))
        assert (r.meta["x_m"], r.meta["y_m"]) == (c.x_m, c.y_m)
        if grid is None:
            assert r.meta["grid_index"] is None and (c.grid_x, c.grid_y) == (None, None)
        else:
            assert r.meta["grid_shape"] == GRID_SHAPE[key] == c.grid_shape
            assert r.meta["grid_index"] == (c.grid_x, c.grid_y)
    if grid is not None:
        assert [(c.grid_x, c.grid_y) for c in curves] == grid
        # a map's positions: as many distinct places as curves, spread on the sample
        xy = {(round(c.x_m, 12), round(c.y_m, 12)) for c in curves}
        assert len(xy) == len(curves)
    # a picked curve is that curve
    last = read_record(path, dataclasses.replace(options or ReadOptions(), curve=enums[-1]))
    assert last.meta["curve"] == enums[-1]
    assert np.array_equal(last.force_N, records[-1].force_N)


@pytest.mark.parametrize("key", list(EXPECT), ids=list(EXPECT))
def test_every_afm_record_goes_to_the_analysis(key):
    rec = read_record(_file(key), EXPECT[key][3])
    trial = prepare(rec)
    assert trial.n > 100 and trial.source == EXPECT[key][1]


def test_the_flipsign_file_analyses_end_to_end(capsys):
    path = _file("fmt-jpk-fd_flipsign")
    rec = read_record(path)
    assert _rise_N(rec) > 0  # afmformats gives the force rising on the approach; the file's sign kept
    assert main(["analyze", str(path)]) == 0
    out = capsys.readouterr().out
    assert "RMSE" in out and "nN" in out


def test_positions_and_instrument_facts():
    ref = read_record(_file("fmt-jpk-fd_map-data-reference-points"), ReadOptions(curve=416))
    assert ref.meta["grid_index"] == (16, 16) and ref.meta["curve_id"].endswith(":416")
    assert ref.meta["x_m"] == pytest.approx(-1.07977e-3, rel=1e-4)
    ws = list_curves(_file("fmt-afm-workshop-fd_mapping_16"), WORKSHOP_MAP_OPTIONS)
    assert ws[0].x_m == pytest.approx(1e-6) and ws[0].y_m == pytest.approx(2e-6)
    assert ws[-1].x_m == pytest.approx(20e-6) and ws[-1].y_m == pytest.approx(21e-6)
    ibw = read_record(_file("fmt-igor-fd_U3_3"))
    assert ibw.meta["time_from"] == "sampling rate" and ibw.t_s[1] == pytest.approx(1 / 2000.0)
    assert any("split at the deepest point" in n for n in ibw.notes)  # the .ibw marks no retract
    assert ibw.meta["instrument_model"] == "MFP3D" and ibw.meta["sensitivity"] == pytest.approx(2.0364e-7)
    nt = read_record(_file("fmt-ntmdt-txt-fd"), NTMDT_OPTIONS)
    assert nt.meta["time_from"] == "sample number" and nt.meta["sensitivity"] == 61.0
    assert read_record(_file("fmt-jpk-fd_spot3")).meta["time_from"] == "file"


def test_chiaro_header_probe_and_the_instruments_own_fit():
    path = _file("fmt-chiaro-txt")
    head = chiaro_header(path)
    assert head["tip_radius_m"] == pytest.approx(27.5e-6)
    assert head["spring_constant_N_per_m"] == pytest.approx(0.019)
    assert head["indenter"] == "sphere:R=27.5um"
    res = head["instrument_result"]
    assert res["model"] == "Hertz" and res["poisson"] == 0.5
    assert res["E_Pa"] == pytest.approx(117.0, rel=1e-3) and res["E_eff_Pa"] == pytest.approx(156.0, rel=1e-3)
    assert res["max_force_N"] == pytest.approx(0.049e-6)
    rec = read_record(path)
    assert rec.meta["indenter"] == "sphere:R=27.5um" and rec.meta["instrument_result"] == res
    assert rec.meta["position_column"] == "height (piezo)"  # its "Indentation" column is its own estimate
    assert any("E = 117 Pa at Poisson 0.5" in n for n in rec.notes), rec.notes
    # the other files say nothing of the tip
    assert read_record(_file("fmt-jpk-fd_spot3")).meta["indenter"] is None


@pytest.mark.parametrize(("key", "options", "message"), [
    ("fmt-ntmdt-txt-fd", None, "the file does not hold the cantilever's spring constant or the deflection "
                               "sensitivity: give them with --spring-constant (N/m) and --sensitivity (nm/nA"),
    ("fmt-ntmdt-txt-fd", ReadOptions(spring_constant_N_per_m=0.055),
     "the file does not hold the deflection sensitivity: give it with --sensitivity (nm/nA"),
    ("fmt-afm-workshop-fd_mapping_16", ReadOptions(sensitivity_m_per_V=1e-8),
     "the file does not hold the cantilever's spring constant: give it with --spring-constant (N/m)"),
    ("fmt-afm-workshop-fd_mapping_16", ReadOptions(spring_constant_N_per_m=20.0),
     "the file does not hold the deflection sensitivity: give it with --sensitivity (m/V)"),
])
def test_a_missing_calibration_is_asked_for(key, options, message):
    path = _file(key)
    with pytest.raises(SpecError) as err:
        read_record(path, options)
    assert str(err.value) == f"{path}: {message}" or str(err.value).startswith(f"{path}: {message}")
    with pytest.raises(SpecError, match="does not hold"):
        list_curves(path, options)


def test_a_missing_calibration_is_one_line_on_the_command_line():
    path = _file("fmt-ntmdt-txt-fd")
    proc = subprocess.run([sys.executable, "-m", "rig", "analyze", str(path)], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert proc.returncode == 2 and "--spring-constant (N/m)" in proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr


def test_a_calibration_the_file_holds_is_overridden_or_refused():
    spot = _file("fmt-jpk-fd_spot3")
    own = read_record(spot)
    k = 2 * own.meta["spring_constant_N_per_m"]
    twice = read_record(spot, ReadOptions(spring_constant_N_per_m=k))
    assert twice.meta["spring_constant_N_per_m"] == k
    assert np.allclose(twice.force_N, 2 * own.force_N, rtol=1e-3, atol=1e-15)  # JPK: force = k x deflection
    with pytest.raises(SpecError, match=r"holds its own cantilever calibration.*--spring-constant"):
        read_record(_file("fmt-igor-fd_U3_3"), ReadOptions(spring_constant_N_per_m=0.3))


def test_an_unknown_curve_lists_the_ones_there():
    path = _file("fmt-jpk-fd_map-data-reference-points")
    with pytest.raises(SpecError) as err:
        read_record(path, ReadOptions(curve=5))
    assert str(err.value) == f"{path}: no curve 5 in the file: it holds curves 109, 129, 416"
    with pytest.raises(SpecError, match=r"no curve 0 in the file: it holds curves 1-16$"):
        read_record(_file("fmt-afm-workshop-fd_mapping_16"), ReadOptions(curve=0, spring_constant_N_per_m=20.0,
                                                                        sensitivity_m_per_V=1e-8))
    with pytest.raises(SpecError, match=r"no curve 3 in the file: it holds curve 0$"):
        read_record(_file("fmt-jpk-fd_spot3"), ReadOptions(curve=3))
    assert describe_numbers(list(range(16384))) == "0-16383"
    assert describe_numbers([0, 1, 5, 7, 8, 9]) == "0, 1, 5, 7-9"
    many = describe_numbers(list(range(0, 200, 2)))
    assert many.startswith("0, 2, 4") and many.endswith("... (100 curves, 0 to 198)")


def test_iter_records_loads_the_file_once(monkeypatch):
    path = _file("fmt-jpk-fd_map2x2_extracted")
    calls = []
    # a JPK file goes straight to afmformats' JPK loader (its format is already known)
    (recipe,) = afmformats.formats.formats_by_suffix[path.suffix]
    load = recipe.recipe["loader"]

    def counting(*args, **kwargs):
        calls.append(args)
        return load(*args, **kwargs)

    monkeypatch.setitem(recipe.recipe, "loader", counting)
    got = [r.meta["curve"] for r in iter_records(path)]
    assert got == [0, 1, 2, 3] and len(calls) == 1


def test_one_curve_is_opened_once_by_the_command_and_again_once_the_file_changed(monkeypatch, tmp_path, capsys):
    # `rig analyze FILE` lists the file (is it a batch?) and then reads its curve: one opening
    path = tmp_path / "one.jpk-force"
    path.write_bytes(_file("fmt-jpk-fd_spot3").read_bytes())
    (recipe,) = afmformats.formats.formats_by_suffix[path.suffix]
    load = recipe.recipe["loader"]
    calls = []

    def counting(*args, **kwargs):
        calls.append(args)
        return load(*args, **kwargs)

    monkeypatch.setitem(recipe.recipe, "loader", counting)
    alone = read_record(path)
    calls.clear()
    assert main(["analyze", str(path), "--model", "hertz", "--indenter", "paraboloid:R=10um", "--json"]) == 0
    assert len(calls) == 1 and '"E_Pa"' in capsys.readouterr().out
    # what the listing kept is the same record, and a file changed since is read afresh
    assert len(list_curves(path)) == 1
    np.testing.assert_array_equal(read_record(path).force_N, alone.force_N)
    list_curves(path)
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 10**9))
    calls.clear()
    read_record(path)
    assert len(calls) == 1
    # another curve exported under the same name is that curve (afmformats keeps archives open)
    path.write_bytes(_file("fmt-jpk-fd_flipsign").read_bytes())
    other = read_record(path)
    assert other.n == read_record(_file("fmt-jpk-fd_flipsign")).n != alone.n


def _damaged(tmp_path: Path) -> list[tuple[Path, str]]:
    out = []

    def cut(prefix: str, name: str, fraction: float, what: str):
        src = _file(prefix).read_bytes()
        p = tmp_path / name
        p.write_bytes(src[: int(len(src) * fraction)])
        out.append((p, what))

    cut("fmt-jpk-fd_spot3", "half.jpk-force", 0.5, "JPK force file")
    cut("fmt-jpk-fd_map2x2", "half.jpk-force-map", 0.5, "JPK force file")
    cut("fmt-jpk-fd_2020.02.07", "half.jpk-qi-data", 0.5, "JPK force file")
    cut("fmt-igor-fd_U3_3", "half.ibw", 0.4, "Asylum .ibw file")
    cut("fmt-chiaro-txt", "half_chiaro.txt", 0.5, "Optics11 Chiaro text export")
    cut("fmt-afm-workshop-fd_single", "half_workshop.csv", 0.5, "AFM Workshop force curve")
    cut("fmt-afm-workshop-fd_mapping_16", "half_workshop.zip", 0.5, "AFM Workshop force map")
    rng = np.random.default_rng(7)
    for name, what in (("random.ibw", "Asylum .ibw file"), ("random.h5", "afmformats HDF5 file"),
                       ("random.jpk-force", "JPK force file")):
        p = tmp_path / name
        p.write_bytes(rng.integers(1, 256, 4000, dtype=np.uint8).tobytes())
        out.append((p, what))
    # a complete zip whose binary channels are cut short
    src = zipfile.ZipFile(_file("fmt-jpk-fd_spot3"))
    p = tmp_path / "short-channels.jpk-force"
    with zipfile.ZipFile(p, "w") as z:
        for n in src.namelist():
            data = src.read(n)
            z.writestr(n, data[: len(data) // 3] if n.endswith(".dat") else data)
    out.append((p, "JPK force file"))
    return out


def test_damaged_afm_files_give_one_line_naming_the_file(tmp_path):
    for path, what in _damaged(tmp_path):
        with pytest.raises(SpecError) as err:
            list(iter_records(path))
        text = str(err.value)
        assert text.startswith(f"{path}: not a readable {what}"), text
        assert "\n" not in text and len(text) < 400, text


@pytest.mark.parametrize("name", ["half.ibw", "half_workshop.csv", "short-channels.jpk-force"])
def test_damaged_afm_files_on_the_command_line_print_no_traceback(tmp_path, name):
    # afmformats logs a traceback for each file it fails on, igor2 the bytes it could not shape
    path = next(p for p, _ in _damaged(tmp_path) if p.name == name)
    proc = subprocess.run([sys.executable, "-m", "rig", "analyze", str(path)], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert proc.returncode == 2 and "not a readable" in proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr


def test_afmformats_own_files_read_back(tmp_path):
    h5py = pytest.importorskip("h5py")
    src = _file("fmt-jpk-fd_map2x2_extracted")
    data = afmformats.load_data(src)
    h5 = tmp_path / "map.h5"
    with h5py.File(h5, "w") as out:
        for d in data:
            d.export_data(out, fmt="hdf5")
    tab = tmp_path / "curve.tab"
    data[1].export_data(tab, fmt="tab")
    for path, curve, enums in ((h5, 2, [0, 1, 2, 3]), (tab, None, [0])):
        rec = read_record(path, ReadOptions(curve=curve))
        orig = read_record(src, ReadOptions(curve=2 if curve == 2 else 1))
        assert rec.source == "afmformats" and rec.meta["instrument"] == "JPK"
        assert [c.enum for c in list_curves(path)] == enums
        assert np.allclose(rec.position_m, orig.position_m) and np.allclose(rec.force_N, orig.force_N)
        assert np.array_equal(rec.segment, orig.segment) and rec.meta["grid_index"] == orig.meta["grid_index"]


def test_every_suffix_afmformats_reads_is_recognised():
    claimed = {s for f in FORMATS for s in f.suffixes}
    assert set(afmformats.formats.supported_extensions) <= claimed


@pytest.mark.parametrize(("name", "content"), [
    ("cartilage.txt", "<Mach-1 File>\n<INFO>\n<END INFO>\n<DATA>\nTime, s\tPosition (z), mm\tFz, N\n"),
    ("cell.txt", "# TEXT EXPORT\n# segment: extend\n# columns: height vDeflection time\n# units: m N s\n"),
    ("Specimen_RawData_1.csv", 'Test : Rate 1,"5",mm/min\n\nExtension,Load,Time\n(mm),(N),(s)\n"0","0","0"\n'),
    ("trial.csv", "t_s,position_mm,force_N\n0.0,0.0,0.0\n0.1,0.001,0.02\n"),
    ("numbers.csv", "".join(f"{i},{i * 0.5},{i * 0.1}\n" for i in range(20))),
    ("notes.txt", "time\tposition\tforce\n" + "".join(f"{i}\t{i * 0.5}\t{i * 0.1}\n" for i in range(20))),
    ("table.csv", "".join(f"{i},5\t{i},1\t{i},2\n" for i in range(20))),  # NT-MDT rows, but a .csv
    ("archive.zip", None),
])
def test_the_projects_own_files_are_not_taken_for_afm_files(tmp_path, name, content):
    p = tmp_path / name
    if content is None:
        with zipfile.ZipFile(p, "w") as z:
            z.writestr("trial.csv", "t_s,position_mm,force_N\n0,0,0\n")
    else:
        p.write_text(content)
    assert detect_afm(p.read_bytes()[:8192], p) is None


def test_afm_files_are_recognised_by_content_and_suffix():
    for key in EXPECT:
        p = _file(key)
        fmt = detect_afm(p.read_bytes()[:8192], p)
        assert fmt is not None and fmt.instrument == EXPECT[key][0], key


def test_options_that_do_not_apply_say_so(tmp_path):
    csv = tmp_path / "trial.csv"
    rows = "".join(f"{i * 0.1},{i * 0.001},{i * 0.02}\n" for i in range(20))
    csv.write_text("t_s,position_mm,force_N\n" + rows)
    with pytest.raises(SpecError, match="--curve apply to AFM force files; this is not one"):
        read_record(csv, ReadOptions(curve=1))
    with pytest.raises(SpecError, match="--block picks a data block of a Mach-1 file"):
        read_record(_file("fmt-jpk-fd_spot3"), ReadOptions(block=1))
    with pytest.raises(SpecError, match="--block picks a data block"):
        read_record(_file("fmt-jpk-fd_spot3"), 1)  # the old positional block


def test_the_old_positional_block_still_picks_a_mach1_block(tmp_path):
    from tests.test_records import write_mach1

    t = np.arange(0.0, 3.0, 0.1)
    z = np.linspace(0.2, 0.1, len(t))
    path = tmp_path / "m.txt"
    write_mach1(path, [("Find Contact", t, z, -z), ("Stress Relaxation", t + 3.0, z, -2 * z)], "N")
    assert read_record(path, 2).t_s[0] == pytest.approx(3.0)
    assert read_record(path, block=2).n == read_record(path, ReadOptions(block=2)).n == len(t)
    assert read_record(path, 1).t_s[0] == 0.0


# -- the relaxation and creep records (afmformats' segments 0..3) read exactly as before --------

HOLDS = sorted(p for p in REALDATA.glob("**/*.jpk-force") if "afm-fd" not in p.parts) \
    if REALDATA.is_dir() else []


@pytest.mark.parametrize("path", HOLDS, ids=[p.name for p in HOLDS])
def test_relaxation_and_creep_records_read_as_before(path):
    """Position, force and time from afmformats' columns: -(height - height at the start) -
    (force - its start) / k, the deflection through a cubic Savitzky-Golay over 15 samples
    within each of the instrument's segments (approach, hold, retract)."""
    from scipy.signal import savgol_filter

    d = afmformats.load_data(path)[0]
    t = np.asarray(d["time"], dtype=float)
    h = np.asarray(d["height (measured)"], dtype=float)
    f = np.asarray(d["force"], dtype=float)
    seg = np.asarray(d["segment"], dtype=int)
    k = float(d.metadata["spring constant"])
    deflection = f - np.median(f[: max(len(f) // 50, 5)])
    for s in np.unique(seg):
        run = np.flatnonzero(seg == s)
        assert np.all(np.diff(run) == 1)  # each segment one stretch of samples
        deflection[run] = savgol_filter(deflection[run], 15, 3, mode="interp")
    travel = -(h - h[0]) - deflection / k
    rec = read_record(path)
    assert np.all(np.diff(t) > 0)
    assert np.array_equal(rec.t_s, t) and np.array_equal(rec.force_N, f)
    assert np.allclose(rec.position_m, travel, rtol=0, atol=1e-12 * np.ptp(travel))  # to rounding
    assert rec.source == "jpk" and rec.length_unit == "µm" and rec.force_unit == "nN"
    assert rec.notes[-1] == f"indentation = travel - deflection (cantilever {k:.3g} N/m)"
    seg = np.asarray(d["segment"], dtype=int)
    names = {"stress-relaxation": ("intermediate", "approach", "intermediate", "retract"),
             "creep-compliance": ("approach", "intermediate", "retract")}[d.modality]
    assert rec.meta["modality"] == d.modality and len(set(seg)) == len(names)
    for i, name in enumerate(names):
        assert set(rec.segment[seg == i]) == {name}


def test_read_jpk_force_is_still_importable():
    from rig.records.jpk import read_jpk_force

    path = _file("fmt-jpk-fd_spot3")
    a, b = read_jpk_force(path), read_record(path)
    assert np.array_equal(a.position_m, b.position_m) and a.meta == b.meta


def test_a_relaxation_on_an_approach_is_said_to_bend_the_ramp_not_a_hold(capsys):
    # an approach has no hold: a relaxation there shows as a ramp that bends with time
    path = _file("fmt-jpk-fd_spot3")
    assert main(["analyze", str(path), "--model", "hertz", "--indenter", "paraboloid:R=10um", "--explain"]) == 0
    out = capsys.readouterr().out
    said = next(line for line in out.splitlines() if line.startswith("* relaxation "))
    assert "ramp residual bends with time, not depth: the force relaxes while it is loaded" in said
    assert "hold residual" not in out
