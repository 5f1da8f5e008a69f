"""The hidden-effect cases of tests/test_realdata_explain.py: four effects hidden in each of the
polymer-gel and brain records (each record's `--auto` model takes a minute, each explain up to one
more): `python -m pytest tests/bench/test_bench_realdata_explain.py`."""

from __future__ import annotations

import functools

import pytest

from tests.test_realdata_explain import SIZES, check_named_first, explain_cleanly, pytestmark  # noqa: F401

# friction -14.4, drift -13.9, offset -13.1 in dBIC: look-alikes the 7 s brain record cannot rank
TIE = pytest.mark.xfail(strict=True, reason="a hidden drift in the brain record ranks second, behind friction")


# the records do not say where their surface is, so their zero is fitted with their contact point:
# an offset present from the first sample is that zero (tests/test_realdata_explain.py shows it)
ZERO = pytest.mark.xfail(strict=True, reason="an offset from the first sample is the record's fitted zero")


def _case(record: str, effect: str):
    marks = [TIE] if (record, effect) == ("brain-creep.jpk-force", "drift") else []
    marks += [ZERO] if effect == "offset" else []
    return pytest.param(record, effect, marks=marks, id=f"{record.split('.')[0]}-{effect}")


CASES = [_case(record, e) for record in ("polymergel-creep.jpk-force", "brain-creep.jpk-force")
         for e in sorted(SIZES)]


@pytest.fixture(scope="module")
def cleanly():
    """Each record explained once (its `--auto` model), for all its cases."""
    return functools.cache(explain_cleanly)


@pytest.mark.parametrize(("record", "effect"), CASES)
def test_hidden_effect_in_a_shared_record_is_named_first(cleanly, record, effect):
    check_named_first(cleanly(record), effect)
