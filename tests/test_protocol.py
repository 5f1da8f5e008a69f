"""Protocol files: the shipped ones load; bad ones give one-line errors naming file and line."""

from __future__ import annotations

import subprocess
import sys

import pytest

from rig.cli import main
from rig.errors import LimitError, SpecError
from rig.specs.config import RigConfig
from rig.specs.protocol import Approach, Hold, Ramp, Return, load_protocol, parse_protocol, plan
from tests.conftest import PROTOCOLS


@pytest.mark.parametrize("speed", ["0.75", "1.5", "3"])
def test_paper_protocols(speed):
    p = load_protocol(PROTOCOLS / f"paper-{speed}mm_s.yaml", RigConfig())
    assert [s.kind for s in p.steps] == ["ramp", "hold", "return"]
    ramp, hold, ret = p.steps
    assert ramp.to_mm == 30 and ramp.speed_mm_s == float(speed)
    assert hold.duration_s == 60
    assert ret.to_mm == 0


def test_demo_is_short():
    cfg = RigConfig()
    assert plan(load_protocol(PROTOCOLS / "demo.yaml", cfg), cfg).duration_s < 15


def test_every_shipped_protocol_is_valid():
    cfg = RigConfig()
    files = sorted(PROTOCOLS.glob("*.yaml"))
    assert len(files) >= 5
    for f in files:
        load_protocol(f, cfg)


def test_step_kinds_and_repeat():
    p = parse_protocol(
        "name: x\nsteps:\n  - approach: {speed_mm_s: 0.5, contact_N: 0.1, max_mm: 5}\n"
        "  - ramp: {to_mm: 3, speed_mm_s: 1}\n  - hold: {until_rate_N_s: 0.01, max_s: 20}\n"
        "  - return: {speed_mm_s: 2}\nrepeat: 2\nrest_s: 4\n")
    assert isinstance(p.steps[0], Approach) and isinstance(p.steps[1], Ramp)
    assert isinstance(p.steps[2], Hold) and p.steps[2].until_rate_N_s == 0.01
    assert isinstance(p.steps[3], Return) and p.steps[3].to_mm is None
    kinds = [s.kind for _, s in p.run_steps()]
    assert kinds == ["approach", "ramp", "hold", "return", "hold", "approach", "ramp", "hold", "return"]


BAD = {
    # kind: (text, expected line, fragment of the message)
    "yaml syntax": ("name: x\nsteps:\n  - ramp: {to_mm: 30, speed_mm_s: 1\n", 4, "YAML syntax error"),
    "unknown step": ("name: x\nsteps:\n  - push: {to_mm: 3}\n", 3, "unknown key 'push'"),
    "misspelt key": ("name: x\nsteps:\n  - ramp: {to_mm: 3, sped_mm_s: 1}\n", 3,
                     "did you mean 'speed_mm_s'"),
    "missing field": ("name: x\nsteps:\n  - ramp: {to_mm: 3}\n", 3, "missing required field 'speed_mm_s'"),
    "wrong type": ("name: x\nsteps:\n  - ramp: {to_mm: deep, speed_mm_s: 1}\n", 3,
                   "expected a number, got text 'deep'"),
    "negative speed": ("name: x\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: -1}\n", 3,
                       "must be greater than 0"),
    "beyond travel": ("name: x\nsteps:\n  - ramp: {to_mm: 80, speed_mm_s: 1}\n", 3,
                      "outside the travel window"),
    "looser force limit": ("name: x\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: 1}\n"
                           "limits: {max_force_N: 50}\n", 4, "looser than the rig's"),
    "too fast": ("name: x\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: 25}\n", 3, "exceeds the limit"),
    "missing name": ("steps:\n  - ramp: {to_mm: 3, speed_mm_s: 1}\n", 1, "missing required field 'name'"),
    "empty steps": ("name: x\nsteps: []\n", 2, "non-empty list"),
    "hold without time": ("name: x\nsteps:\n  - hold: {until_rate_N_s: 0.1}\n", 3, "needs 'max_s'"),
    "duplicate key": ("name: x\nname: y\nsteps:\n  - hold: {duration_s: 1}\n", 2, "appears twice"),
}


@pytest.mark.parametrize("kind", sorted(BAD))
def test_bad_protocol_one_line_error(kind, tmp_path, capsys):
    text, line, fragment = BAD[kind]
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    code = main(["check", str(path)])
    err = capsys.readouterr().err.strip()
    assert code != 0
    assert len(err.splitlines()) == 1, err
    assert f"{path}:{line}" in err, err
    assert fragment in err, err
    assert "Traceback" not in err


def test_bad_protocol_refused_by_run_before_anything_moves(tmp_path):
    """The real command line: one line on stderr, exit 2, and no log written."""
    path = tmp_path / "bad.yaml"
    path.write_text(BAD["beyond travel"][0])
    out = tmp_path / "logs"
    proc = subprocess.run([sys.executable, "-m", "rig.cli", "run", str(path), "--speed", "0",
                           "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert "bad.yaml:3" in proc.stderr
    assert not out.exists() or not list(out.iterdir())


def test_limit_and_spec_errors_are_distinct():
    with pytest.raises(SpecError):
        parse_protocol("name: x\nsteps: 3\n")
    p = parse_protocol("name: x\nsteps:\n  - ramp: {to_mm: 60, speed_mm_s: 1}\n")
    from rig.specs.protocol import check_limits

    with pytest.raises(LimitError):
        check_limits(p, RigConfig())


def test_protocol_limits_only_tighten():
    p = parse_protocol("name: x\nsteps:\n  - ramp: {to_mm: 3, speed_mm_s: 1}\n"
                       "limits: {max_force_N: 5, max_speed_mm_s: 2, travel_mm: [0, 10]}\n")
    eff = p.effective_limits(RigConfig().limits)
    assert eff.max_force_N == 5 and eff.max_speed_mm_s == 2 and eff.travel_mm == (0, 10)


def test_approach_travel_is_checked_relative_to_contact():
    # contact may be found as far as 30 mm, then a 20 mm ramp would reach 50 mm > 45 mm travel
    p = parse_protocol("name: x\nsteps:\n  - approach: {speed_mm_s: 1, contact_N: 0.1, max_mm: 30}\n"
                       "  - ramp: {to_mm: 20, speed_mm_s: 1}\n")
    from rig.specs.protocol import check_limits

    with pytest.raises(LimitError, match="outside the travel"):
        check_limits(p, RigConfig())
