"""Both errors on every curve of the shared AFM files: Hertz (paraboloid, R = 10 um, or the
file's own indenter), the approach, the contact point fitted; E with its statistical and
systematic errors, and E refitted on the approach cut at 50 % and 75 % of its peak force, each
with its own interval; whether each refit's interval overlaps the whole approach's, and how
much wider the reported interval is than the statistical one alone. A markdown table:

    python tests/bench/errors_realdata.py [../shared/realdata]
"""

from __future__ import annotations

import sys
from pathlib import Path

from rig.analysis.fitting.fit import fit
from rig.analysis.intervals.systematic import cut, interval, systematic
from rig.analysis.workflow.inputs import load_inputs
from rig.analysis.workflow.session import AnalyzeRequest, analyze
from rig.errors import RigError
from rig.models.catalogue import build_model
from rig.records import ReadOptions, list_curves

ROOT = Path(__file__).resolve().parents[3] / "shared" / "realdata"
INDENTER = "paraboloid:R=10um"
# what the user gives for files that do not hold their calibration (realdata/README.md)
OVERRIDES = {"fmt-ntmdt-txt-fd_": {"spring constant": 0.055, "sensitivity": 61.0},
             "fmt-afm-workshop-fd_mapping_": {"spring constant": 20.0, "sensitivity": 1e-8}}


def options(path: Path) -> dict:
    o = next((v for k, v in OVERRIDES.items() if path.name.startswith(k)), {})
    return {"spring_constant_N_per_m": o.get("spring constant"), "sensitivity_m_per_V": o.get("sensitivity")}


def kpa(v: float | None) -> str:
    return "-" if v is None else f"{v / 1e3:.4g}"


def row(path: Path, curve: int) -> str:
    o = options(path)
    req = AnalyzeRequest([str(path)], model="hertz", indenter=INDENTER, curve=curve, **o)
    out = analyze(req)
    m = out.json["material"]
    lo, hi = m["E_Pa_interval"]
    # each refit with its own errors: the fit on the cut samples, and its own systematic error
    inp = load_inputs([str(path)], [], [], ReadOptions(curve=curve, **o), indenter=INDENTER, segment="approach")
    res = fit(build_model("hertz", registry=inp.registry), inp.trials)
    cells = []
    for c in systematic(res).choices:
        if "% of peak" not in c.name:
            continue
        sub = fit(res.model, [cut(res.trials[0], 0, c.samples)], starts=1, initial=res.values)
        sub_sys = systematic(sub)
        iv = interval(sub.values["E_Pa"], sub.stderr["E_Pa"], sub_sys.error["E_Pa"] if sub_sys else 0.0)
        overlap = iv is not None and iv[0] <= hi and iv[1] >= lo
        cells.append(f"{kpa(sub.values['E_Pa'])} [{kpa(iv[0])}, {kpa(iv[1])}] {'yes' if overlap else 'NO'}")
    widen = (hi - lo) / (2 * 1.96 * m["E_Pa_stat"]) if m["E_Pa_stat"] else float("nan")
    return (f"| {path.name[:38]} | {curve} | {kpa(m['E_Pa'])} | {m['E_Pa_stat'] / 1e3:.3g} | "
            f"{(m['E_Pa_sys'] or 0) / 1e3:.3g} | {'yes' if out.json['adequate'] else 'no'} | {widen:.3g} | "
            + " | ".join(cells + ["-"] * (2 - len(cells))) + " |")


def main(root: Path) -> None:
    print("| file | curve | E (kPa) | stat | sys | adequate | interval / (+/-1.96 stat) | "
          "to 50 %: E [interval] overlaps | to 75 %: E [interval] overlaps |")
    print("|---|---|---|---|---|---|---|---|---|")
    for path in sorted((root / "afm-fd").iterdir()):
        o = options(path)
        try:
            found = list_curves(path, ReadOptions(**o))
        except RigError as exc:
            print(f"| {path.name[:38]} | - | {exc} |")
            continue
        for c in found:
            try:
                print(row(path, c.enum), flush=True)
            except RigError as exc:
                print(f"| {path.name[:38]} | {c.enum} | not analysed: {str(exc)[:80]} |", flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT)
