"""How often a drift hidden in a real AFM force curve is named, on every curve of the shared
force-distance files and maps (`../shared/realdata/afm-fd/`): the researcher's workflow as in
tests/bench/realdata_naming.py. Each curve's `--auto` model from Hertz (a paraboloid of 10 um, the
approach, the contact point fitted) is its clean model; a drift of a tenth and of a twentieth of
the approach's force range over the approach's time is added to the force, and `--explain` on the
clean model must name it first; `--auto` from Hertz on the curve with the drift must add it. The
clean curve is a control: `--explain` on its `--auto` model must suggest nothing.

Of the four effects hidden in the creep records, only the drift is an effect of an approach's
own: on one approach at one speed a friction or a drag is a constant (the curve's fitted zero) and
a delay of the reading is a shift of the contact point. On one approach at one speed a drift and a
tilt of the baseline (a force growing with the piezo's travel) are one function of time, so either
name is the answer; a curve whose force is the same as another's (the AFM Workshop map repeats one
curve 16 times) counts once. All 19 distinct curves take hours on two cores (a long curve's
`--auto` runs take ten to twenty-five minutes): `python tests/bench/afm_naming.py`; `--list` names
the curves, `--only TEXT` (repeatable) keeps those whose file name contains TEXT, `--max N` the first
N per file, `--controls` the clean curves alone."""

from __future__ import annotations

import hashlib
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from rig.analysis.workflow.session import AnalyzeRequest, analyze
from rig.records import ReadOptions, read_record
from rig.records.afm import list_curves

AFM = Path(__file__).resolve().parents[3] / "shared" / "realdata" / "afm-fd"
INDENTER = "paraboloid:R=10um"
# what the user gives for files that do not hold their calibration (realdata/README.md)
OVERRIDES = {"fmt-ntmdt-txt-fd_": (0.055, 61.0), "fmt-afm-workshop-fd_mapping_": (20.0, 1e-8)}
SIZES = (0.1, 0.05)
DRIFT = ("drift", "tilt")  # one function of time on one approach at one speed
PER_RECORD = ("contact_point", "offset")


def options(path: Path, curve: int | None = None) -> ReadOptions:
    k, s = next((v for p, v in OVERRIDES.items() if path.name.startswith(p)), (None, None))
    return ReadOptions(curve=curve, spring_constant_N_per_m=k, sensitivity_m_per_V=s)


def with_drift(rec, size: float):
    """`rec` with a drift of `size` of its approach's force range over the approach's time."""
    a = rec.segment == "approach" if rec.segment is not None else np.ones(rec.n, bool)
    t, f = rec.t_s, rec.force_N
    span = float(np.ptp(t[a])) or float(np.ptp(t))
    return replace(rec, force_N=f + size * float(np.ptp(f[a])) * (t - t[a][0]) / span)


def _run(path: Path, rec, **kw) -> dict:
    return analyze(AnalyzeRequest([str(path)], model="hertz", indenter=INDENTER, segment="approach",
                                  records=[rec], **kw)).json


def one(job: tuple[Path, int, bool]) -> dict:
    path, curve, controls_only = job
    t0 = time.time()
    rec = read_record(path, options(path, curve))
    clean = _run(path, rec, auto=True)
    adds = [e for e in clean["auto_final"]["effects"] if e not in ("elastic_contact", *PER_RECORD)]
    control = _run(path, rec, add=adds, explain=True)
    out = {"curve": f"{path.name[:40]} #{curve}", "clean": adds, "quiet": not control["suggestions"],
           "beyond": any(s["unsupported"] for s in control["suggestions"]),
           "control": control["diagnosis"]["text"][:100], "cases": []}
    for size in () if controls_only else SIZES:
        hidden = with_drift(rec, size)
        ex = _run(path, hidden, add=[e for e in adds if e not in DRIFT], explain=True)
        d = ex["diagnosis"]
        auto = _run(path, hidden, auto=True)
        out["cases"].append({"size": size, "held": bool(set(DRIFT) & set(adds)), "named": d["best"] in DRIFT
                             and d["text"].startswith(f"most likely missing: {d['best']}"),
                             "said": d["text"][:100],
                             "auto_added": bool(set(DRIFT) & set(auto["auto_final"]["effects"])),
                             "auto": " ".join(f"+{s['added']}" if s["added"] else f"-{s['removed']}"
                                              for s in auto["auto"][1:])})
    out["seconds"] = time.time() - t0
    return out


def curves(only: list[str] | None = None, most: int | None = None) -> list[tuple[Path, int]]:
    """The distinct curves of the shared files (a repeated curve counts once), those whose file name
    contains one of `only`, at most `most` per file."""
    out, seen = [], set()
    for p in sorted(AFM.iterdir()):
        if only and not any(o in p.name for o in only):
            continue
        kept = 0
        for c in list_curves(p, options(p)):
            key = hashlib.sha1(read_record(p, options(p, c.enum)).force_N.tobytes()).hexdigest()
            if key not in seen and (most is None or kept < most):
                seen.add(key)
                kept += 1
                out.append((p, c.enum))
    return out


def main(controls_only: bool = False, only: list[str] | None = None, most: int | None = None) -> None:
    jobs = [(p, c, controls_only) for p, c in curves(only, most)]
    if not jobs:
        sys.exit(f"no curve of {AFM} matches --only {' '.join(only or [])}")
    named = cases = added = quiet = beyond = 0
    with ProcessPoolExecutor(2) as pool:
        for r in pool.map(one, jobs):
            said = "quiet" if r["quiet"] else "SUGGESTED"
            print(f"## {r['curve']}: clean +{' +'.join(r['clean']) or '(hertz)'}; control {said}: "
                  f"{r['control']}  ({r['seconds']:.0f} s)", flush=True)
            quiet += r["quiet"]
            beyond += r["beyond"]
            for c in r["cases"]:
                said = "held by the clean model" if c["held"] else ("named" if c["named"] else "MISSED")
                print(f"   drift {c['size']:<5} {said:<24} auto {c['auto'] or '(none)'} -> "
                      f"{'added' if c['auto_added'] else 'NOT ADDED'}  {c['said']}", flush=True)
                cases += not c["held"]
                named += c["named"] and not c["held"]
                added += c["auto_added"]
    n = len(jobs)
    print(f"named first {named} of {cases} ({100 * named / max(cases, 1):.0f} %); --auto added it in "
          f"{added} of {2 * n}; clean controls with no suggestion {quiet} of {n}, with one the curve cannot "
          f"support {beyond}")


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="A drift hidden in the shared AFM curves: named first, added by "
                                             "--auto, and the clean curves left quiet.")
    ap.add_argument("--controls", action="store_true", help="the clean curves alone")
    ap.add_argument("--only", action="append", metavar="TEXT", help="curves of files whose name contains TEXT")
    ap.add_argument("--max", type=int, metavar="N", help="at most N curves per file")
    ap.add_argument("--list", action="store_true", help="name the curves and stop")
    args = ap.parse_args()
    if args.list:
        for p, c in curves(args.only, args.max):
            print(f"{p.name} #{c}")
    else:
        main(args.controls, args.only, args.max)
