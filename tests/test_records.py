"""Records from the files instruments write, recognised by content: Mach-1 .txt, Instron
Bluehill CSV, JPK text exports, CSV with units in the column names; bad files get one line.

The Mach-1 and Instron files are written here by following reference/formats.md: a ramp
and hold on a standard linear solid, in the instrument's own units, sign and zero."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import load_trial
from rig.cli import main
from rig.errors import SpecError
from rig.models import build_model
from rig.models.core import first_order_lag
from rig.records import read_record
from tests.conftest import ROOT

GF = 9.80665e-3


def sls_record(dt_s: float, depth_m: float, ramp_s: float, hold_s: float, k_N_per_m: float,
               tau_s: float, eta_N_s_per_m: float, seed: int, rest_s: float = 0.0, noise_N: float = 0.0):
    """Ramp and hold (and a rest before) on a standard linear solid, f + tau f' = k x + eta x'
    (instantaneous stiffness eta / tau, relaxed stiffness k)."""
    t = np.arange(0.0, rest_s + ramp_s + hold_s, dt_s)
    x = np.clip((t - rest_s) / ramp_s, 0.0, 1.0) * depth_m
    v = np.gradient(x, dt_s)
    f = first_order_lag(k_N_per_m * x + eta_N_s_per_m * v, dt_s, tau_s)
    rng = np.random.default_rng(seed)
    return t, x, f + rng.normal(0.0, noise_N, len(t))


def write_mach1(path, blocks: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]], force_unit: str) -> None:
    lines = ["<Mach-1 File>", "<INFO>", "Date:\t11/22/2026", "Mach-1 Motion Software Version:\t4.4.0.19",
             "Load Cell Name:\tFT00000-17N", "<END INFO>"]
    for section, t, z, fz in blocks:
        lines += [f"<{section}>", "Amplitude, mm:\t0.0400", "Velocity, mm/s:\t0.0010", "Number of Ramp:\t1",
                  "Stop based on:\tTime", "<DATA>", f"Time, s\tPosition (z), mm\tFz, {force_unit}"]
        half = len(t) // 2
        for i in range(len(t)):
            if i == half:
                lines.append("<divider>")  # a multi-ramp test splits its data; time runs on
            lines.append(f"{t[i]:.6f}\t{z[i]:.6f}\t{fz[i]:.6f}")
        lines.append("<END DATA>")
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("force_unit", ["N", "gf"])
def test_mach1_file_compression_preload_and_blocks(tmp_path, force_unit):
    # cartilage: 40 um at 1 um/s, then 10 minutes of relaxation, at 10 Hz; z falls as it goes in,
    # compression reads as negative Fz, and a 0.25 N preload is on before the ramp
    t, x, f = sls_record(0.1, 40e-6, 40.0, 600.0, 2.0e4, 60.0, 3.6e6, seed=1, rest_s=5.0, noise_N=2e-4)
    preload = 0.25
    z_mm = 0.1574 - x * 1000.0
    fz = -(f + preload) / (GF if force_unit == "gf" else 1.0)
    tc = np.arange(0.0, 3.0, 0.1)
    find_contact = ("Find Contact", tc, np.full(len(tc), 0.1574), -np.full(len(tc), preload) /
                    (GF if force_unit == "gf" else 1.0))
    path = tmp_path / "cartilage.txt"  # named like any text file: recognised by content
    write_mach1(path, [find_contact, ("Stress Relaxation", t + 3.0, z_mm, fz)], force_unit)
    tr = load_trial(path)
    assert tr.source == "mach1"
    assert any("starts in contact" in n and "250 mN" in n for n in tr.notes), tr.notes
    assert any("block 2 of 2" in n for n in tr.notes)
    assert tr.force_unit[1] == "N" and tr.length_unit[1] == "µm"  # about 2.4 N at 40 um
    assert np.isclose(tr.scales.length_m, 40e-6, rtol=1e-3)
    assert np.isclose(np.max(tr.force_N), np.max(f), rtol=0.01)
    assert {"ramp", "hold_early", "hold_late"} <= set(tr.phase)
    res = fit(build_model("kelvin"), [tr])
    assert abs(res.values["tau1_s"] / 60.0 - 1) < 0.05, res.values
    assert abs(res.values["k_N_per_m"] / 2.0e4 - 1) < 0.05, res.values
    assert not any("bound" in w for w in res.warnings)
    with pytest.raises(SpecError, match="data block"):
        load_trial(path, block=3)
    assert read_record(path, block=1).n == len(tc)
    with pytest.raises(SpecError, match="no contact: the position never moves"):
        load_trial(path, block=1)  # the find-contact step: nothing to analyse, said so


def test_mach1_bad_files_name_the_line(tmp_path):
    p = tmp_path / "m.txt"
    p.write_text("<Mach-1 File>\n<INFO>\n<END INFO>\n<Stress Relaxation>\n<DATA>\nTime, s\tPosition (z), mm\t"
                 "Fz, N\n0.0\t0.1\t-0.2\n0.1\tabc\t-0.2\n<END DATA>\n")
    with pytest.raises(SpecError, match=r"m.txt:8: not a row of 3 numbers"):
        load_trial(p)
    p.write_text("<Mach-1 File>\n<DATA>\nTime, s\tPosition (z), mm\tFz, kip\n0\t0\t0\n<END DATA>\n")
    with pytest.raises(SpecError, match="column 'Fz, kip': unknown force unit 'kip'"):
        load_trial(p)
    p.write_text("<Mach-1 File>\n<INFO>\n<END INFO>\n")
    with pytest.raises(SpecError, match=r"without a <DATA> \.\.\. <END DATA> block"):
        load_trial(p)


def write_instron(path, t, ext_mm, load_N) -> None:
    lines = ['Specimen properties : Specimen label,"tendon-3"', 'Specimen properties : Width,"4.00000",mm',
             'Test : Rate 1,"5.00000",mm/min', 'Test : Hold,"300.000",s', "",
             "Extension,Load,Tensile stress,Time", "(mm),(N),(MPa),(s)"]
    for ti, e, fl in zip(t, ext_mm, load_N, strict=True):
        lines.append(f'"{e:.5f}","{fl:.5f}","{fl / 4.0:.5f}","{ti:.5f}"')
    path.write_text("\n".join(lines) + "\n")


def test_instron_tension_relaxation(tmp_path):
    # a tendon stretched 2 mm at 5 mm/min, held 5 minutes, at 10 Hz; tension is positive
    t, x, f = sls_record(0.1, 2e-3, 24.0, 300.0, 5.0e3, 20.0, 3.0e5, seed=2, rest_s=2.0, noise_N=0.01)
    path = tmp_path / "Specimen_RawData_1.csv"
    write_instron(path, t, x * 1000.0, f + 0.05)
    tr = load_trial(path)
    assert tr.source == "instron"
    assert np.isclose(tr.scales.length_m, 2e-3, rtol=0.02)
    assert {"ramp", "hold_early", "hold_late"} <= set(tr.phase)
    res = fit(build_model("kelvin"), [tr])
    assert abs(res.values["tau1_s"] / 20.0 - 1) < 0.05, res.values
    assert abs(res.values["k_N_per_m"] / 5.0e3 - 1) < 0.02
    assert abs(res.values["eta_N_s_per_m"] / 3.0e5 - 1) < 0.02
    bad = tmp_path / "Specimen_RawData_2.csv"
    bad.write_text('Test : Rate 1,"5",mm/min\n\nExtension,Weight,Time\n(mm),(N),(s)\n"0","0","0"\n')
    with pytest.raises(SpecError, match="no force column"):
        load_trial(bad)


def write_csv(path, header: str, cols) -> None:
    rows = "\n".join(",".join(repr(float(c)) for c in r) for r in zip(*cols, strict=True))
    path.write_text(header + "\n" + rows + "\n")


@pytest.mark.parametrize(("header", "kt", "kx", "kf"), [
    ("t_ms,indentation_um,force_nN", 1e3, 1e6, 1e9),
    ("time [s],Indentation (nm),Force (mN)", 1.0, 1e9, 1e3),
    ("t_s,displacement_um,load_gf", 1.0, 1e6, 1 / GF),
    ("Time (min),position_mm,force_uN", 1 / 60, 1e3, 1e6),
])
def test_csv_units_in_the_header(tmp_path, header, kt, kx, kf):
    t, x, f = sls_record(0.01, 20e-6, 1.0, 20.0, 0.02, 3.0, 0.18, seed=3, rest_s=0.5, noise_N=1e-10)
    si = tmp_path / "si.csv"
    length = "indentation_m" if "ndentation" in header else "position_m"
    write_csv(si, f"t_s,{length},force_N", (t, x, f))
    other = tmp_path / "other.csv"
    write_csv(other, header, (t * kt, x * kx, f * kf))
    a, b = load_trial(si), load_trial(other)
    assert np.allclose(a.motion.x_m, b.motion.x_m, rtol=1e-9, atol=1e-15)
    assert np.allclose(a.force_N, b.force_N, rtol=1e-9, atol=1e-18)
    assert a.force_unit[1] == "µN" and a.length_unit[1] == "µm"  # about 1.2 uN at 20 um


def test_csv_unknown_or_missing_unit_names_the_column(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text("t_s,position_mm,force_kip\n0,0,0\n1,1,1\n")
    with pytest.raises(SpecError, match=r"x.csv:1: column 'force_kip': unknown force unit 'kip'"):
        load_trial(p)
    p.write_text("t_s,position,force_N\n0,0,0\n1,1,1\n")
    with pytest.raises(SpecError, match="column 'position' does not say its unit"):
        load_trial(p)
    rows = "".join(f"{i * 0.1},{min(i, 10) * 0.01},{min(i, 10) * 0.2}\n" for i in range(40))
    p.write_text("t_s,strain,force_N\n" + rows)  # strain needs no unit: it is a ratio
    assert np.isclose(load_trial(p).scales.length_m, 0.1)


def jpk_text_export(path, t, height_m, force_N) -> None:
    """A JPK Data Processing text export: per segment, seriesTime restarting at zero."""
    lines = ["# TEXT EXPORT", "# data-description.instrument: JPK00000-CellHesion"]
    n = len(t)
    bounds = [0, n // 4, n // 2, n]
    for name, a, b in zip(["extend", "pause", "retract"], bounds[:-1], bounds[1:], strict=True):
        lines += [f"# segment: {name}", "# columns: height vDeflection seriesTime", "# units: m N s"]
        lines += [f"{height_m[i]:.10E} {force_N[i]:.6E} {t[i] - t[a]:.6f}" for i in range(a, b)]
        lines.append("")
    path.write_text("\n".join(lines) + "\n")


def test_jpk_text_export(tmp_path):
    t, x, f = sls_record(0.002, 10e-6, 1.0, 10.0, 0.02, 2.0, 0.12, seed=4, rest_s=0.5, noise_N=2e-11)
    h = 50e-6 - x  # heights fall as the tip goes in
    p = tmp_path / "cell.txt"
    jpk_text_export(p, t, h, f + 5e-9)  # a baseline offset before contact
    tr = load_trial(p)
    assert tr.source == "jpk-text"
    assert np.all(np.diff(tr.motion.t_s) > 0)  # seriesTime made continuous
    assert np.isclose(tr.scales.length_m, 10e-6, rtol=0.01)
    assert abs(np.median(tr.baseline_N if tr.baseline_N is not None else [0.0])) < 1e-10
    res = fit(build_model("kelvin"), [tr])
    assert abs(res.values["tau1_s"] / 2.0 - 1) < 0.05, res.values


@pytest.mark.parametrize(("content", "fragment"), [
    (b"\x00\x01\x02binary junk" * 50, "a binary file this tool cannot read"),
    (b"hello, this is\nnot a record\n", "not a file this tool can read (looked for an MCAP log"),
    (b"t_s,position_mm\n0,1\n", "missing column(s) force_N"),
    (b"just words\nno commas\n", "not a file this tool can read (looked for an MCAP log"),
    (b"PK\x03\x04notazip" * 10, "not a file this tool can read"),
])
def test_unreadable_files_get_one_line(tmp_path, content, fragment):
    p = tmp_path / "thing.dat"
    p.write_bytes(content)
    proc = subprocess.run([sys.executable, "-m", "rig", "analyze", str(p)], capture_output=True, text=True,
                          cwd=ROOT, timeout=60)
    assert proc.returncode == 2
    assert fragment in proc.stderr, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_broken_jpk_force_file_is_one_line(tmp_path):
    p = tmp_path / "curve.jpk-force"
    p.write_bytes(b"PK\x03\x04" + b"\x00" * 100)
    proc = subprocess.run([sys.executable, "-m", "rig", "analyze", str(p)], capture_output=True, text=True,
                          cwd=ROOT, timeout=60)
    assert proc.returncode == 2 and "not a readable JPK force file" in proc.stderr
    assert proc.stderr.count("\n") == 1


def test_import_writes_the_canonical_csv_that_analyses_alike(tmp_path, capsys):
    t, x, f = sls_record(0.1, 40e-6, 40.0, 300.0, 2.0e4, 30.0, 1.8e6, seed=5, rest_s=5.0, noise_N=2e-4)
    src = tmp_path / "c.txt"
    write_mach1(src, [("Stress Relaxation", t, 0.2 + x * 1000.0, -(f + 0.1))], "N")
    out = tmp_path / "c.csv"
    assert main(["import", str(src), "--csv", str(out)]) == 0
    text = capsys.readouterr().out
    assert "mach1" in text and "starts in contact" in text and f"wrote {out}" in text
    assert out.read_text().splitlines()[0] == "t_s,indentation_mm,force_N"
    a = fit(build_model("kelvin"), [load_trial(src)])
    b = fit(build_model("kelvin"), [load_trial(out)])
    for k, v in a.values.items():
        assert abs(b.values[k] / v - 1) < 1e-6, (k, v, b.values[k])
    assert main(["import", str(src), "--csv", str(tmp_path / "nodir" / "x.csv")]) == 2
    assert "cannot write" in capsys.readouterr().err


def test_a_staircase_and_a_creeping_hold_are_found_in_the_motion(tmp_path):
    """Three steps of a staircase give three ramps and three holds; a hold whose position
    creeps slowly (force control) is still a hold."""
    dt = 0.01
    t = np.arange(0.0, 95.0, dt)
    x = np.zeros_like(t)
    for start in (2.0, 32.0, 62.0):  # 1 mm steps at 1 mm/s, then holds of 29 s
        x += np.clip(t - start, 0.0, 1.0) * 1e-3
    x += np.where(t > 63.0, (t - 63.0) * 2e-6, 0.0)  # the last hold creeps at 0.2 % of the ramp speed
    f = first_order_lag(80.0 * x + 4000.0 * np.gradient(x, dt), dt, 5.0)
    p = tmp_path / "stairs.csv"
    write_csv(p, "t_s,position_mm,force_N", (t, x * 1e3, f))
    tr = load_trial(p)

    def runs(name: str) -> int:
        m = (tr.phase == name).astype(int)
        return int(np.sum(np.diff(np.concatenate([[0], m])) == 1))

    assert runs("ramp") == 3 and runs("hold_early") == 3 and runs("hold_late") == 3
    last_hold = (tr.motion.t_s > 70.0) & (tr.motion.t_s < 94.0)
    assert set(tr.phase[last_hold]) == {"hold_late"}
