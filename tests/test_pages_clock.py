"""The documentation's console examples that reach the rig on the real clock (a trial at speed 1,
the devices on the wire, the daemon): run with the machine to themselves, as the other clock
tests are, and compared with what their pages show."""

from __future__ import annotations

import pytest

from tests.pages import cases, check


@pytest.mark.parametrize("example", cases(True))
def test_the_page_shows_what_the_command_prints(example, tmp_path):
    check(example, tmp_path)
