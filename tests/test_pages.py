"""Every console example of the documentation runs and prints what its page shows (those on the
real clock are in test_pages_clock.py); and the comparison itself: a word changed fails it."""

from __future__ import annotations

import pytest

from tests.pages import DOCS, GENERATED, README, ROOT, cases, check, console


@pytest.mark.parametrize("example", cases(False))
def test_the_page_shows_what_the_command_prints(example, tmp_path):
    check(example, tmp_path)


# Code blocks shown and not run: commands for the machine itself, which the suite cannot give on
# the machine it runs on (installing the package, systemd). Each says where it is exercised.
SHOWN_NOT_RUN = {
    ("README.md", "python3 -m pip install '.[afm]' && python3 -m rig run protocols/demo.yaml"):
        "the set-up commands: .ci/run runs the second from a clean checkout; the first is the "
        "demo trial that tutorials/first-trial.md runs",
    ("daemon.md", "sudo cp config/rigd.service /etc/systemd/system/"):
        "installing the systemd unit needs root and systemd (tests/test_daemon.py checks the "
        "daemon's readiness and watchdog notifications on a socket of its own)",
    ("dask-cluster.md", "python3 -m pip install '.[cluster,afm]'"): "installing the extras",
    ("web.md", "python3 -m pip install '.[web]'"): "installing the extra (tests/test_web.py runs rig web)",
    ("calibrate.md", "rig calibrate 200 500 1000 --config rig.yaml"):
        "interactive: it waits for the technician to place each mass (tests/test_calibrate.py runs it on "
        "the simulated rig, scripted)",
}


def test_every_code_block_is_run_or_shown_for_a_reason():
    con = console()
    unrun = {(page.name, block.text[0] if block.text else ""): f"{page.relative_to(ROOT)}:{block.fence}"
             for page in [README, *sorted(DOCS.rglob("*.md"))] if GENERATED not in page.parents
             for block in con.unrun(page)}
    not_allowed = {where: key for key, where in unrun.items() if key not in SHOWN_NOT_RUN}
    assert not not_allowed, ("code blocks no test runs (make them console blocks, name the file a "
                             f"command uses, or show output as text): {not_allowed}")
    assert set(SHOWN_NOT_RUN) <= set(unrun), "SHOWN_NOT_RUN names a block that is no longer there"


def test_a_python_block_runs_and_its_printed_output_is_compared(tmp_path):
    con = console()
    page = tmp_path / "page.md"
    page.write_text("Some prose.\n\n```python\nprint(6 * 7)\n```\n\nIt prints:\n\n```text\n42\n```\n")
    (example,) = con.examples(page)
    _, shown = example.commands[0]
    assert shown == ["42"]
    ran = con.run(example, ROOT, tmp_path / "run")
    assert ran[0][1] == 0 and con.mismatch(shown, ran[0][2]) is None
    assert con.mismatch(["45"], ran[0][2]) is not None


def test_one_word_changed_on_a_page_fails_it(tmp_path):
    con = console()
    example = next(ex for p in cases(False) for ex in p.values
                   if ex.commands and ex.commands[0][0].startswith("rig check protocols/paper"))
    command, shown = example.commands[0]
    assert con.mismatch(shown, con.run(example, ROOT, tmp_path)[0][2]) is None
    changed = [line.replace("relaxes", "rests") for line in shown]
    assert changed != shown
    example.commands[0] = (command, changed)
    problem = con.mismatch(changed, con.run(example, ROOT, tmp_path / "again")[0][2])
    assert problem is not None and "rests" in problem


@pytest.mark.parametrize("shown, got, same", [
    ("peak force 5.882 N", "peak force 5.882 N", True),
    ("peak force 5.882 N", "peak force 5.90 N", True),  # within 1 %
    ("peak force 5.882 N", "peak force 6.1 N", False),
    ("peak force 5.882 N", "peak load 5.882 N", False),  # a word
    ("trial completed: 1129 samples in 11.3 s", "trial completed: 1129 samples in 19.8 s", True),  # a time
    ("curves at 83/s", "curves at 41/s", True),  # a rate of the machine
    ("reading 1.09 s (23 %), analysing 3.61 s (77 %)", "reading 0.871 s (25 %), analysing 2.68 s (75 %)", True),
    ("error falls by 86.7 %", "error falls by 80.1 %", False),  # a percentage that is not the machine's
    ("log: trials/20261122-033543_pig-07_demo.mcap", "log: trials/20270101-120000_pig-07_demo.mcap", True),
    ("a   table   row 1.5", "a table row 1.5", True),  # columns shift
    ("force ... N (untared)", "force -0.151 N (untared)", True),
    ("(0 late, 0 missed ticks)", "(2 late, 0 missed ticks)", True),  # the machine's timing
    ("(0 late, 0 missed ticks)", "(0 late, 0 skipped ticks)", False),
    ("max diff 0.00e+00 N/m", "max diff 0.00e+00 N/m", True),
])
def test_a_line_is_compared_in_its_words_and_to_a_percent_in_its_numbers(shown, got, same):
    assert console().line_matches(shown, got) is same


def test_an_elided_run_of_lines_takes_any_lines():
    con = console()
    assert con.mismatch(["a", "...", "d"], ["a", "b", "c", "d"]) is None
    assert con.mismatch(["a", "...", "d"], ["a", "d"]) is None
    assert con.mismatch(["a", "d"], ["a", "b", "d"]) is not None
    assert "'e'" in con.mismatch(["a", "...", "e"], ["a", "b", "d"])
