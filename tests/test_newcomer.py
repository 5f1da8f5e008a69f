"""A newcomer's path, end to end: in a fresh virtual environment, the README's first command (install
with the AFM extra, run the demo trial on the simulated rig), then every command of its tour, each
output compared with what the README shows (as the documentation's examples are compared:
docs_build/console.py; the trial's tick counts aside, which a busy machine changes). On the real
clock (two 12 s trials): a module of CLOCK_MODULES, so it runs once, alone on the machine, in the
default suite; under a minute (the install from the local wheels about 15 s).

The project is copied (every file of the working tree git does not ignore) beside a link to the
shared measurements, so the README's paths (`protocols/`, `../shared/`, `trials/`) read as they
do in a checkout and nothing is written into the tree itself."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.pages import README, ROOT, console

SHARED = ROOT.parent / "shared"


def _first_command() -> str:
    text = README.read_text()
    block = re.search(r"^```sh\n(.*?)^```", text, re.S | re.M).group(1)
    return block.splitlines()[0]


def _copy_tree(dst: Path) -> None:
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT,
                            capture_output=True, check=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        src = ROOT / name
        if src.is_file():
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / name)


@pytest.mark.skipif(shutil.which("git") is None, reason="copying the working tree needs git")
def test_the_readme_s_first_command_then_its_tour_in_a_fresh_virtual_environment(tmp_path):
    if not SHARED.is_dir():
        pytest.skip("the tour reads ../shared/ (the real measurements), which is not beside the project")
    project = tmp_path / "indentation-rig"
    _copy_tree(project)
    (tmp_path / "shared").symlink_to(SHARED)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(PATH=os.pathsep.join([str(venv / "bin"), env.get("PATH", "")]), VIRTUAL_ENV=str(venv),
               COLUMNS="100", NO_COLOR="1", PYTHONUNBUFFERED="1")

    def sh(command: str, timeout: float) -> tuple[int, list[str]]:
        """The command's exit status and its output (stdout and stderr as a terminal shows them)."""
        done = subprocess.run(["bash", "-c", f"{{ {command}\n}} 2>&1"], cwd=project, env=env,
                              capture_output=True, text=True, timeout=timeout)
        return done.returncode, done.stdout.rstrip("\n").split("\n")

    first = _first_command()
    assert first.startswith("python3 -m pip install '.[afm]'"), first
    status, lines = sh(first, timeout=600)
    assert status == 0, "\n".join(lines[-30:])
    assert re.fullmatch(r"log: trials/\S+_specimen_demo-\S+\.mcap", lines[-1]), lines[-5:]
    # the environment's own rig, not the suite's
    status, where = sh("command -v rig; python3 -c 'import afmformats, rig; print(rig.__file__)'", timeout=60)
    assert status == 0 and where[0] == str(venv / "bin" / "rig"), where
    con = console()
    (tour,) = [ex for ex in con.examples(README)]
    assert len(tour.commands) >= 3
    for command, shown in tour.commands:
        status, lines = sh(command, timeout=300)
        # how many ticks a busy machine made late is the clock tests' concern (test_pages_clock holds
        # the README to its figures with the machine to itself); here, that the path runs
        shown = ["duration   ... s, ... samples, ... late, ... missed" if line.startswith("duration ") else line
                 for line in shown]
        problem = con.mismatch(shown, lines)
        assert status == 0 and problem is None, (f"README tour: `{command}` (exit status {status}): {problem}\n"
                                                 + "\n".join(lines))
    assert (project / "demo.png").stat().st_size > 10_000
