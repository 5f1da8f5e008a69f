"""Protocols and rig configs that would defeat the limits are refused before anything moves:
limits that are not finite numbers, a stale check a config could switch off, durations that
never end, force steps with a depth budget that retracts, numbers YAML 1.1 reads as text,
repeats beyond the rig's cap, and repeats whose approaches re-zero deeper each time (issue 41).
Every refusal is one line naming the file, line and field."""

from __future__ import annotations

import dataclasses
import itertools
import json
import re
import subprocess
import sys
import time
import tracemalloc
import typing

import numpy as np
import pytest
import yaml

from rig.cli import main
from rig.control.estimator import excitation_order
from rig.errors import LimitError, SpecError
from rig.specs.config import RigConfig, parse_config
from rig.specs.motion import LaggedSums, sample_move
from rig.specs.protocol import Reach, check_limits, load_protocol, parse_protocol, plan
from tests.conftest import PROTOCOLS, ROOT, run_sim


def _check(tmp_path, capsys, text: str, *extra: str, name: str = "p.yaml") -> tuple[int, str, str]:
    """`rig check` on `text`: (exit status, stdout, the one line on stderr)."""
    path = tmp_path / name
    path.write_text(text)
    code = main(["check", str(path), *extra])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) <= 1, err
    return code, out, err.strip()


# ---------------------------------------------------------------- 1. limits that limit nothing

@pytest.mark.parametrize(("limits", "key", "fragment"), [
    ("{max_force_N: .inf}", "limits.max_force_N", "must be a finite number, not .inf"),
    ("{max_speed_mm_s: .inf}", "limits.max_speed_mm_s", "must be a finite number, not .inf"),
    ("{max_force_N: .nan}", "limits.max_force_N", "not NaN"),
    ("{travel_mm: [-.inf, .inf]}", "limits.travel_mm", "finite numbers"),
    ("{travel_mm: [0, .inf]}", "limits.travel_mm", "finite numbers"),
])
def test_a_protocol_with_limits_that_are_not_finite_is_refused_naming_line_and_key(
        tmp_path, capsys, limits, key, fragment):
    text = f"name: x\nsteps:\n  - ramp: {{to_mm: 3, speed_mm_s: 1}}\nlimits: {limits}\n"
    code, _, err = _check(tmp_path, capsys, text)
    assert code == 2
    assert "p.yaml:4:" in err and key in err and fragment in err, err


@pytest.mark.parametrize(("text", "line", "key"), [
    ("limits: {max_force_N: .inf}\n", 1, "limits.max_force_N"),
    ("limits:\n  travel_mm: [-.inf, .inf]\n", 2, "limits.travel_mm[0]"),
    ("limits:\n  max_speed_mm_s: .inf\n", 2, "limits.max_speed_mm_s"),
    ("limits:\n  max_speed_mm_s: .nan\n", 2, "limits.max_speed_mm_s"),
])
def test_a_rig_config_with_limits_that_are_not_finite_is_refused_naming_line_and_key(text, line, key):
    with pytest.raises(SpecError) as err:
        parse_config(text, "rig.yaml")
    msg = str(err.value)
    assert msg.startswith(f"rig.yaml:{line}:") and f" {key}: " in msg, msg
    assert "finite" in msg or "NaN" in msg, msg


@pytest.mark.parametrize("value", [".inf", "5000", "3600000"])
def test_the_stale_check_cannot_be_switched_off_by_a_long_limit(value):
    with pytest.raises(SpecError) as err:
        parse_config(f"limits:\n  loadcell_stale_ms: {value}\n", "rig.yaml")
    msg = str(err.value)
    assert msg.startswith("rig.yaml:2:") and "limits.loadcell_stale_ms" in msg, msg
    assert "stale check cannot be switched off" in msg and "1000 ms" in msg, msg
    assert parse_config("limits: {loadcell_stale_ms: 1000}\n").limits.loadcell_stale_ms == 1000


def _numeric_fields(cls: type, prefix: tuple[str, ...] = ()) -> typing.Iterator[tuple[tuple[str, ...], type]]:
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        tp = args[0] if typing.get_origin(tp) in (typing.Union, type(int | None)) and len(args) == 1 else tp
        if dataclasses.is_dataclass(tp):
            yield from _numeric_fields(tp, (*prefix, f.name))
        elif tp is float:
            yield (*prefix, f.name), tp


CONFIG_FLOATS = [".".join(path) for path, _ in _numeric_fields(RigConfig)]


def test_the_config_has_many_numbers_to_check():
    assert len(CONFIG_FLOATS) > 60 and "sim.tissue.k1_N_per_m3" in CONFIG_FLOATS


@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan"])
def test_every_number_in_a_rig_config_must_be_finite(value):
    """No field of the rig config (the simulated rig's included) is documented to take
    infinity: every one of them, set to .inf, -.inf or .nan, is refused naming its key."""
    accepted = []
    for dotted in CONFIG_FLOATS:
        *outer, last = dotted.split(".")
        text = "".join(f"{'  ' * i}{k}:\n" for i, k in enumerate(outer))
        text += f"{'  ' * len(outer)}{last}: {value}\n"
        try:
            parse_config(text, "rig.yaml")
        except SpecError as exc:
            assert f"rig.yaml:{len(outer) + 1}:" in str(exc) and dotted in str(exc), str(exc)
        else:
            accepted.append(dotted)
    assert not accepted, f"{value} accepted in {accepted}"


STEP_NUMBERS = {
    "ramp": ("{to_mm: 3, speed_mm_s: 1, accel_mm_s2: 20}", ("to_mm", "speed_mm_s", "accel_mm_s2")),
    "hold": ("{until_rate_N_s: 0.01, max_s: 9, window_s: 2}", ("until_rate_N_s", "max_s", "window_s")),
    "return": ("{to_mm: 0, speed_mm_s: 5}", ("to_mm", "speed_mm_s")),
    "approach": ("{speed_mm_s: 0.5, contact_N: 0.2, max_mm: 10}", ("speed_mm_s", "contact_N", "max_mm")),
    "ramp_force": ("{to_N: 2, rate_N_s: 1, max_mm: 10}", ("to_N", "rate_N_s", "max_mm")),
    "hold_force": ("{force_N: 2, duration_s: 3, max_mm: 10}", ("force_N", "duration_s", "max_mm")),
}


@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan"])
def test_every_number_in_a_protocol_must_be_finite(value):
    accepted = []
    cases = [(kind, key) for kind, (_, keys) in STEP_NUMBERS.items() for key in keys]
    for kind, key in cases:
        body, _ = STEP_NUMBERS[kind]
        body = re.sub(rf"\b{key}: [^,}}]+", f"{key}: {value}", body)
        text = f"name: x\nsteps:\n  - ramp: {{to_mm: 1, speed_mm_s: 1}}\n  - {kind}: {body}\n"
        try:
            parse_protocol(text, "p.yaml")
        except SpecError as exc:
            assert str(exc).startswith("p.yaml:4:") and f"steps[1].{kind}.{key}" in str(exc), str(exc)
        else:
            accepted.append(f"{kind}.{key}")
    for top in ("rest_s", "limits: {max_force_N", "limits: {max_speed_mm_s"):
        close = "}" if "{" in top else ""
        text = f"name: x\nsteps:\n  - hold: {{duration_s: 1}}\nrepeat: 2\n{top}: {value}{close}\n"
        with pytest.raises(SpecError, match=r"p\.yaml:5:"):
            parse_protocol(text, "p.yaml")
    assert not accepted, f"{value} accepted in {accepted}"


@pytest.mark.parametrize(("text", "line", "key", "fragment"), [
    ("limits: {max_force_N: 600}\n", 1, "limits.max_force_N",
     "a force limit of 600 N is beyond the load cell's range (loadcell.max_abs_N 500 N)"),
    ("loadcell:\n  max_abs_N: 10\n", 2, "loadcell.max_abs_N",
     "a force limit of 20 N is beyond the load cell's range (loadcell.max_abs_N 10 N)"),
    ("limits:\n  travel_mm: [-5, 100000.0]\n", 2, "limits.travel_mm[1]",
     "must be at most 10000, got 100000: a travel window wider than any slider's stroke"),
    ("limits:\n  max_speed_mm_s: 100000.0\n", 2, "limits.max_speed_mm_s",
     "must be at most 1000, got 100000: a speed limit beyond any indentation slider limits nothing"),
])
def test_a_rig_config_with_absurd_limits_is_refused(text, line, key, fragment):
    with pytest.raises(SpecError) as err:
        parse_config(text, "rig.yaml")
    msg = str(err.value)
    assert msg.startswith(f"rig.yaml:{line}:") and f" {key}: " in msg and fragment in msg, msg
    # a rig without a load cell limits the model's force: no range to stay within
    assert parse_config("limits: {max_force_N: 600}\nloadcell: {backend: none}\n").limits.max_force_N == 600


@pytest.mark.parametrize(("step", "fragment"), [
    ("ramp: {to_mm: 3, speed_mm_s: 0.001}", "ramp speed 0.001 mm/s is below the drive's slowest (one step a "
                                            "second, 0.01 mm/s at slider.steps_per_mm 100)"),
    ("approach: {speed_mm_s: 1.0e-300, contact_N: 0.2, max_mm: 5}", "approach speed 1e-300 mm/s is below"),
    ("ramp: {to_mm: 3, speed_mm_s: 1, accel_mm_s2: 1.0e-300}",
     "ramp accel_mm_s2 1e-300 is below the drive's least, one step a second squared (0.01 mm/s^2)"),
])
def test_a_move_slower_than_the_drive_can_go_is_refused(tmp_path, capsys, step, fragment):
    """The drive moves at whole steps a second at least: 0.001 mm/s would run ten times faster
    than planned, and 1e-300 mm/s planned a move of 1e300 s (rig check hung on it)."""
    code, _, err = _check(tmp_path, capsys, f"name: x\nsteps:\n  - {step}\n")
    assert code == 2 and f"p.yaml:3: {fragment}" in err, err


@pytest.mark.parametrize("step", ["hold: {duration_s: 1.0e+300}",
                                  "ramp_force: {to_N: 3, rate_N_s: 1.0e-300, max_mm: 5}"])
def test_a_finite_but_endless_step_is_planned_without_sampling_it(tmp_path, capsys, step):
    began = time.perf_counter()
    text = f"name: x\nsteps:\n  - ramp: {{to_mm: 3, speed_mm_s: 1}}\n  - {step}\n"
    code, out, _ = _check(tmp_path, capsys, text)
    assert code == 0 and "duration  " in out and time.perf_counter() - began < 10


# ---------------------------------------------------------------- 2. durations that never end

@pytest.mark.parametrize(("text", "line", "field"), [
    ("name: x\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: 1}\n  - hold: {duration_s: .inf}\n", 4,
     "steps[1].hold.duration_s"),
    ("name: x\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: 1}\nrepeat: 2\nrest_s: .inf\n", 5, "rest_s"),
    ("name: x\nsteps:\n  - hold: {until_rate_N_s: 0.01, max_s: .inf}\n", 3, "steps[0].hold.max_s"),
    ("name: x\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: 1}\n"
     "  - hold_force: {force_N: 1, duration_s: .inf, max_mm: 10}\n", 4, "steps[1].hold_force.duration_s"),
])
def test_an_endless_duration_is_refused_by_rig_check_without_a_traceback(tmp_path, capsys, text, line, field):
    code, _, err = _check(tmp_path, capsys, text)
    assert code == 2
    assert f"p.yaml:{line}:" in err and f" {field}: " in err and "finite" in err, err


# ---------------------------------------------------------------- 3. a depth budget that retracts

@pytest.mark.parametrize("kind", ["hold_force", "ramp_force", "approach"])
@pytest.mark.parametrize("max_mm", ["-3", "0"])
def test_a_force_step_or_approach_with_max_mm_not_above_zero_is_refused(tmp_path, capsys, kind, max_mm):
    body = {"hold_force": "force_N: 2, duration_s: 3", "ramp_force": "to_N: 2, rate_N_s: 1",
            "approach": "speed_mm_s: 0.5, contact_N: 0.2"}[kind]
    text = f"name: x\nsteps:\n  - ramp: {{to_mm: 3, speed_mm_s: 1}}\n  - {kind}: {{{body}, max_mm: {max_mm}}}\n"
    code, _, err = _check(tmp_path, capsys, text)
    assert code == 2
    assert "p.yaml:4:" in err and f"steps[1].{kind}.max_mm" in err, err
    assert f"must be greater than 0, got {max_mm}" in err and "how deep" in err, err


# ---------------------------------------------------------------- 4. 1e12 is text in YAML 1.1

@pytest.mark.parametrize(("written", "hint"), [
    ("1e12", "write 1.0e+12 or 1000000000000"),
    ("1.5e3", "write 1.5e+3 or 1500"),
    ("5e-3", "write 5.0e-3 or 0.005"),
    ("-4E2", "write -4.0e+2 or -400"),
])
def test_exponent_notation_yaml_reads_as_text_says_how_to_write_it(tmp_path, capsys, written, hint):
    # a protocol's number
    code, _, err = _check(tmp_path, capsys, f"name: x\nsteps:\n  - ramp: {{to_mm: {written}, speed_mm_s: 1}}\n")
    assert code == 2 and "p.yaml:3:" in err and "steps[0].ramp.to_mm" in err, err
    assert f"expected a number, got text '{written}' (YAML reads {written} as text: {hint})" in err, err
    # a rig config's number
    with pytest.raises(SpecError) as info:
        parse_config(f"sim:\n  tissue:\n    k1_N_per_m3: {written}\n", "rig.yaml")
    assert str(info.value).startswith("rig.yaml:3:") and hint in str(info.value), str(info.value)
    # both spellings it offers are the number, as YAML reads them
    for spelling in hint.removeprefix("write ").split(" or "):
        assert yaml.safe_load(spelling) == pytest.approx(float(written))


def test_exponent_notation_where_an_integer_is_expected_offers_the_digits(tmp_path, capsys):
    code, _, err = _check(tmp_path, capsys, "name: x\nsteps:\n  - hold: {duration_s: 1}\nrepeat: 1e3\n")
    assert code == 2 and "p.yaml:4:" in err and "repeat" in err, err
    assert "expected an integer, got text '1e3' (YAML reads 1e3 as text: write 1000)" in err, err
    with pytest.raises(SpecError, match=r"write 20000\)"):
        parse_config("limits: {max_protocol_steps: 2e4}\n", "rig.yaml")


# ---------------------------------------------------------------- 5. the size of a protocol

def test_a_huge_repeat_is_refused_at_once_by_the_real_command_line(tmp_path):
    path = tmp_path / "huge.yaml"
    path.write_text("name: huge\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: 1}\n  - return: {speed_mm_s: 5}\n"
                    "repeat: 100000000\n")
    began = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "rig", "check", str(path)], capture_output=True, text=True,
                          timeout=60, cwd=ROOT)  # before: it hung, growing by gigabytes
    assert time.perf_counter() - began < 30
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "huge.yaml:5:" in proc.stderr and "repeat" in proc.stderr, proc.stderr
    assert "200000000 steps run (2 x repeat 100000000)" in proc.stderr, proc.stderr


def test_the_rig_config_caps_the_steps_a_protocol_runs(tmp_path, capsys):
    text = ("name: many\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: 5}\n  - return: {speed_mm_s: 5}\n"
            "repeat: 4000\nrest_s: 1\n")
    proto = parse_protocol(text, "many.yaml")
    assert proto.executed_steps == 2 * 4000 + 3999 == len(proto.run_steps())
    assert RigConfig().limits.max_protocol_steps == 10_000
    with pytest.raises(LimitError) as err:
        check_limits(proto, RigConfig())
    msg = str(err.value)
    assert msg.startswith("many.yaml:5: repeat 4000: 11999 steps run (2 x repeat 4000 + 3999 rests)"), msg
    assert "limits.max_protocol_steps 10000" in msg, msg
    code, _, err_line = _check(tmp_path, capsys, text)
    assert code == 2 and "max_protocol_steps" in err_line
    # a rig config may raise it (up to a ceiling no config passes)
    cfg = tmp_path / "rig.yaml"
    cfg.write_text("limits: {max_protocol_steps: 12000}\n")
    code, out, _ = _check(tmp_path, capsys, text, "--config", str(cfg))
    assert code == 0 and "(x4000, 1 s rest between: 11999 steps)" in out, out
    with pytest.raises(SpecError, match="at most 1e\\+06"):
        parse_config("limits: {max_protocol_steps: 2000000}\n", "rig.yaml")


AT_THE_CAP = ("name: at the cap\nsteps:\n  - ramp: {to_mm: 10, speed_mm_s: 2}\n  - hold: {duration_s: 60}\n"
              "  - return: {to_mm: 0, speed_mm_s: 5}\nrepeat: 2500\nrest_s: 30\n")  # 3 x 2500 + 2499 = 9999


def test_a_protocol_at_the_cap_is_checked_and_planned_in_little_time_and_memory(tmp_path, capsys):
    """9,999 steps, 73 hours of trial: 26 million samples at 100 Hz, which the plan once sampled
    (with four lagged copies for the excitation order: gigabytes). Now its pieces only."""
    cfg = RigConfig()
    proto = parse_protocol(AT_THE_CAP, "cap.yaml")
    assert proto.executed_steps == 9999 <= cfg.limits.max_protocol_steps
    tracemalloc.start()
    # the work's own CPU time: on a loaded machine the wall clock measured the load (20 s of
    # wall for 3.3 s of CPU, under tracemalloc, beside a benchmark on both cores)
    began = time.process_time()
    check_limits(proto, cfg)
    p = plan(proto, cfg)
    order = p.excitation_order(1.0 / cfg.sim.slider.steps_per_mm)
    took = time.process_time() - began
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert order == 1 and p.duration_s == pytest.approx(2500 * (5.04 + 60 + 2.1) + 2499 * 30 + 0.5)
    assert peak < 40e6, f"{peak / 1e6:.0f} MB"  # the samples alone would be 210 MB
    assert took < 20, took  # 3.3 s of CPU under tracemalloc here (0.4 s without)
    code, out, _ = _check(tmp_path, capsys, AT_THE_CAP)
    assert code == 0 and "depths    10 mm in each of 2500 repeats" in out, out


@pytest.mark.parametrize("repeat", [1000, 2000])
def test_check_and_plan_grow_in_proportion_to_the_steps_run(repeat):
    """A return that stays in contact gives every repeat a new zero: no repeat is like the last,
    so the check walks them all; twice the repeats, about twice the work, not four times."""
    text = ("name: x\nsteps:\n  - approach: {speed_mm_s: 0.1, contact_N: 0.2, max_mm: 2}\n"
            "  - ramp: {to_mm: 0.01, speed_mm_s: 1}\n  - return: {to_mm: 0.001, speed_mm_s: 1}\n"
            f"repeat: {repeat}\n")
    cfg = RigConfig()
    proto = parse_protocol(text, "x.yaml")
    best = min(_timed(lambda: (check_limits(proto, cfg), plan(proto, cfg))) for _ in range(3))
    per_step_us = best / proto.executed_steps * 1e6
    assert per_step_us < 500, per_step_us  # about 20 us a step alone on the machine


def _timed(fn: typing.Callable[[], object]) -> float:
    began = time.perf_counter()
    fn()
    return time.perf_counter() - began


def _random_pieces(rng: np.random.Generator) -> tuple[LaggedSums, np.ndarray]:
    acc, parts, x = LaggedSums(), [], 0.0
    for _ in range(int(rng.integers(1, 7))):
        if rng.random() < 0.4:
            n = int(rng.integers(1, 400))
            acc.push_poly((x, 0.0, 0.0), n)
            parts.append(np.full(n, x))
        else:
            x1 = float(rng.uniform(-5, 40))
            speed, accel = float(rng.choice([0.05, 0.75, 3, 10, 100])), float(rng.choice([0.5, 50, 5000]))
            acc.push_move(x, x1, speed, accel, 100.0)
            parts.append(sample_move(x, x1, speed, accel, 100.0))
            x = x1
    return acc, np.concatenate(parts)


def test_the_lagged_sums_of_pieces_equal_those_of_the_samples():
    rng = np.random.default_rng(41)
    for _ in range(200):
        acc, u = _random_pieces(rng)
        assert acc.count == len(u)
        for n in range(1, 5):
            if len(u) <= n + 1:
                break
            lags = np.column_stack([u[n - i: len(u) - i] for i in range(1, n + 1)])
            np.testing.assert_allclose(acc.information(n), lags.T @ lags, rtol=1e-9, atol=1e-6)
        for resolution in (0.01, 0.1, 1.0):
            assert acc.excitation_order(resolution) == excitation_order(u, resolution)


@pytest.mark.parametrize("name", sorted(p.name for p in PROTOCOLS.glob("*.yaml")))
def test_the_plan_of_every_shipped_protocol_has_the_excitation_order_of_its_samples(name):
    cfg = RigConfig()
    p = plan(load_protocol(PROTOCOLS / name, cfg), cfg)
    t, x = p.samples()
    assert t[-1] == pytest.approx(p.duration_s) and x.max() == pytest.approx(p.max_position_mm)
    for resolution in (0.01, 0.001):
        assert p.excitation_order(resolution) == excitation_order(x, resolution)


# ---------------------------------------------------------------- 6. repeats that re-zero deeper

ISSUE = ("name: deeper each time\nsteps:\n  - approach: {{speed_mm_s: 0.5, contact_N: 0.1, max_mm: 10}}\n"
         "  - ramp: {{to_mm: 8, speed_mm_s: 2}}\n  - return: {{to_mm: {back}, speed_mm_s: 5}}\n"
         "repeat: {repeat}\n")


def test_repeats_whose_return_stays_in_contact_are_refused_before_they_leave_the_travel(tmp_path, capsys):
    """The issue's protocol: each return to 4 mm leaves the probe in the tissue, the next approach
    re-zeroes there, and with 12 repeats the trial faulted at 46.4 mm; `rig check` passed it."""
    code, _, err = _check(tmp_path, capsys, ISSUE.format(back=4, repeat=12))
    assert code == 2, err
    assert ("p.yaml:4: repeat 8 of 12: ramp to 36.19 mm from the first contact "
            "(absolute up to 46.19 mm)") in err, err
    assert "outside the travel window [-5, 45] mm" in err and "re-zeroes where it starts" in err, err
    with pytest.raises(LimitError, match="repeat 8 of 12: ramp"):
        check_limits(parse_protocol(ISSUE.format(back=4, repeat=12), "p.yaml"), RigConfig())


def test_rig_check_prints_the_depths_from_the_first_contact(tmp_path, capsys):
    code, out, _ = _check(tmp_path, capsys, ISSUE.format(back=4, repeat=6))
    assert code == 0
    assert ("depths    8, 12.03, 16.05, 20.08, 24.11, 28.14 mm from the first contact (an approach that "
            "starts in contact re-zeroes there: each repeat goes deeper)") in out, out
    assert "steps     approach -> ramp -> return  (x6: 18 steps)" in out, out
    code, out, _ = _check(tmp_path, capsys, ISSUE.format(back=4, repeat=6), "--json")
    info = json.loads(out)
    assert info["depths_from"] == "first contact" and info["depths_mm"][-1] == 28.14
    assert len(info["steps"]) == info["executed_steps"] == 18


def test_repeats_whose_return_leaves_contact_are_accepted_at_the_same_depth(tmp_path, capsys):
    code, out, _ = _check(tmp_path, capsys, ISSUE.format(back=-2, repeat=12))
    assert code == 0
    assert "depths    8 mm in each of 12 repeats" in out, out
    proto = parse_protocol(ISSUE.format(back=-2, repeat=500), "p.yaml")
    check_limits(proto, RigConfig())  # every repeat starts where the second did


def test_the_check_follows_the_zero_from_where_the_slider_is():
    proto = parse_protocol(ISSUE.format(back=4, repeat=3), "p.yaml")
    check_limits(proto, RigConfig(), start_mm=10.0)  # repeat 3 reaches 10 + 10 + 16.06 mm at most
    with pytest.raises(LimitError, match=r"p\.yaml:4: repeat 3 of 3: ramp to 16\.05 mm from the first contact "
                                         r"\(absolute up to 45\.0\d mm\)"):
        check_limits(proto, RigConfig(), start_mm=19.0)


def test_a_force_step_after_a_return_in_contact_is_checked_from_the_new_zero():
    text = ("name: x\nsteps:\n  - approach: {speed_mm_s: 0.5, contact_N: 0.1, max_mm: 5}\n"
            "  - hold_force: {force_N: 2, duration_s: 3, max_mm: 20}\n  - return: {to_mm: 8, speed_mm_s: 5}\n"
            "repeat: 4\n")
    # the force step may push 20 mm in; its return to 8 mm is in contact, the next approach (up,
    # towards its max_mm of 5) re-zeroes there as it starts, and the fourth force step may reach
    # 3 x 8 + 20 mm past the first contact, less the approaches' run-on upwards
    with pytest.raises(LimitError, match=r"p\.yaml:4: repeat 4 of 4: hold_force to 43\.92 mm from the first "
                                         r"contact \(absolute up to 48\.92 mm\)"):
        check_limits(parse_protocol(text, "p.yaml"), RigConfig())
    check_limits(parse_protocol(text.replace("repeat: 4", "repeat: 3"), "p.yaml"), RigConfig())


def test_the_plan_matches_the_simulated_rig_repeat_by_repeat(tmp_path):
    """On the simulated rig each approach re-zeroes about 4 mm deeper than the last; the plan says
    so within a quarter of a millimetre, and the check's worst case is never exceeded."""
    cfg = RigConfig()
    proto = parse_protocol(ISSUE.format(back=4, repeat=4), "p.yaml")
    p = plan(proto, cfg)
    result = run_sim(proto, cfg, tmp_path=tmp_path)
    assert result.outcome == "completed", result.fault
    from rig.recording.logs import read_log

    log = read_log(result.log_path)
    zeros = [e["data"]["zero_mm"] for e in log.events
             if e["kind"] == "step_start" and e["data"]["kind"] == "ramp"]
    measured = [z - zeros[0] + 8 for z in zeros]
    assert len(measured) == 4 and all(3.5 < b - a < 4.5 for a, b in itertools.pairwise(measured))
    np.testing.assert_allclose(p.depths_mm, measured, atol=0.25)
    reach = Reach(cfg)
    worst = []
    for _ in range(proto.repeat):
        for step in proto.steps:
            reach.step(step)
            if step.kind == "ramp":
                worst.append(reach.in_frame(reach.pos)[1])
    assert all(m <= w + 0.05 for m, w in zip(measured, worst, strict=True)), (measured, worst)


def test_every_shipped_protocol_and_config_still_loads():
    cfg = RigConfig()
    for f in sorted(PROTOCOLS.glob("*.yaml")):
        check_limits(load_protocol(f, cfg), cfg)
    for f in sorted((ROOT / "config").glob("*.yaml")):
        parse_config(f.read_text(), str(f))
