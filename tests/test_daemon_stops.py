"""Stops latch in the daemon, requests are checked field by field, and the names a client sends
never pick where a file goes. The daemon runs in this process on a WireSim's Modbus TCP drive and
serial load cell (as in test_stop_anytime), so a test can hold a start in its set-up and send a
stop into that window, deterministically."""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import pytest
from rig.sim.params import SimParams
from rig.sim.server import WireSim

import rig.service.daemon as daemon_module
from rig.cli import main
from rig.errors import RigError
from rig.recording.logs import read_log
from rig.recording.names import file_part, inside
from tests.test_stop_anytime import InProcessDaemon

RAMP = "name: ramp\nsteps:\n  - ramp: {to_mm: 10, speed_mm_s: 5}\n  - return: {speed_mm_s: 10}\n"
SHORT = "name: short\nsteps:\n  - ramp: {to_mm: 1, speed_mm_s: 5}\n  - return: {speed_mm_s: 5}\n"
FIRST = ("name: first look\nsteps:\n  - ramp: {to_mm: 6, speed_mm_s: 3}\n  - hold: {duration_s: 3}\n"
         "  - return: {to_mm: 0, speed_mm_s: 5}\n")


@pytest.fixture
def daemon(tmp_path):
    with WireSim(SimParams(), rtu=False) as sim:
        d = InProcessDaemon(tmp_path, sim)
        try:
            yield d
        finally:
            d.close()


class HeldSetUp:
    """Holds the daemon's limit check (a start's, or a campaign trial's, set-up: after its
    position read, before its trial is handed the devices) until released."""

    def __init__(self, monkeypatch) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()
        original = daemon_module.check_limits

        def held(*args, **kwargs):
            self.entered.set()
            self.release.wait(30)
            return original(*args, **kwargs)

        monkeypatch.setattr(daemon_module, "check_limits", held)


@pytest.fixture
def held(daemon, monkeypatch):
    h = HeldSetUp(monkeypatch)
    yield h
    h.release.set()  # a failed test does not leave the set-up waiting


def _in_thread(fn) -> tuple[threading.Thread, dict]:
    out: dict = {}
    t = threading.Thread(target=lambda: out.update(reply=fn()), name="client")
    t.start()
    return t, out


def _idle(d: InProcessDaemon, timeout_s: float = 30.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st = d.req({"cmd": "status"})
        if st["state"] == "idle":
            return st
        time.sleep(0.05)
    raise AssertionError(f"not idle: {st}")


def _logs(tmp: Path) -> list[Path]:
    return sorted((tmp / "trials").rglob("*.mcap"))


# ------------------------------------------------------------------ 1. a latched stop
@pytest.mark.parametrize("cmd", [{"cmd": "estop"}, {"cmd": "stop", "mode": "abort"}])
def test_a_stop_while_a_start_is_set_up_cancels_it_and_nothing_moves(daemon, held, monkeypatch, tmp_path, cmd):
    """A stop that came while a start read the position and checked the limits was answered
    'no trial was running' (an estop) or 'no trial is running' (a stop), and the start then ran
    its trial in full."""
    sim = daemon.sim
    client, start = _in_thread(lambda: daemon.req({"cmd": "start", "protocol_text": RAMP,
                                                   "protocol_path": "ramp.yaml", "specimen": "pig-1"}))
    assert held.entered.wait(10)
    moves, stops = sim.drive.moves, sim.drive.stops
    reply = daemon.req(cmd)
    # answered while the start is still held in its set-up: the stop does not wait for it
    assert client.is_alive()
    assert reply["ok"], reply
    assert "the start of 'ramp' (specimen pig-1" in reply["message"], reply
    assert "was cancelled: nothing moved" in reply["message"] and "no trial was running" in reply["message"]
    assert reply["acknowledged"] and not reply["trial_running"], reply
    assert sim.drive.stops > stops  # the STOP is on the wire before the answer
    held.release.set()
    client.join(20)
    refused = start["reply"]
    assert not refused["ok"], refused
    who = "an estop" if cmd["cmd"] == "estop" else "a stop (abort)"
    assert refused["error"].startswith(f"not started: {who} from "), refused
    assert "cancelled before anything moved" in refused["error"]
    time.sleep(0.3)  # a trial would have sent its ramp by now
    assert sim.drive.moves == moves and _logs(tmp_path) == []
    st = daemon.req({"cmd": "status"})
    assert st["state"] == "idle" and st["last"] is None, st
    # the latch cancels what was under way when it came, not what comes after it
    monkeypatch.undo()
    _starts_and_runs(daemon)


def _starts_and_runs(d: InProcessDaemon) -> None:
    """A start is taken and its trial runs (its outcome is the machine's business here: on a
    loaded machine an in-process load cell can fall silent past its limit)."""
    r = d.req({"cmd": "start", "protocol_text": SHORT, "protocol_path": "short.yaml"})
    assert r["ok"], r
    last = _idle(d)["last"]
    assert last["log"] == r["log"] and last["samples"] > 0 and read_log(r["log"]).complete, last


def test_a_stop_with_nothing_to_stop_is_refused_and_latches_nothing(daemon):
    """A stop on an idle daemon cuts nothing: refused as before; an idle estop goes to the drive;
    neither holds back the next start."""
    refused = daemon.req({"cmd": "stop"})
    assert not refused["ok"] and refused["error"] == "no trial is running", refused
    stops = daemon.sim.drive.stops
    estop = daemon.req({"cmd": "estop"})
    assert estop["ok"] and estop["message"] == "STOP acknowledged by the drive (no trial was running)", estop
    assert daemon.sim.drive.stops > stops
    _starts_and_runs(daemon)


def _journal(path: str) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines()]


@pytest.mark.parametrize("cmd", [{"cmd": "estop"}, {"cmd": "stop", "mode": "abort"}])
def test_a_stop_while_a_campaign_sets_up_its_trial_cancels_it(daemon, held, tmp_path, cmd):
    """A stop that came while the campaign set up its next trial was answered 'no trial was
    running' / 'the campaign ends before its next trial', and 50 ms later the trial started and
    ran to completion."""
    sim = daemon.sim
    r = daemon.req({"cmd": "start", "specimen": "liver-9", "protocol_text": FIRST,
                    "protocol_path": "first.yaml", "characterize": {"max_trials": 2, "rest_s": 1.0}})
    assert r["ok"], r
    assert held.entered.wait(20)
    moves, stops = sim.drive.moves, sim.drive.stops
    reply = daemon.req(cmd)
    assert reply["ok"], reply
    assert "the campaign's trial 1 ('first look', specimen liver-9) was cancelled: nothing moved" \
        in reply["message"], reply
    assert "the campaign ends before its next trial" in reply["message"]
    assert reply["campaign_ends"] and not reply["trial_running"] and sim.drive.stops > stops
    held.release.set()
    st = _idle(daemon)
    camp = st["campaign"]
    assert camp["status"] == "stopped" and "cancelled" in camp["reason"], camp
    assert sim.drive.moves == moves and _logs(tmp_path) == []
    events = _journal(camp["journal"])
    ran = [e for e in events if e["event"] == "ran"]
    assert [e["outcome"] for e in ran] == ["cancelled"], ran
    assert "arrived while it was being set up" in ran[0]["fault"]
    assert events[-1]["event"] == "end" and events[-1]["status"] == "stopped"


# ------------------------------------------------------------------ 2. fields checked
BAD_FIELDS = [
    ({"cmd": "watch", "rate_Hz": "abc"}, 'watch "rate_Hz" must be a number > 0'),
    ({"cmd": "watch", "rate_Hz": 0}, 'watch "rate_Hz" must be a number > 0'),
    ({"cmd": "watch", "rate_Hz": -2}, 'watch "rate_Hz" must be a number > 0'),
    ({"cmd": "watch", "rate_Hz": True}, "are sent), not true"),
    ({"cmd": "watch", "rate_Hz": [10]}, "are sent), not [10]"),
    ({"cmd": "stop", "mode": 5}, 'must be "abort" (stop, then return) or "hold" (stop and stay), not 5'),
    ({"cmd": "stop", "mode": ["hold"]}, 'stop "mode" must be "abort"'),
    ({"cmd": "start", "protocol_text": SHORT, "specimen": {"a": 1}}, '"specimen" must be a string, not {"a"'),
    ({"cmd": "start", "protocol_text": SHORT, "specimen": "pig\u00007"}, '"specimen" must be printable text'),
    ({"cmd": "start", "protocol_text": SHORT, "operator": 7}, '"operator" must be a string, not 7'),
    ({"cmd": "start", "protocol_text": SHORT, "operator": "ann\nbob"}, '"operator" must be printable text'),
    ({"cmd": "start", "protocol_text": SHORT, "protocol_path": ["p"]}, '"protocol_path" must be a string'),
    ({"cmd": "start", "protocol_text": SHORT, "notes": 3}, '"notes" must be a string, not 3'),
    ({"cmd": "start", "characterize": {"max_trials": 2.5}}, 'must be a whole number >= 1, not 2.5'),
    ({"cmd": "start", "characterize": {"budget_min": True}}, 'characterize "budget_min" must be a number >= 0'),
    ({"cmd": "start", "characterize": {"rest_s": "soon"}}, 'characterize "rest_s" must be a number >= 0'),
    ({"cmd": "start", "characterize": {"model": 3}}, '"model" must be a string, not 3'),
]
BAD_LINES = [
    (b'{"cmd": "ping", "x": NaN}\n', "not JSON: NaN is not a JSON number"),
    (b'{"cmd": "ping", "x": -Infinity}\n', "not JSON: -Infinity is not a JSON number"),
    (b"[" * 30000 + b"\n", "nested too deeply"),
    (b'{"cmd": "ping", "n": ' + b"9" * 5000 + b"}\n", "not JSON: Exceeds the limit"),
]


def test_every_request_field_is_checked_and_the_connection_carries_on(daemon, monkeypatch):
    """`{"cmd": "watch", "rate_Hz": "abc"}` killed its connection's thread with a traceback and
    no reply."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(10)
        s.connect(str(daemon.sock))
        f = s.makefile("rb")
        raw = [(json.dumps(req).encode() + b"\n", fragment) for req, fragment in BAD_FIELDS] + BAD_LINES
        for line, fragment in raw:
            s.sendall(line)
            answer = f.readline()
            assert answer, f"no reply to {line[:80]!r}: the connection closed"
            reply = json.loads(answer)
            assert reply["ok"] is False and fragment in reply["error"], (fragment, reply)
        # a handler that fails in a way nobody foresaw: an answer, and the connection carries on
        monkeypatch.setattr(daemon.daemon, "cmd_ping", lambda req, user, received: 1 / 0)
        s.sendall(b'{"cmd": "ping"}\n')
        reply = json.loads(f.readline())
        assert not reply["ok"] and "could not carry out 'ping': ZeroDivisionError" in reply["error"], reply
        monkeypatch.undo()
        s.sendall(b'{"cmd": "ping"}\n')
        assert json.loads(f.readline())["ok"] is True
    assert daemon.req({"cmd": "status"})["state"] == "idle"  # nothing was started by a bad request


# ------------------------------------------------------------------ 3. the CLI says what the daemon said
def test_rig_stop_prints_what_the_daemon_answered(monkeypatch, capsys):
    """`rig stop` printed 'stopping, then returning to the start position' whatever the daemon
    answered, e.g. when it ended a campaign between trials and nothing was returning anywhere."""
    said = ("STOP acknowledged by the drive (no trial was running); the campaign ends before its next "
            "trial (the probe stays where it is)")
    sent = []

    def answer(path, obj, timeout_s=10.0):
        sent.append(obj)
        return {"ok": True, "mode": obj["mode"], "message": said}

    monkeypatch.setattr("rig.service.client.request", answer)
    assert main(["stop", "--socket", "/nonexistent/rigd.sock"]) == 0
    assert capsys.readouterr().out == said + "\n"
    assert sent == [{"cmd": "stop", "mode": "abort"}]


def test_rig_stop_on_a_running_trial_says_what_the_trial_does(daemon, capsys):
    r = daemon.req({"cmd": "start", "protocol_text": RAMP, "protocol_path": "ramp.yaml"})
    assert r["ok"], r
    deadline = time.monotonic() + 10
    while daemon.sim.rig.slider.position_mm < 1.0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert main(["stop", "--hold", "--socket", str(daemon.sock)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("stopping and staying in place: STOP sent in ") and "acknowledged by the drive" in out
    assert _idle(daemon)["last"]["outcome"] == "stopped"


# ------------------------------------------------------------------ 4. names are not paths
@pytest.mark.parametrize("name, part", [
    ("pig-07", "pig-07"), ("pig 07", "pig-07"), ("/some/dir/x", "some-dir-x"), ("..", "specimen"),
    ("../../etc/passwd", "etc-passwd"), (".hidden", "hidden"), ("a\x00b", "a-b"), ("", "specimen"),
    ("-rf", "rf"), ("a/./b", "a-b"), ("C:\\x", "C-x"), ("léa_2", "léa_2"), ("x" * 90, "x" * 40),
])
def test_a_name_becomes_one_safe_file_name_part(name, part):
    got = file_part(name, default="specimen")
    assert got == part
    assert "/" not in got and "\x00" not in got and not got.startswith((".", "-"))


def test_inside_refuses_a_path_out_of_the_folder(tmp_path):
    assert inside(tmp_path, tmp_path / "a" / "b.mcap") == tmp_path / "a" / "b.mcap"
    for bad in (tmp_path / ".." / "x.mcap", Path("/etc/x.mcap")):
        with pytest.raises(RigError, match="outside the log folder"):
            inside(tmp_path, bad)


def test_a_campaigns_specimen_name_cannot_put_its_files_outside_the_log_folder(daemon, tmp_path):
    """`rig start --characterize --specimen /some/dir/x` made the daemon write
    /some/dir/x-trial1.mcap, outside its log folder, and `rig logs` did not list it."""
    elsewhere = tmp_path / "elsewhere"
    specimen = f"{elsewhere}/x"
    r = daemon.req({"cmd": "start", "specimen": specimen, "protocol_text": FIRST, "protocol_path": "first.yaml",
                    "characterize": {"max_trials": 1}})
    assert r["ok"], r
    stem = file_part(specimen, default="specimen")
    out = tmp_path / "trials" / f"characterize-{stem}"
    assert r["out"] == str(out)
    assert any(f"specimen {specimen!r} is not a file name" in w for w in r["warnings"]), r
    deadline = time.monotonic() + 20
    while daemon.req({"cmd": "status"})["state"] != "running" and time.monotonic() < deadline:
        time.sleep(0.02)
    assert daemon.req({"cmd": "estop"})["ok"]  # no need to run it out: its log is open by now
    st = _idle(daemon)
    assert not elsewhere.exists()
    files = sorted(p.relative_to(tmp_path / "trials") for p in (tmp_path / "trials").rglob("*") if p.is_file())
    assert [p.parent for p in files] == [Path(out.name)] * 2, files
    log = next(p for p in _logs(tmp_path))
    assert log.name == f"{stem}-trial1.mcap" and read_log(log).trial["specimen"] == specimen
    assert st["campaign"]["specimen"] == specimen
    listed = daemon.req({"cmd": "logs"})["trials"]
    assert [(e["path"], e["campaign"]) for e in listed] == [(str(log), out.name)]


# ------------------------------------------------------------------ 5. after an estop, the probe in the tissue
def _estop_in_contact(d: InProcessDaemon, depth_past_mm: float = 6.0) -> dict:
    r = d.req({"cmd": "start", "protocol_text": RAMP, "protocol_path": "ramp.yaml"})
    assert r["ok"], r
    deadline = time.monotonic() + 10
    while d.sim.rig.slider.position_mm < depth_past_mm and time.monotonic() < deadline:
        time.sleep(0.01)
    assert d.req({"cmd": "estop"})["ok"]
    st = _idle(d)
    assert st["last"]["outcome"] == "estopped"
    return st


def test_a_start_after_an_estop_left_the_probe_in_contact_is_refused_until_returned_or_confirmed(
        daemon, capsys):
    """The estop leaves the probe in the tissue (the simulated surface is at about 4.3 mm): the next
    `rig start` says so, with the depth, and refuses; `--from-contact` confirms and runs from there;
    `rig return` raises the probe to where the cut-short trial started, and a start then runs as usual."""
    sock = ["--socket", str(daemon.sock)]
    st = _estop_in_contact(daemon)
    left = st["probe_in_contact"]
    assert left["depth_mm"] > 1.0 and left["force_N"] > 0
    assert left["return_to_mm"] == pytest.approx(0.0, abs=0.05)
    ramp, short = daemon.sock.parent / "ramp.yaml", daemon.sock.parent / "short.yaml"
    ramp.write_text(RAMP)
    short.write_text(SHORT)
    logs_before = len(_logs(daemon.sock.parent))
    assert main(["start", str(ramp), *sock]) == 2
    err = capsys.readouterr().err
    assert "not started: the probe is in contact, " in err
    assert f"{left['depth_mm']:.2f} mm into the specimen" in err and "where the estop of trial 'ramp'" in err
    assert "`rig return`" in err and "--from-contact" in err
    assert main(["status", *sock]) == 0
    assert f"CONTACT   the probe is {left['depth_mm']:.2f} mm into the specimen" in capsys.readouterr().out
    assert len(_logs(daemon.sock.parent)) == logs_before  # refused: no trial, no log
    campaign = daemon.req({"cmd": "start", "specimen": "pig", "characterize": {"max_trials": 1}})
    assert not campaign["ok"] and campaign["error"].startswith("not started: the probe is in contact, ")
    assert daemon.sim.rig.slider.position_mm == pytest.approx(left["position_mm"], abs=0.05)  # nothing moved
    # confirmed: it runs from there, says so, and ends where it started, still in contact
    assert main(["start", str(short), "--from-contact", *sock]) == 0
    assert "starting in contact, as confirmed (--from-contact): the probe is " in capsys.readouterr().err
    st = _idle(daemon)
    assert st["last"]["outcome"] == "completed" and st["probe_in_contact"]["surface_mm"] == left["surface_mm"]
    assert main(["start", str(ramp), *sock]) == 2
    assert "the probe is in contact" in capsys.readouterr().err
    # returned: out of the specimen, and a start runs as usual
    assert main(["return", *sock]) == 0
    assert capsys.readouterr().out.startswith("returned the probe to 0.000 mm (from ")
    assert daemon.sim.rig.slider.position_mm < left["surface_mm"]
    assert "probe_in_contact" not in _idle(daemon)
    assert main(["start", str(short), *sock]) == 0
    assert "in contact" not in capsys.readouterr().err
    assert _idle(daemon)["last"]["outcome"] == "completed"


def test_a_trial_stopped_and_returned_leaves_nothing_to_return(daemon):
    r = daemon.req({"cmd": "start", "protocol_text": RAMP, "protocol_path": "ramp.yaml"})
    assert r["ok"], r
    deadline = time.monotonic() + 10
    while daemon.sim.rig.slider.position_mm < 6.0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert daemon.req({"cmd": "stop", "mode": "abort"})["ok"]
    assert "probe_in_contact" not in _idle(daemon)
    r = daemon.req({"cmd": "return"})
    assert not r["ok"] and "no trial has left the probe in contact" in r["error"]
