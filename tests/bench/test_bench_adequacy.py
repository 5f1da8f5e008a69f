"""The adequacy rule over forty seeds per sensor and record kind (tests/test_adequacy.py runs
twelve): a perfect model adequate in at least 38, a misfit of 1.5x the noise caught in at least
36. About two minutes on two cores: `python -m pytest tests/bench/test_bench_adequacy.py`."""

from __future__ import annotations

import pytest

from tests.test_adequacy import SENSORS, check


@pytest.mark.parametrize("record", ["afm", "rig"])
@pytest.mark.parametrize("kind", SENSORS)
def test_forty_seeds(kind, record):
    check(kind, record, range(40), 38, 36)
