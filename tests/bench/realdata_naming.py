"""How often an effect hidden in a real record is named, on the shared creep and relaxation
records: the researcher's workflow (the clean record's `--auto` model as the base, then the effect
hidden as tests/test_realdata_explain.py hides it, at its size and at half, and taken out of the
model if the clean model held it: `--explain` must name it first), and `--auto` from the paper's
model on the record with the effect (it must add it). Each clean record is a control: `--explain`
on its `--auto` model must suggest nothing the record cannot support. About 75 minutes on two
cores: `python tests/bench/realdata_naming.py [RECORD ...]`."""

from __future__ import annotations

import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import tests.test_realdata_explain as T
from rig.analysis.diagnosis.explain import auto, explain, richness
from rig.analysis.fitting.fit import fit
from rig.analysis.trials.data import load_trial
from rig.models import CATALOGUE, build_model
from rig.models.core import Model

# the two creep records, and every fourth of the fifteen oocyte relaxations from the first
RECORDS = ["polymergel-creep.jpk-force", "brain-creep.jpk-force",
           *(f"oocyte-cell1/cell1-{i:04d}.jpk-force" for i in (1, 5, 9, 13))]
EFFECTS = ["drift", "friction", "delay"]  # an offset from the first sample is the record's zero
SIZES = (1.0, 0.5)
BASE_SIZES = dict(T.SIZES)


def _model(names: list[str]) -> Model:
    # the per-record contact point and zero come back with the fit (`with_record_params`)
    return Model([CATALOGUE[n] for n in names if n != "contact_point"])


def clean(record: str) -> tuple[str, list[str], dict, dict]:
    """The record's `--auto` model (its effects and values) and the control: `--explain` on it."""
    t0 = time.time()
    _, res = T.explain_cleanly(record)
    ex = explain(res, dict(CATALOGUE))
    control = {"quiet": not ex.suggestions, "said": ex.summary[:110], "rich": richness(res),
               "unsupported": any(s.unsupported for s in ex.suggestions),
               "model": f"{res.model.name} ({len(res.model.params)} params, N_eff {res.n_eff:.0f})",
               "seconds": time.time() - t0}
    return record, res.model.effect_names, res.values, control


def case(args: tuple) -> dict:
    record, names, values, effect, mult = args
    t0 = time.time()
    trial = load_trial(T.REALDATA / record, form="force")
    T.SIZES = {**BASE_SIZES, effect: BASE_SIZES[effect] * mult}  # a worker runs several cases
    hidden = T.hide(trial, effect)
    held = effect in names
    base = fit(_model([n for n in names if n != effect]), [hidden], starts=1, initial=values)
    ex = explain(base, dict(CATALOGUE))
    named = ex.best == effect and ex.summary.startswith(f"most likely missing: {effect}")
    steps = auto(fit(build_model("proposed"), [hidden]), dict(CATALOGUE))
    final = steps[-1]["fit"]
    return {"record": record, "effect": effect, "mult": mult, "held": held, "named": named,
            "ranked": [(s.label, round(s.delta_bic, 1)) for s in ex.ranked[:3]], "said": ex.summary[:110],
            "auto_added": final.model.has(effect),
            "auto": " ".join(f"+{s['added']}" if s["added"] else f"-{s['removed']}" for s in steps[1:]),
            "auto_rich": richness(final), "seconds": time.time() - t0}


def main(records: list[str]) -> None:
    with ProcessPoolExecutor(2) as pool:
        cleans = list(pool.map(clean, records))
        for record, _, _, c in cleans:
            print(f"## {record}: clean model {c['model']}, {c['seconds']:.0f} s; control: "
                  f"{'quiet' if c['quiet'] else 'SUGGESTED'}: {c['said']}"
                  + (f"; beyond the floor: {c['rich']}" if c["rich"] else ""), flush=True)
        jobs = [(r, names, values, e, m) for r, names, values, _ in cleans for e in EFFECTS for m in SIZES]
        rows = []
        for r in pool.map(case, jobs):  # in order, each as soon as it can (the run takes most of an hour)
            rows.append(r)
            said = "held by the clean model" if r["held"] else ("named" if r["named"] else "MISSED")
            got = "added" if r["auto_added"] else "NOT ADDED"
            got += f"; {r['auto_rich']}" if r["auto_rich"] else ""
            print(f"{r['record'][:24]:<25}{r['effect']:<9}{r['mult']:>4}  {said:<24} auto "
                  f"{r['auto'] or '(none)'} -> {got}  {r['seconds']:.0f} s\n      {r['ranked']}  {r['said']}",
                  flush=True)
    named = cases = added = auto_cases = rich = 0
    for r in rows:
        if not r["held"]:
            cases += 1
            named += r["named"]
        auto_cases += 1
        added += r["auto_added"]
        rich += not r["auto_rich"]
    quiet = sum(c["quiet"] for *_, c in cleans)
    beyond = sum(c["unsupported"] for *_, c in cleans)
    print(f"named first {named} of {cases} ({100 * named / max(cases, 1):.0f} %); --auto added it in "
          f"{added} of {auto_cases} ({100 * added / max(auto_cases, 1):.0f} %), its model within the floor in "
          f"{rich}; clean controls with no suggestion {quiet} of {len(cleans)}, with one the record cannot "
          f"support {beyond}")


if __name__ == "__main__":
    main(sys.argv[1:] or RECORDS)
