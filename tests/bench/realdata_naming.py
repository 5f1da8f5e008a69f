"""How often `--explain` names an effect hidden in a real record first: the researcher's workflow
(the clean record's `--auto` model as the base, then the effect hidden as
tests/test_realdata_explain.py hides it, at its size and at half, and taken out of the model if the
clean model held it), on the shared creep and relaxation records, with each clean record as a
control. About nine minutes on two cores: `python tests/bench/realdata_naming.py`."""

from __future__ import annotations

import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import tests.test_realdata_explain as T
from rig.analysis.explain import explain
from rig.analysis.fit import fit
from rig.models import CATALOGUE
from rig.models.core import Model

RECORDS = ["polymergel-creep.jpk-force", "brain-creep.jpk-force", "oocyte-cell1/cell1-0001.jpk-force",
           "oocyte-cell1/cell1-0005.jpk-force"]
EFFECTS = ["drift", "friction", "delay"]  # an offset from the first sample is the record's zero
SIZES = (1.0, 0.5)


def one(record: str) -> tuple[list[tuple], float, str]:
    t0 = time.time()
    trial, clean = T.explain_cleanly(record)
    rows = []
    sizes = dict(T.SIZES)
    for effect in EFFECTS:
        for mult in SIZES:
            T.SIZES = {**sizes, effect: sizes[effect] * mult}
            held = effect in clean.model.effect_names
            base = fit(Model([e for e in clean.model.effects if e.name != effect]), [T.hide(trial, effect)],
                       starts=1, initial=clean.values)
            ex = explain(base, dict(CATALOGUE))
            named = ex.summary.startswith(f"most likely missing: {effect}")
            ranked = [(s.effect, round(s.delta_bic, 1)) for s in ex.ranked[:3]]
            rows.append((effect, mult, held, named, ranked, ex.summary[:90]))
    T.SIZES = sizes
    ex = explain(clean, dict(CATALOGUE))
    rows.append(("clean", 0.0, False, not ex.suggestions, [], ex.summary[:90]))
    return rows, time.time() - t0, f"{clean.model.name} ({len(clean.model.params)} params)"


def main() -> None:
    named = cases = quiet = controls = 0
    with ProcessPoolExecutor(2) as pool:
        for record, (rows, seconds, model) in zip(RECORDS, pool.map(one, RECORDS), strict=True):
            print(f"## {record}: clean model {model}, {seconds:.0f} s", flush=True)
            for effect, mult, held, ok, ranked, summary in rows:
                said = "held by the clean model" if held else ("named" if ok else "MISSED")
                print(f"   {effect:<9}{mult:>4}  {said}  {ranked}  {summary}", flush=True)
                if effect == "clean":
                    controls += 1
                    quiet += ok
                elif not held:
                    cases += 1
                    named += ok
    print(f"named first {named} of {cases} ({100 * named / max(cases, 1):.0f} %); clean controls with no "
          f"suggestion {quiet} of {controls}")


if __name__ == "__main__":
    main()
