"""A curve's quality rating, 0 to 10, from its analysis (the `quality` column of a batch table;
the rule is set out in rig.analysis.batch.table and docs/explanation/quality.md).

Four parts, each from what the analysis measured, none from a trained model:

- contact (0-3): how well the contact point is found: its uncertainty (statistical and
  systematic, combined) over the indentation past it. 3 at 1 % or less, 0 at 30 % or more,
  falling with the logarithm between; 0 on a curve with less than 5 % of its samples out of
  contact (its contact point extrapolated, not seen). A record whose surface is known (the
  rig's own logs) gets 3.
- fit (0-4): the fit's RMSE over the noise at rest. 4 at 1.1 or less, 0 at 5 or more, falling
  with the logarithm between.
- baseline (0-2): the share of the curve's samples out of contact (the baseline the zero and
  the noise are measured on). 2 from 30 % to 90 %; falling linearly to 0 at 5 % (too little
  baseline) and at 99 % (barely indented).
- artefacts (0-1): 1 when nothing is named about the curve, 0.5 for one, 0 for two or more:
  each caveat the file's reader recorded, a curve that starts in contact, the effect
  `--explain` names missing, a physics warning of the fit (a law that pulls, a modulus below
  nought).
"""

from __future__ import annotations

import math

PARTS = {"contact": 3.0, "fit": 4.0, "baseline": 2.0, "artefacts": 1.0}


def _log_ramp(x: float, good: float, bad: float) -> float:
    """1 at `good` or better, 0 at `bad` or worse, linear in log(x) between (good < bad)."""
    if not x > good:
        return 1.0
    if x >= bad:
        return 0.0
    return 1.0 - math.log(x / good) / math.log(bad / good)


def _plateau(b: float) -> float:
    if 0.30 <= b <= 0.90:
        return 1.0
    if b < 0.30:
        return max(0.0, (b - 0.05) / 0.25)
    return max(0.0, (0.99 - b) / 0.09)


def rate(out: dict, effect: str = "") -> tuple[float, dict[str, float]]:
    """The rating and its parts, from one curve's analysis (rig.analysis.workflow.session's JSON, as a
    batch row is built from it) and the effect --explain named missing ("" for none)."""
    rec = out["records"][0]
    m = out.get("material") or {}
    depth = float((out.get("scales") or {}).get("length_m") or 0.0)
    if "contact_point_m" in rec:
        stat = rec.get("contact_point_m_stderr")
        sys_ = m.get("contact_point_m_sys")
        u = math.hypot(stat if _finite(stat) else math.inf, sys_ if _finite(sys_) else 0.0)
        contact = _log_ramp(u / depth, 0.01, 0.30) if depth > 0 and math.isfinite(u) else 0.0
    else:
        contact = 1.0  # the record knows its surface
    r = out["fit"].get("rmse_over_noise")
    fit = _log_ramp(float(r), 1.1, 5.0) if _finite(r) else 0.0
    n = int(rec.get("samples") or 0)
    touched = sum(int(p["n"]) for p in (out.get("phases") or {}).values() if p)
    free = 1.0 - touched / n if n else 0.0
    baseline = _plateau(free)
    if free < 0.05:
        contact = 0.0  # the curve (nearly) starts in contact: its contact point is extrapolated, not seen
    starts_in_contact = any("starts in contact" in str(note) for note in rec.get("notes") or [])
    named = len(m.get("caveats") or []) + (1 if effect else 0) + (1 if starts_in_contact else 0) + sum(
        1 for w in out.get("warnings") or [] if str(w).startswith("physics"))
    artefacts = {0: 1.0, 1: 0.5}.get(named, 0.0)
    parts = {"contact": contact * PARTS["contact"], "fit": fit * PARTS["fit"],
             "baseline": baseline * PARTS["baseline"], "artefacts": artefacts * PARTS["artefacts"]}
    return round(sum(parts.values()), 1), parts


def describe(parts: dict[str, float]) -> str:
    """The parts as the table's `quality_parts` column gives them."""
    return ", ".join(f"{k} {v:.1f}/{PARTS[k]:g}" for k, v in parts.items())


def _finite(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
