"""Input the rig must refuse with one clear line: saved models out of range, YAML alias bombs,
a stored config that does not parse, parameters the data cannot determine."""

from __future__ import annotations

import json
import time

import pytest

from rig.errors import RigError
from rig.models.catalogue import build_model
from rig.models.saved import SavedModel, load, loads, runnable

# ---------------------------------------------------------------- saved models


def _saved_text(**changes: float) -> str:
    model = build_model("proposed")
    values = {"k1_N_per_m3": 5.6e4, "k2_N_per_m2": 550.0, "k3_N_per_m": 14.0, "tau2_N_s_per_m2": 2.3e5,
              "tau1_s": 8.0}
    assert set(values) == set(model.param_names)
    data = json.loads(SavedModel(model, values).text())
    for name, value in changes.items():
        data["parameters"][name]["value"] = value
    return json.dumps(data)  # NaN and Infinity as Python's json writes (and reads) them


def test_a_valid_saved_model_loads():
    assert loads(_saved_text(), "m.json").values["tau1_s"] == 8.0


@pytest.mark.parametrize(("name", "value", "expect"), [
    ("k3_N_per_m", float("nan"), "parameter 'k3_N_per_m' = nan N/m: not a finite number"),
    ("tau2_N_s_per_m2", float("inf"), "parameter 'tau2_N_s_per_m2' = inf N s/m^2: not a finite number"),
    ("tau1_s", -2.0, "parameter 'tau1_s' = -2 s is outside its bounds (> 0 s)"),
    ("tau1_s", 0.0, "parameter 'tau1_s' = 0 s is outside its bounds (> 0 s)"),
])
def test_a_saved_model_out_of_range_is_refused_naming_file_parameter_value_and_bounds(
        tmp_path, name, value, expect):
    path = tmp_path / "bad.json"
    path.write_text(_saved_text(**{name: value}))
    with pytest.raises(RigError) as err:
        runnable(load(path))  # what `rig run --model` and the daemon's socket request go through
    assert str(err.value) == f"{path}: {expect}"


def test_a_dimensionless_parameter_is_checked_against_its_bounds_as_written():
    model = build_model("linear_elastic", ["hc_damping"])
    values = {p.name: 1.0 for p in model.params} | {"n": 7.5}
    with pytest.raises(RigError, match=r"m.json: parameter 'n' = 7.5 is outside its bounds \(>= 0.2, <= 6\)"):
        loads(SavedModel(model, values).text(), "m.json")


# ---------------------------------------------------------------- YAML aliases

def _alias_bomb(levels: int) -> str:
    lines = ["name: bomb", "a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for i in range(1, levels + 1):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]")
    lines.append("steps:\n  - hold: {duration_s: 1}")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("levels", [5, 9])
def test_nested_aliases_are_refused_at_once_naming_where(levels):
    from rig.errors import SpecError
    from rig.specs.protocol import parse_protocol

    text = _alias_bomb(levels)
    assert len(text) < 700
    began = time.perf_counter()
    with pytest.raises(SpecError) as err:
        parse_protocol(text, "bomb.yaml")
    assert time.perf_counter() - began < 1.0  # before: 5.5 s at 5 levels, ten times more per level
    assert "bomb.yaml:" in str(err.value) and "aliases (*name) are expanded" in str(err.value)
    assert err.value.line is not None and err.value.column is not None


@pytest.mark.parametrize("text", ["name: x\nsteps: &s\n  - hold: *s\n", "name: x\nsteps: &s [*s]\n"])
def test_a_self_referencing_alias_is_one_clear_error(text):
    from rig.errors import SpecError
    from rig.specs.protocol import parse_protocol

    with pytest.raises(SpecError, match=r"x.yaml:\d+:\d+: .*alias \(\*name\) inside its own anchor"):
        parse_protocol(text, "x.yaml")


def test_config_files_use_the_same_guarded_loader():
    from rig.errors import SpecError
    from rig.specs.config import parse_config

    with pytest.raises(SpecError, match=r"rig.yaml:\d+:\d+: .*aliases \(\*name\) are expanded"):
        parse_config(_alias_bomb(5), "rig.yaml")


def test_deep_nesting_is_refused():
    from rig.errors import SpecError
    from rig.specs.protocol import parse_protocol

    text = "name: x\nsteps: " + "[" * 100 + "]" * 100 + "\n"
    with pytest.raises(SpecError, match=r"x.yaml:2:\d+: .*nested more than 64 levels"):
        parse_protocol(text, "x.yaml")


def test_an_ordinary_alias_still_works():
    from rig.specs.protocol import parse_protocol

    text = ("name: x\nsteps:\n  - ramp: &r {to_mm: 2, speed_mm_s: 1}\n  - return: {speed_mm_s: 1}\n"
            "  - ramp: *r\n")
    proto = parse_protocol(text, "x.yaml")
    assert [s.kind for s in proto.steps] == ["ramp", "return", "ramp"]


# ---------------------------------------------------------------- a parameter the data cannot determine

def _inert(m, force, inert_N):
    """A sensor effect whose parameter the force does not depend on: its Jacobian column is zero."""
    return 0.0 * inert_N * force


def test_a_parameter_the_data_cannot_determine_is_reported_so_not_as_exact(paper_075_log):
    import math

    from rig.analysis.fitting.fit import fit
    from rig.analysis.trials.data import load_trial
    from rig.analysis.workflow.results import result_json
    from rig.models.catalogue import CATALOGUE
    from rig.models.core import Effect, Model, Param

    inert = Effect(name="inert", stage="sensor", params=(Param("inert_N", "N", 0.5),), fn=_inert,
                   equation="no force at all", signature="-", source="plugin")
    res = fit(Model([CATALOGUE["linear_elastic"], inert]), [load_trial(paper_075_log.log_path)])
    assert res.stderr["inert_N"] == math.inf
    assert 0 < res.stderr["k_N_per_m"] < math.inf
    text = res.report()
    line = next(ln for ln in text.splitlines() if ln.strip().startswith("inert_N"))
    assert "+/-" not in line and "(not determined)" in line
    assert any("inert.inert_N" in w and "not determined" in w for w in res.warnings)
    js = result_json(res, ["x"])["parameters"]
    assert js["inert_N"]["stderr"] is None and js["inert_N"]["determined"] is False
    assert js["k_N_per_m"]["determined"] is True and js["k_N_per_m"]["stderr"] > 0
    json.dumps(js, allow_nan=False)  # valid JSON: no Infinity


# ---------------------------------------------------------------- replay's stored config

def test_replay_says_when_the_stored_config_does_not_parse(paper_075_log, tmp_path):
    """A log whose config.yaml does not parse is replayed with the defaults, and says so."""
    from mcap.writer import Writer

    from rig.recording.logs import read_log
    from rig.views.replay import format_summary, summarize

    log = read_log(paper_075_log.log_path, keep_raw=True)
    path = tmp_path / "broken-config.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        ids = {}
        for topic, rows in log.raw_messages.items():
            sid = w.register_schema(topic, "jsonschema", json.dumps(log.schemas.get(topic, {})).encode())
            ids[topic] = w.register_channel(topic, "json", sid)
            for row in rows:
                w.add_message(ids[topic], 0, json.dumps(row).encode(), 0)
        for name, kv in log.metadata.items():
            w.add_metadata(name, kv)
        w.add_attachment(0, 0, "config.yaml", "application/yaml", b"loop:\n  rate_Hz: fast\n")
        w.finish()
    d = summarize(read_log(path))
    assert "reproduced" not in d["estimator"]
    (warning,) = d["warnings"]
    assert "config.yaml does not parse" in warning and "rate_Hz" in warning
    assert "defaults (100 Hz, 5 ms late)" in warning and "estimator not re-run" in warning
    assert f"WARNING    {warning}" in format_summary(d)
