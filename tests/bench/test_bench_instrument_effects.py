"""`--explain` on every curve of the shared AFM files (realdata/afm-fd) with and without the AFM's
own effects (tilt, drag, the bottom effect, adhesion: rig.models.instrument), as `rig analyze FILE
--model hertz --segment approach --explain` runs it, and with `--segment all` (approach and
retract: where adhesion and drag show) (R = 10 µm where the file names no indenter; the
Chiaro's header radius where it does). Prints a markdown table: the verdict before and after, and
the dBIC of each. A measurement, not a pass/fail: it fails only if a curve cannot be analysed
after that could be before.

    python -m pytest -s tests/bench/test_bench_instrument_effects.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from rig.analysis.diagnosis import explain as explain_module
from rig.analysis.workflow.session import AnalyzeRequest, analyze
from rig.records import read_record

sys.path.insert(0, str(Path(__file__).parent))
import nanite_table as nt

pytestmark = pytest.mark.skipif(not nt.afm_dir().is_dir(), reason="the shared AFM files are not here")


def _verdict(path: Path, curve: int, segment: str) -> tuple[str, float | None, str]:
    o = nt.read_options(path, curve)
    named = read_record(path, o).meta.get("indenter") if path.name == nt.CHIARO else None
    j = analyze(AnalyzeRequest([str(path)], model="hertz", indenter="paraboloid" if named else nt.INDENTER,
                               segment=segment, curve=curve, explain=True,
                               spring_constant_N_per_m=o.spring_constant_N_per_m,
                               sensitivity_m_per_V=o.sensitivity_m_per_V)).json
    d = j["diagnosis"]
    sug = {s["effect"]: s["delta_bic"] for s in j.get("suggestions", [])}
    name = d["best"] or (f"({d['closest']})" if d["closest"] else "-")
    dbic = sug.get(d["best"] or d["closest"] or "")
    twins = "; ".join("/".join(x["effects"]) for x in d["lookalikes"])
    return name, dbic, twins


def _without_instrument_effects(monkeypatch) -> None:
    # explain's candidates as they were: the registry alone
    monkeypatch.setattr(explain_module, "instrument_effects", lambda model, registry: registry)


@pytest.mark.parametrize("segment", ["approach", "all"])
def test_verdicts_on_the_shared_afm_curves_before_and_after(monkeypatch, segment):
    rows = []
    for path, curve in nt.curves():
        with monkeypatch.context() as m:
            _without_instrument_effects(m)
            before = _verdict(path, curve, segment)
        after = _verdict(path, curve, segment)
        rows.append((path.name, curve, before, after))
    fmt = lambda x: "" if x is None else f"{x:.1f}"  # noqa: E731
    print(f"\nsegment {segment}")
    print("\n| file | curve | best before | dBIC | best after | dBIC | look-alikes after |")
    print("|---|---|---|---|---|---|---|")
    for name, curve, b, a in rows:
        print(f"| {name} | {curve} | {b[0]} | {fmt(b[1])} | {a[0]} | {fmt(a[1])} | {a[2]} |")
    changed = sum(b[0] != a[0] for *_, b, a in rows)
    print(f"\n{changed} of {len(rows)} verdicts changed")
