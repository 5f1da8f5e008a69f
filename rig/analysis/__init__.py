"""The model lab: trials from records, fits, how far their numbers can move, which effect a
model misses, the material's terms, one `rig analyze` request and many curves in a batch.

The public API is the names below (documented in docs/api.md); the subpackages are layers,
each importing only from those before it in `LAYERS` (held by tests/test_layers.py):

    stats      the noise, standard errors, the one criterion, the adequacy tests
    trials     records on a uniform grid, with contact, phases and the record's scales
    fitting    the engine: scaled least squares, variable projection, the result
    intervals  profile likelihood, the bootstrap, the fit-range systematics
    diagnosis  which effect is missing (explain, --auto), the residual in words, design
    material   modulus against depth, creep compliance
    workflow   one `rig analyze` request: inputs, JSON, report
    batch      `rig analyze --each`: the engine over many curves, the table, the map

The names are imported when first used (PEP 562), as scikit-image's are: `import rig.analysis`
costs nothing, and a one-curve command pays only for the modules it runs.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

LAYERS = ("stats", "trials", "fitting", "intervals", "diagnosis", "material", "workflow", "batch")

_PUBLIC = {
    "TrialData": "trials.data", "load_trial": "trials.data", "prepare": "trials.data",
    "fit": "fitting.fit", "FitResult": "fitting.result",
    "explain": "diagnosis.explain", "auto": "diagnosis.explain", "Explanation": "diagnosis.explain",
    "AnalyzeRequest": "workflow.session", "analyze": "workflow.session",
    "analyze_curves": "batch.each", "on_grid": "batch.each",
}

__all__ = ["AnalyzeRequest", "Explanation", "FitResult", "TrialData", "analyze", "analyze_curves", "auto",
           "explain", "fit", "load_trial", "on_grid", "prepare"]

if TYPE_CHECKING:
    from rig.analysis.batch.each import analyze_curves, on_grid
    from rig.analysis.diagnosis.explain import Explanation, auto, explain
    from rig.analysis.fitting.fit import fit
    from rig.analysis.fitting.result import FitResult
    from rig.analysis.trials.data import TrialData, load_trial, prepare
    from rig.analysis.workflow.session import AnalyzeRequest, analyze


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        value = getattr(importlib.import_module(f"{__name__}.{_PUBLIC[name]}"), name)
        globals()[name] = value  # once: later lookups are plain attribute reads
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
