"""The pictures a researcher reads: what each figure shows, checked on the Figure objects the
commands save (axis labels and units, legends, what is shaded, where the legend sits)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rig.analysis import report as report_mod
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
    assert main(["analyze", str(SPOT3), *HERTZ, "--report", str(tmp_path / "rep")]) == 0
    [fig] = contact
    labels = legend_texts(fig.axes[0])
    assert {"measured, approach", "measured, retract"} <= set(labels)
