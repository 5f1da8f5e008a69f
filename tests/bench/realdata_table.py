"""RMSE over noise of every named model on every shared real record (a markdown table).

    python tests/bench/realdata_table.py [../shared/realdata]
"""

from __future__ import annotations

import sys
from pathlib import Path

from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import load_trial
from rig.models import CATALOGUE, build_model
from rig.models.catalogue import named_models

LUMPED = named_models(CATALOGUE)  # the models without an indenter

root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[3] / "shared" / "realdata"
print("| record | noise | " + " | ".join(LUMPED) + " | at a bound |")
print("|---|---|" + "---|" * len(LUMPED) + "---|")
for path in sorted(root.glob("**/*.jpk-force")):
    trial = load_trial(path)
    k, unit = trial.force_unit
    cells, bound = [], []
    for name in LUMPED:
        res = fit(build_model(name), [trial])
        cells.append(f"{res.overall.rmse_N / res.noise_N:.0f}")
        bound += [f"{name}: {w.split(' =')[0]}" for w in res.warnings if "sits at its bound" in w]
    row = f"| {path.name} | {res.noise_N / k:.3g} {unit} | " + " | ".join(cells)
    print(row + f" | {'; '.join(bound) or '-'} |", flush=True)
