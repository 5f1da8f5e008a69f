"""The documentation site: it builds without a warning, and its reference pages follow the code
(an option, a config field, a step's field or a log field added in the code is on the site at
the next build, with no page edited by hand)."""

from __future__ import annotations

import dataclasses
import importlib.util
import subprocess
import sys
from dataclasses import dataclass, field

import pytest

import rig.specs.config as config
from tests.pages import DOCS, README, ROOT, docs_module


def _reference():
    return docs_module("reference")


def test_the_site_builds_without_a_warning(tmp_path):
    for name in ("sphinx", "myst_parser", "furo"):
        if importlib.util.find_spec(name) is None:
            pytest.skip(f"{name} is not installed: the docs extra builds the site (pip install '.[docs]')")
    done = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
                           str(DOCS), str(tmp_path / "html")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    for page in ("index", "reference/cli", "reference/config", "reference/protocol", "reference/log",
                 "reference/effects"):
        assert (tmp_path / "html" / f"{page}.html").is_file(), page
    cli = (tmp_path / "html" / "reference" / "cli.html").read_text()
    assert "--speed" in cli and "rig analyze" in cli
    # the figures the tool draws at the build, and the API from the docstrings
    for figure in ("demo-trial.png", "map-E.png"):
        assert (tmp_path / "html" / "_images" / figure).stat().st_size > 10_000, figure
    assert "analyze_curves" in (tmp_path / "html" / "api.html").read_text()


def test_an_option_added_to_the_parser_is_on_the_site(monkeypatch):
    import rig.cli

    reference = _reference()
    built = rig.cli.build_parser

    def with_an_option():
        parser = built()
        sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
        sub.choices["run"].add_argument("--humidity-percent", type=float, default=40.0,
                                        help="the room's humidity, recorded in the log")
        return parser

    before = reference.cli_page()
    assert "--humidity-percent" not in before
    monkeypatch.setattr(rig.cli, "build_parser", with_an_option)
    after = reference.cli_page()
    row = next(line for line in after.splitlines() if line.startswith("| `--humidity-percent`"))
    assert "the room's humidity, recorded in the log" in row and "`40.0`" in row


@dataclass
class _WithHumidity(config.RecorderConfig):
    # The room's humidity while the rig runs, written into every log.
    humidity_percent: float = field(default=40.0, metadata={"ge": 0, "le": 100})


@dataclass
class _RigWithHumidity(config.RigConfig):
    recorder: _WithHumidity = field(default_factory=_WithHumidity)


def test_a_config_field_added_in_the_code_is_on_the_site(monkeypatch):
    reference = _reference()

    assert "humidity_percent" not in reference.config_page()
    monkeypatch.setattr(config, "RigConfig", _RigWithHumidity)
    page = reference.config_page()
    section = page[page.index("## `recorder:`"):]
    row = next(line for line in section.splitlines() if "humidity_percent" in line)
    assert "`40.0`" in row and ">= 0, <= 100" in row and "The room's humidity while the rig runs" in row


def test_every_field_of_the_schemas_is_on_the_site():
    """Nothing of the config, the protocol's steps or the log's messages is left off its page."""
    import typing

    from rig.recording.messages import MESSAGES
    from rig.specs import protocol
    from rig.specs.config import RigConfig

    reference = _reference()
    config_page, protocol_page = reference.config_page(), reference.protocol_page()
    log_page = reference.log_page()

    def leaves(cls):
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            tp = hints[f.name]
            inner = [a for a in typing.get_args(tp) if dataclasses.is_dataclass(a)] or [tp]
            if dataclasses.is_dataclass(inner[0]):
                yield from leaves(inner[0])
            elif f.repr:
                yield f.name

    assert [n for n in leaves(RigConfig) if f"| `{n}` |" not in config_page] == []
    for step in typing.get_args(protocol.Step):
        names = [f.name for f in dataclasses.fields(step) if f.name not in ("line", "kind")]
        assert [n for n in names if f"| `{n}` |" not in protocol_page] == [], step.__name__
    for message in MESSAGES:
        assert message.topic in log_page
        assert [f.name for f in message.fields if f"| `{f.name}` |" not in log_page] == [], message.topic


def test_the_readme_is_short_starts_with_the_two_commands_and_its_links_resolve():
    import re

    text = README.read_text()
    lines = text.splitlines()
    assert len(lines) < 200, f"the README has {len(lines)} lines: what it says in more belongs on the site"
    # its first code block is the two set-up commands (.ci/run runs the second)
    first = text.index("```")
    assert text[first:].startswith("```sh\n")
    block = text[first + len("```sh\n"):text.index("```", first + 3)].strip().splitlines()
    assert block[0].startswith("python3 -m pip install '.[afm]' && python3 -m rig run ")
    assert block[1] == "python3 -m pip install '.[test]' && python3 -m pytest -n 2 --dist loadgroup"
    # every link into the project names a file that is there
    targets = [t.split("#")[0] for t in re.findall(r"\]\(([^)\s]+)\)", text) if "://" not in t]
    assert targets
    missing = [t for t in targets if not (ROOT / t).exists()]
    assert not missing, f"the README links to files that are not there: {missing}"
