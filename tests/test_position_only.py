"""Position-only records: a CSV of time, position and force from an arbitrary zero, the probe
approaching out of contact, does not say where the surface is. Every fit places it (one contact
point and one zero per record) and the clean simulated controls fit to the noise, with nothing
to add, and with each record's contact where the simulated surface was."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rig.analysis.diagnosis.explain import explain
from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import load_trial
from rig.analysis.workflow.session import AnalyzeRequest, analyze
from rig.cli import main
from rig.models import CATALOGUE, build_model
from rig.recording.logs import read_log
from rig.specs.config import RigConfig
from tests.conftest import per_seed, run_sim

SEEDS = (1, 2, 3, 4, 5)
SPEEDS = ("1.5", "3")
SPECIMENS = ({}, {"k1_N_per_m3": 7.3e4, "tau1_s": 6.0, "k3_N_per_m": 20.0})  # stiffening, both


def surface_mm(seed: int) -> float:
    return 2.0 + 0.7 * seed  # where the surface lies in the slider's travel from its start


def controls(tmp: Path, seed: int) -> list[Path]:
    """Ramp-and-hold trials on the simulated rig with no hidden effect, the probe starting out
    of contact, written as t_s,position_mm,force_N with the position from an arbitrary zero."""
    surface = surface_mm(seed)
    zero = 13.7 - 4.3 * seed
    paths = []
    for i, v in enumerate(SPEEDS):
        cfg = RigConfig()
        cfg.sim.seed = 100 * seed + i
        cfg.sim.tissue.surface_mm = surface
        for k, val in SPECIMENS[seed % 2].items():
            setattr(cfg.sim.tissue, k, val)
        proto = (f"name: ramp {v} mm/s\nsteps:\n  - ramp: {{to_mm: {30 + surface}, speed_mm_s: {v}}}\n"
                 "  - hold: {duration_s: 30}\n  - return: {to_mm: 0, speed_mm_s: 5}\n")
        log = read_log(run_sim(proto, cfg, tmp, name=f"{seed}-{v}.mcap").log_path)
        s = log.samples
        path = tmp / f"control-{seed}-{v}.csv"
        rows = (f"{float(t)!r},{float(p) + zero!r},{float(f)!r}"
                for t, p, f in zip(s["t_s"], s["position_mm"], s["force_N"], strict=True))
        path.write_text("t_s,position_mm,force_N\n" + "\n".join(rows) + "\n")
        paths.append(path)
    return paths


def _one_seed(seed: int, tmp_path: Path) -> str:
    """'' when the controls of `seed` are adequate, with nothing to add and each contact within
    two standard errors of the surface; else what was read."""
    tmp = tmp_path / str(seed)
    tmp.mkdir()
    trials = [load_trial(p) for p in controls(tmp, seed)]
    assert all(t.contact_estimated for t in trials)
    base = fit(build_model("proposed"), trials)
    ex = explain(base, dict(CATALOGUE))
    problems = []
    if not base.adequate:
        problems.append(base.verdict())
    if ex.suggestions:
        problems.append(ex.summary)
    for row in base.placements():
        off = row["contact_point_m"] - surface_mm(seed) / 1000.0
        se = row["contact_point_m_stderr"]
        if not (se and 0 < se < 1e-3 and abs(off) <= 2 * se):
            problems.append(f"contact {row['contact_point_m'] * 1e3:.3f} mm +/- {se and se * 1e3:.3g}, "
                            f"surface {surface_mm(seed):.3f} mm")
    return f"seed {seed}: " + "; ".join(problems) if problems else ""


def test_clean_controls_fit_to_the_noise_with_each_contact_where_the_surface_was(tmp_path):
    misses = [m for m in per_seed(_one_seed, SEEDS, tmp_path) if m]
    assert not misses, "\n".join(misses)


def test_what_the_user_reads_through_the_command_line(tmp_path, capsys):
    paths = controls(tmp_path, 3)
    assert main(["analyze", *map(str, paths), "--explain", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["adequate"] is True and out["suggestions"] == [], out["diagnosis"]
    assert out["diagnosis"]["best"] is None
    assert {"contact_point", "offset"} <= set(out["effects"])
    for rec in out["records"]:
        assert abs(rec["contact_point_m"] - surface_mm(3) / 1000.0) <= 2 * rec["contact_point_m_stderr"], rec
        assert "zero_N" in rec and rec["zero_N_stderr"] > 0
        assert any("the fit refines it" in n for n in rec["notes"])
    assert main(["analyze", *map(str, paths)]) == 0
    text = capsys.readouterr().out
    for p in paths:
        line = next(s for s in text.splitlines() if s.startswith(f"contact    {p.name}: at "))
        at_mm = float(line.split(" at ")[1].split()[0])
        assert abs(at_mm - surface_mm(3)) < 0.5, line
    assert "adequate" in text and "NOT adequate" not in text


def test_a_record_that_knows_its_surface_keeps_it(tmp_path):
    """The same samples as indentation from the surface: nothing is added to the model."""
    (path,) = controls(tmp_path, 1)[:1]
    rows = np.loadtxt(path, delimiter=",", skiprows=1)
    rows[:, 1] -= rows[0, 1] + surface_mm(1)
    known = tmp_path / "known.csv"
    np.savetxt(known, rows, delimiter=",", header="t_s,indentation_mm,force_N", comments="")
    t = load_trial(known)
    assert not t.contact_estimated
    res = fit(build_model("proposed"), [t])
    assert res.model.effect_names == ["poly_elastic", "nonlinear_damping", "relaxation"]
    assert res.adequate, res.verdict()


@pytest.mark.parametrize("n", [1, 2])
def test_each_record_has_its_own_contact_point_and_zero(tmp_path, n):
    paths = controls(tmp_path, 2)[:n]
    res = fit(build_model("proposed"), [load_trial(p) for p in paths])
    names = res.model.param_names
    if n == 1:
        assert "x_c_m" in names and "offset_N" in names
    else:
        assert {"x_c_m@0", "x_c_m@1", "offset_N@0", "offset_N@1"} <= set(names)
        assert "x_c_m" not in names
        # the report names the record each belongs to
        assert f"({paths[1].name})" in next(s for s in res.report().splitlines() if "x_c_m@1" in s)


def test_a_held_out_record_is_placed_before_it_is_scored(tmp_path):
    """Fitted on one control, scored on the other: the held-out record's contact point and zero
    are its own (fitted with the model held), so its error is the noise."""
    paths = controls(tmp_path, 4)
    out = analyze(AnalyzeRequest([str(paths[0])], holdout=[str(paths[1])])).json
    assert out["adequate"], out["fit"]
    (held,) = out["holdout"]
    assert held["rmse_N"] < 1.2 * out["fit"]["noise_N"], (held, out["fit"]["noise_N"])
    assert abs(held["contact_point_m"] - surface_mm(4) / 1000.0) <= 2 * held["contact_point_m_stderr"], held
