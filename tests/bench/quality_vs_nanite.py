"""rig's per-curve quality rating (rig.analysis.batch.quality, the batch table's `quality` column) against
nanite's (`Indentation.rate_quality()`: an Extra Trees regressor trained on the zef18 set of
zebrafish spinal-cord maps, rating 0-10), on every curve of the shared AFM files.

    python tests/bench/quality_vs_nanite.py [../shared/realdata]

Both fit Hertz for a 10 µm paraboloid to the approach (rig: `rig analyze --each --model hertz
--indenter paraboloid:R=10um --segment approach`; nanite: as tests/bench/nanite_table.py runs it,
weight_cp=0), then each rates the curve. nanite is a benchmark-only peer (GPL): the rig package
never imports it. Prints one row per curve (rig's rating with its parts, nanite's), the rank
correlation (Spearman) of the two over the curves both rate, and where they disagree on which
side of 5 a curve falls.
"""

from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import nanite_table as nt

from rig.analysis.batch.each import run_each
from rig.analysis.batch.engine import BatchRequest


def rig_rows(root: Path) -> dict[tuple[str, int], dict]:
    out = {}
    for path in sorted(nt.afm_dir(root).iterdir()):
        o = nt.read_options(path)
        req = BatchRequest(model="hertz", indenter=nt.INDENTER, segment="approach",
                           spring_constant_N_per_m=o.spring_constant_N_per_m,
                           sensitivity_m_per_V=o.sensitivity_m_per_V)
        res = run_each([str(path)], req, workers=1, progress=False)
        for r in res.rows:
            out[(path.name, int(r["curve"]) if r.get("curve") not in (None, "") else 0)] = r
    return out


def nanite_rating(path: Path, curve: int) -> float | str:
    try:
        idnt = nt.load_nanite(path, curve)
        nt.fit_nanite(idnt, nt.R_M, 0.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return float(idnt.rate_quality())
    except nt.FAILURES as exc:
        return nt._why(exc)


def spearman(a: list[float], b: list[float]) -> float:
    ra, rb = (np.argsort(np.argsort(x)).astype(float) for x in (a, b))
    return float(np.corrcoef(ra, rb)[0, 1])


def main(root: Path = nt.ROOT) -> dict:
    rows = rig_rows(root)
    lines = ["| file | curve | rig quality | its parts | rig RMSE/noise | nanite rating |",
             "|---|---:|---:|---|---:|---:|"]
    both = []
    for (name, curve), r in sorted(rows.items()):
        theirs = nanite_rating(nt.afm_dir(root) / name, curve)
        ours = r.get("quality")
        if r.get("error"):
            ours_s, parts = "-", f"rig could not analyse it: {r['error'][:60]}"
        else:
            ours_s, parts = f"{ours:.1f}", r.get("quality_parts", "")
        theirs_s = f"{theirs:.2f}" if isinstance(theirs, float) else f"- ({theirs[:50]})"
        ron = r.get("rmse_over_noise")
        lines.append(f"| {name[:40]} | {curve} | {ours_s} | {parts} | "
                     f"{'' if ron is None else f'{ron:.3g}'} | {theirs_s} |")
        if isinstance(theirs, float) and isinstance(ours, int | float) and math.isfinite(theirs):
            both.append((name, curve, float(ours), theirs))
    print("\n".join(lines))
    out = {"curves": len(rows), "both": len(both)}
    if len(both) >= 3:
        ours, theirs = [b[2] for b in both], [b[3] for b in both]
        out["spearman"] = spearman(ours, theirs)
        split = [b for b in both if (b[2] >= 5) != (b[3] >= 5)]
        out["disagree_at_5"] = len(split)
        print(f"\n{len(both)} curves rated by both: Spearman rank correlation {out['spearman']:+.2f}; "
              f"rig median {np.median(ours):.2g}, nanite median {np.median(theirs):.2g}; on opposite sides "
              f"of 5: {len(split)} ({', '.join(f'{n[:24]} {c}' for n, c, *_ in split[:6])})")
    return out


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else nt.ROOT)
