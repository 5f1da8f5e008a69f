"""The documentation's console examples as test cases (tests/test_pages.py and
tests/test_pages_clock.py run them; docs_build/console.py says how output is compared)."""

from __future__ import annotations

import functools
import importlib.util
import re
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
GENERATED = DOCS / "reference"  # written by the build from the code; no examples to run
README = ROOT / "README.md"  # its tour is run as the pages' examples are


@functools.cache
def docs_module(name: str):
    """A module of docs_build/ (the site's build tools, beside the docs, not part of the package)."""
    spec = importlib.util.spec_from_file_location(f"docs_{name}", ROOT / "docs_build" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def console():
    return docs_module("console")


# commands that reach the rig on the real clock (a trial at speed 1, the devices on the wire, the
# daemon): their pages' blocks run with the machine to themselves, as the other clock tests do
_CLOCK = re.compile(r"^rig (run|characterize|position|move|home|tare|reset-alarm|probe|daemon|start|stop|"
                    r"estop|status|watch|sim|bench)(?=\s|$)")


def on_the_clock(example) -> bool:
    return any(_CLOCK.match(c) and "--speed 0" not in c for c, _ in example.commands)


def cases(clock: bool) -> list:
    con = console()
    out = []
    for page in [README, *sorted(DOCS.rglob("*.md"))]:
        if GENERATED in page.parents:
            continue
        for ex in con.examples(page):
            if on_the_clock(ex) == clock:
                name = page.relative_to(DOCS) if DOCS in page.parents else page.name
                out.append(pytest.param(ex, id=f"{name}:{ex.line}"))
    return out


# programs a page uses that the project does not install, with the Debian package that has them
PROGRAMS = {"socat": "socat"}


def check(example, tmp_path: Path) -> None:
    con = console()
    if any("../shared/" in c for c, _ in example.commands) and not (ROOT.parent / "shared").is_dir():
        pytest.skip("the page reads ../shared/ (the real measurements), which is not beside the project")
    for program, package in PROGRAMS.items():
        if any(re.search(rf"\b{program}\b", c) for c, _ in example.commands) and shutil.which(program) is None:
            pytest.skip(f"the page runs {program}, which is not installed (.ci/run installs it: "
                        f"apt-get install {package})")
    results = con.run(example, ROOT, tmp_path)
    where = f"{example.page.relative_to(ROOT)}, the block at line {example.line}"
    for (command, shown), (_, status, lines) in zip(example.commands, results, strict=True):
        problem = con.mismatch(shown, lines)
        assert problem is None, (f"{where}: `{command}` (exit status {status}): {problem}\n"
                                 f"its output:\n" + "\n".join(lines))
        if status != 0:
            assert any("error" in s or "fault" in s for s in shown), (
                f"{where}: `{command}` failed (exit status {status}) where the page shows no error or fault:\n"
                + "\n".join(lines))
