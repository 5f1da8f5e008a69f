"""The hidden-effect cases of tests/test_realdata_explain.py on the polymer-gel record (its
`--auto` model and each explain take as long again as the brain record's, which the default
run covers): `python -m pytest tests/bench/test_bench_realdata_explain.py`."""

from __future__ import annotations

import pytest

from tests.test_realdata_explain import SIZES, explain_cleanly, pytestmark  # noqa: F401
from tests.test_realdata_explain import test_hidden_effect_in_a_real_record_is_named_first as named_first


@pytest.fixture(scope="module")
def explained():
    return explain_cleanly("polymergel-creep.jpk-force")


@pytest.mark.parametrize("effect", sorted(SIZES))
def test_hidden_effect_in_the_gel_record_is_named_first(explained, effect):
    named_first(explained, effect)
