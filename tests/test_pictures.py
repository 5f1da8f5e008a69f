"""The pictures a researcher reads: what each figure shows, checked on the Figure objects the
commands save (axis labels and units, legends, what is shaded, where the legend sits)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rig.analysis.workflow import report as report_mod
from rig.cli import main

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
SPOT3 = REALDATA / "afm-fd" / "fmt-jpk-fd_spot3-0192.jpk-force"
HERTZ = ["--model", "hertz", "--indenter", "paraboloid:R=10um"]


def spy(monkeypatch, module, name: str) -> list:
    """Keep every figure `module.name` returns while the test runs."""
    made = []
    original = getattr(module, name)

    def keep(*args, **kw):
        fig = original(*args, **kw)
        made.append(fig)
        return fig

    monkeypatch.setattr(module, name, keep)
    return made


def legend_texts(ax) -> list[str]:
    leg = ax.get_legend()
    return [t.get_text() for t in leg.get_texts()] if leg else []


@pytest.mark.skipif(not SPOT3.is_file(), reason=f"the real curve is not at {SPOT3}")
@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_report_of_an_afm_curve_draws_force_against_indentation_with_the_fit(tmp_path, monkeypatch):
    pytest.importorskip("afmformats", reason="reading JPK files needs the afm extra (afmformats)")
    contact = spy(monkeypatch, report_mod, "contact_figure")
    over_time = spy(monkeypatch, report_mod, "fit_figure")
    rep = tmp_path / "rep"
    assert main(["analyze", str(SPOT3), *HERTZ, "--segment", "approach", "--report", str(rep)]) == 0
    text = (rep / "report.md").read_text()
    assert "![indentation_1](indentation_1.png)" in text and (rep / "indentation_1.png").stat().st_size > 20_000
    assert "material   E = " in text and "kPa" in text  # the material line the terminal prints
    [fig] = contact
    ax_f, _, ax_fr, ax_sr = fig.axes[:4]
    # force against indentation and against the tip-sample separation (the cantilever's deflection known)
    assert ax_fr.get_xlabel() == "indentation (nm)" and ax_f.get_ylabel() == "force (nN)"
    assert ax_sr.get_xlabel().startswith("tip-sample separation (nm)")
    assert ax_fr.get_ylabel().startswith("residual (nN)")
    labels = legend_texts(ax_f)
    assert "model: hertz" in labels and "measured, approach" in labels
    assert "measured, retract" not in labels  # the approach alone was analysed
    assert any(t.startswith("contact point (fitted, ") and "nm of travel" in t for t in labels)
    # the contact point sits at indentation 0, on the fitted curve's baseline
    marker = next(line for line in ax_f.get_lines() if line.get_label().startswith("contact point"))
    assert marker.get_xdata()[0] == 0.0
    model = next(line for line in ax_f.get_lines() if line.get_label() == "model: hertz")
    xs, ys = np.asarray(model.get_xdata()), np.asarray(model.get_ydata())
    assert np.nanmax(xs) > 100  # the contact is the plot, not its last 5 %: > 100 nm deep on the axis
    assert np.nanmax(ys) > 3.0  # nN at the deepest point
    # the force against time keeps only the phases this approach-only curve has
    [tfig] = over_time
    shown = legend_texts(tfig.axes[0])
    assert "ramp" in shown and not {"hold_early", "hold_late", "return"} & set(shown)


@pytest.mark.skipif(not SPOT3.is_file(), reason=f"the real curve is not at {SPOT3}")
@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_report_tells_approach_from_retract(tmp_path, monkeypatch):
    pytest.importorskip("afmformats", reason="reading JPK files needs the afm extra (afmformats)")
    contact = spy(monkeypatch, report_mod, "contact_figure")
    assert main(["analyze", str(SPOT3), *HERTZ, "--segment", "all", "--report", str(tmp_path / "rep")]) == 0
    [fig] = contact
    labels = legend_texts(fig.axes[0])
    assert {"measured, approach", "measured, retract"} <= set(labels)


# ---------------------------------------------------------------- the rig's trials
SHORT = """name: short ramp-hold {v} mm/s to 6 mm
steps:
  - ramp: {{to_mm: 6, speed_mm_s: {v}}}
  - hold: {{duration_s: 6}}
  - return: {{to_mm: 0, speed_mm_s: 5}}
"""


@pytest.fixture(scope="module")
def day(tmp_path_factory):
    """A day's trials: three speeds on pig-07 (named as the recorder names them), a creep trial
    and a trial that tripped the force limit on pig-08."""
    from tests.conftest import PROTOCOLS, run_sim

    tmp = tmp_path_factory.mktemp("day")
    logs = [run_sim(SHORT.format(v=v), tmp_path=tmp, specimen="pig-07",
                    name=f"20261128-0900{i}0_pig-07_short-ramp-hold-{v}-mm-s-to-6-mm.mcap").log_path
            for i, v in enumerate((1, 2, 4))]
    creep = run_sim(PROTOCOLS / "creep-hold.yaml", tmp_path=tmp, specimen="pig-08",
                    name="20261128-100000_pig-08_creep-1-5-n-held-for-10-s.mcap").log_path
    fault = (PROTOCOLS / "paper-3mm_s.yaml").read_text().replace("max_force_N: 15", "max_force_N: 5")
    tripped = run_sim(fault, tmp_path=tmp, specimen="pig-08",
                      name="20261128-110000_pig-08_paper-ramp-hold-3-mm-s.mcap")
    assert tripped.outcome == "fault"
    return {"speeds": logs, "creep": creep, "fault": tripped.log_path, "dir": tmp}


def test_replay_of_several_logs_prints_a_table_and_draws_one_plot(day, tmp_path, capsys, monkeypatch):
    from rig.views import replay

    made = spy(monkeypatch, replay, "compare_figure")
    png = tmp_path / "cmp.png"
    logs = [*day["speeds"], day["fault"]]
    assert main(["replay", *map(str, logs), "--plot", str(png)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["trial", "specimen", "protocol", "outcome", "peak", "force", "k", "at", "hold",
                                "end", "est.", "error", "duration"]
    rows = lines[1:1 + len(logs)]
    assert [r.split()[0] for r in rows] == [p.name for p in logs]
    for r, v in zip(rows[:3], (1, 2, 4), strict=True):
        assert f"pig-07    short ramp-hold {v} mm/s to 6 mm" in r and "completed" in r
        assert " N/m" in r and r.rstrip().endswith(" s")
    assert "pig-08" in rows[3] and "fault" in rows[3] and "5.0" in rows[3]
    assert lines[-1] == f"plot       {png}" and png.stat().st_size > 20_000
    # one plot: every trial, told apart by specimen and protocol (its speed)
    [fig] = made
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels[:3] == [f"pig-07  short ramp-hold {v} mm/s to 6 mm" for v in (1, 2, 4)]
    assert [ax.get_xlabel() for ax in fig.axes] == ["time (s)", "indentation (mm)"]
    # the figures of each row are the single log's summary's
    assert main(["replay", *map(str, logs), "--json"]) == 0
    import json

    table = json.loads(capsys.readouterr().out)["trials"]
    assert main(["replay", str(logs[0]), "--json"]) == 0
    one = json.loads(capsys.readouterr().out)
    assert table[0]["peak_force_N"] == one["peak_force_N"]
    assert table[0]["hold_end_stiffness_N_per_m"] == one["estimator"]["hold_end"]["stiffness_N_per_m"]
    # CSV is one log's samples: said in one line, exit status 2
    assert main(["replay", *map(str, logs), "--csv", str(tmp_path / "x.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--csv writes one log's samples: give one log" in err[0]


def test_replay_tour_command_with_a_glob(day, tmp_path):
    """The README tour's `rig replay trials/*_pig-07_*.mcap` once a folder holds several."""
    import subprocess
    import sys

    from tests.conftest import ROOT

    command = f"{sys.executable} -m rig replay {day['dir']}/*_pig-07_*.mcap --plot {tmp_path}/d.png"
    proc = subprocess.run(command, shell=True, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "unrecognized arguments" not in proc.stderr
    assert len([line for line in proc.stdout.splitlines() if "_pig-07_" in line]) == 3


def test_logs_lists_peak_force_stiffness_and_estimator_error(day, capsys):
    assert main(["logs", "--dir", str(day["dir"])]) == 0
    lines = capsys.readouterr().out.splitlines()
    head = lines[0]
    for col in ("peak force", "k at hold end", "est. error", "outcome", "duration"):
        assert col in head
    assert len(lines) == 1 + 5
    creep_row = next(line for line in lines if "creep" in line)
    assert " N/m " in creep_row  # the force hold's end counts as a hold's end
    import json

    assert main(["logs", "--dir", str(day["dir"]), "--json"]) == 0
    entries = json.loads(capsys.readouterr().out)
    fault = next(e for e in entries if e["outcome"] == "fault")
    assert 5.0 <= fault["peak_force_N"] < 5.5
    assert all(e["estimator_error_rms_N"] > 0 for e in entries)


def test_fault_trial_legend_leaves_the_peak_in_sight(day, tmp_path, monkeypatch):
    from rig.recording.logs import read_log
    from rig.views import replay

    made = spy(monkeypatch, replay, "log_figure")
    assert main(["replay", str(day["fault"]), "--plot", str(tmp_path / "f.png")]) == 0
    [fig] = made
    fig.canvas.draw()
    ax = fig.axes[0]
    log = read_log(day["fault"])
    fault = next(e for e in log.events if e["kind"] == "fault")
    peak = ax.transData.transform((fault["t_s"], fault["data"]["force_N"]))
    box = ax.get_legend().get_window_extent()
    assert not box.contains(*peak)  # the peak where the limit tripped is not under the legend
    assert not box.overlaps(ax.get_window_extent())  # nor is any other sample
    texts = legend_texts(ax)
    assert any(t.startswith("fault: force ") and "above the limit of 5 N" in t for t in texts)


def test_creep_trial_shades_force_steps_and_draws_the_setpoint(day, tmp_path, monkeypatch):
    from rig.views import replay

    made = spy(monkeypatch, replay, "log_figure")
    assert main(["replay", str(day["creep"]), "--plot", str(tmp_path / "c.png")]) == 0
    [fig] = made
    ax = fig.axes[0]
    texts = legend_texts(ax)
    assert {"ramp_force", "hold_force", "force setpoint"} <= set(texts)
    setpoint = next(line for line in ax.get_lines() if line.get_label() == "force setpoint")
    assert np.nanmax(setpoint.get_ydata()) == pytest.approx(1.5)
    from matplotlib.colors import to_rgb

    shaded = [p.get_facecolor()[:3] for p in ax.patches]
    for kind in ("ramp_force", "hold_force"):
        assert any(np.allclose(c, to_rgb(replay._STEP_COLOURS[kind])) for c in shaded), kind


def test_fe_and_before_after_labels_keep_specimen_protocol_and_speed(day, tmp_path, monkeypatch):
    made_fe = spy(monkeypatch, report_mod, "fe_figure")
    made_steps = spy(monkeypatch, report_mod, "residual_steps_figure")
    assert main(["analyze", *map(str, day["speeds"]), "--model", "hooke", "--add", "relaxation",
                 "--report", str(tmp_path / "rep")]) == 0
    want = [f"pig-07 short-ramp-hold-{v}-mm-s-to-6-mm" for v in (1, 2, 4)]
    [fe] = [f for f in made_fe if f is not None]
    assert [t.replace("\n", "") for t in legend_texts(fe.axes[0])] == want
    [steps] = made_steps
    xlabels = [ax.get_xlabel() for ax in steps.axes if ax.get_xlabel()]
    assert [x.split("\n", 1)[0] for x in xlabels] == ["time (s)"] * 3
    assert [x.split("\n", 1)[1].replace("\n", "") for x in xlabels] == want


def test_campaign_plot_has_no_offset_that_makes_a_flat_error_look_steep():
    from rig.service.characterize import Campaign, Turn, campaign_figure

    camp = Campaign("pig-07", status="done", turns=[
        Turn("first look", "why", model="proposed", rmse_over_noise=1.0004, max_rse=0.05),
        Turn("designed", "why", model="proposed", rmse_over_noise=0.9999, max_rse=0.02)])
    fig = campaign_figure(camp)
    fig.canvas.draw()
    a = fig.axes[0]
    assert a.get_ylabel() == "RMSE / noise"
    assert a.yaxis.get_offset_text().get_text() == ""
    lo, hi = a.get_ylim()
    # the fall of 0.0005 is under a thousandth of the axis: drawn flat
    assert lo == 0.0 and 0.0005 / (hi - lo) < 1e-3


# ---------------------------------------------------------------- map reports
def _map_rows(with_positions: bool = True) -> list[dict]:
    """A 4 x 3 map, 5 µm pitch from (100 µm, -20 µm), E from 1 to 12 kPa, the surface rising
    0.1 µm per column; one curve that could not be analysed."""
    rows = []
    for gy in range(3):
        for gx in range(4):
            r = {"file": "m.jpk-force-map", "curve": gy * 4 + gx, "grid_x": gx, "grid_y": gy,
                 "x_m": (100 + 5 * gx) * 1e-6 if with_positions else None,
                 "y_m": (-20 + 5 * gy) * 1e-6 if with_positions else None,
                 "E_Pa": 1000.0 * (1 + gx + 4 * gy) / 1.0, "contact_point_m": 3e-6 - 0.1e-6 * gx,
                 "rmse_over_noise": 1.05, "error": ""}
            rows.append(r)
    place = ("file", "curve", "grid_x", "grid_y", "x_m", "y_m")
    rows[5] = {k: rows[5][k] for k in place} | {"error": "no contact"}
    return rows


def test_map_report_draws_um_axes_kpa_and_the_contact_height(tmp_path, monkeypatch):
    from rig.analysis.batch import map_report

    made = spy(monkeypatch, map_report, "map_figure")
    rows = _map_rows()
    report = map_report.write_map_report(rows, tmp_path, ["E_Pa"], "12 curves")
    names = {p.name for p in tmp_path.iterdir()}
    assert {"map1_E_Pa.png", "map1_contact_height.png", "map1_rmse_over_noise.png", "hist_E_Pa.png"} <= names
    assert "contact_height_m" not in rows[0]  # the caller's rows are left as they were
    by_label = {f.axes[1].get_ylabel(): f for f in made if f is not None}  # the colour bar's label
    assert {"E (kPa)", "contact height (µm)", "RMSE / noise"} <= set(by_label)
    e = by_label["E (kPa)"].axes[0]
    assert (e.get_xlabel(), e.get_ylabel()) == ("x (µm)", "y (µm)")
    img = e.get_images()[0]
    assert img.get_extent() == pytest.approx([97.5, 117.5, -22.5, -7.5])  # cells 5 µm wide around their centres
    data = np.ma.filled(img.get_array(), np.nan)
    assert data[0, 0] == pytest.approx(1.0) and data[2, 3] == pytest.approx(12.0)  # kPa
    assert np.isnan(data[1, 1])  # the curve that failed is a hole, hatched
    assert any(p.get_hatch() == "xxx" for p in e.patches)
    h = np.ma.filled(by_label["contact height (µm)"].axes[0].get_images()[0].get_array(), np.nan)
    assert h[0] == pytest.approx([0.0, 0.1, 0.2, 0.3])  # higher where the contact came sooner
    assert "Contact height" in report.read_text()


def test_map_report_without_positions_keeps_grid_numbers(tmp_path, monkeypatch):
    from rig.analysis.batch import map_report

    made = spy(monkeypatch, map_report, "map_figure")
    map_report.write_map_report(_map_rows(with_positions=False), tmp_path, ["E_Pa"], "12 curves")
    ax = next(f for f in made if f is not None).axes[0]
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("grid x", "grid y")


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_simulated_map_report_topography_follows_the_truth(tmp_path, monkeypatch):
    """The contact-height map of a simulated map (every curve started at one piezo height) is
    the surface the simulation drew, to a nanometre."""
    import json

    from rig.analysis.batch import map_report

    pytest.importorskip("afmformats", reason="reading the map needs the afm extra (afmformats)")
    made = spy(monkeypatch, map_report, "map_figure")
    h5 = tmp_path / "m.h5"
    assert main(["sim-map", str(h5), "--grid", "5x4"]) == 0
    assert main(["analyze", str(h5), *HERTZ, "--report", str(tmp_path / "rep")]) == 0
    fig = next(f for f in made if f is not None and f.axes[1].get_ylabel() == "contact height (µm)")
    got = np.ma.filled(fig.axes[0].get_images()[0].get_array(), np.nan)
    truth = json.loads(h5.with_suffix(".truth.json").read_text())["curves"]
    want = np.full(got.shape, np.nan)
    for c in truth:
        gx, gy = c["grid_index"]
        want[gy, gx] = c["contact_height_piezo_m"] / 1e-6
    want -= np.nanmin(want)
    assert np.nanmax(np.abs(got - want)) < 0.005  # µm
    assert fig.axes[0].get_xlabel() == "x (µm)"
