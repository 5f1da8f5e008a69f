"""The apparent modulus against depth: the plateau check AFM users read.

With the contact point and every other fitted term taken off the measured force, the contact law
inverted sample by sample gives the modulus the record shows at each depth. A fit with the right
geometry on a thick, elastic sample gives a plateau at the fitted E; a wrong radius, a thin sample
feeling its substrate (stiffer with depth) or a viscous or nonlinear material make it drift.
"""

from __future__ import annotations

import itertools

import numpy as np

from rig.analysis.fitting.fit import FitResult
from rig.models.catalogue import CONTACT

BINS = 6  # depth bands from a tenth of the deepest indentation down to it
SHALLOWEST = 0.1  # below a tenth of the depth the force is too small to invert against the noise


def modulus_vs_depth(res: FitResult) -> list[dict]:
    """Per depth band of the loading (moving in), the median apparent E and its spread (SI).

    The contact law's own force is the model's prediction minus what the other terms add, so
    offset, drift and friction come off as fitted; the indentation is the motion past the
    fitted contact point."""
    if not res.model.has(CONTACT):
        return []
    law = next(e for e in res.model.effects if e.name == CONTACT)
    E = res.values["E_Pa"]
    rows: list[dict] = []
    for k, (t, pred) in enumerate(zip(res.trials, res.predictions, strict=True)):
        m = t.motion
        d = m.x_m - res.contact_m(k)  # the indentation: past the fitted contact point
        contact = law.fn(np.maximum(d, 0.0), m.v_m_s, E_Pa=E)
        others = pred - contact  # offset, drift, friction: what the fit says is not the tissue
        g = contact / E if E else np.zeros_like(d)
        loading = (d > 0) & (m.v_m_s > 0) & (g > 0)
        if np.count_nonzero(loading) < 2 * BINS:
            continue
        d_max = float(np.max(d[loading]))
        edges = np.linspace(SHALLOWEST * d_max, d_max, BINS + 1)
        E_app = (t.force_N - others)[loading] / g[loading]
        depth = d[loading]
        for lo, hi in itertools.pairwise(edges):
            band = (depth >= lo) & (depth <= hi)
            if np.count_nonzero(band) < 3:
                continue
            q25, q50, q75 = np.percentile(E_app[band], [25, 50, 75])
            rows.append({"trial": t.name, "depth_m": float(np.median(depth[band])), "E_Pa": float(q50),
                         "E_iqr_Pa": float(q75 - q25), "n": int(np.count_nonzero(band))})
    return rows


def plateau_drift(rows: list[dict]) -> float | None:
    """Relative change of the apparent E from the shallow half of the bands to the deep half."""
    if len(rows) < 4:
        return None
    half = len(rows) // 2
    shallow = float(np.median([r["E_Pa"] for r in rows[:half]]))
    deep = float(np.median([r["E_Pa"] for r in rows[half:]]))
    return (deep - shallow) / abs(shallow) if shallow else None


def format_modulus(rows: list[dict], length_unit: tuple[float, str]) -> str:
    """The apparent modulus at each depth, in the record's length unit, and how far it drifts from a
    plateau."""
    if not rows:
        return ""
    k, u = length_unit
    parts = [f"{r['depth_m'] / k:.3g} {u}: {format_pa(r['E_Pa'])}" for r in rows]
    drift = plateau_drift(rows)
    tail = ""
    if drift is not None:
        tail = (f"; {abs(drift) * 100:.0f} % {'stiffer' if drift > 0 else 'softer'} deep than shallow"
                + (" (a plateau)" if abs(drift) < 0.1 else
                   " (not a plateau: a wrong geometry, a hard substrate below a thin sample, or a material "
                   "that is not linear elastic)"))
    return "apparent E by depth  " + ", ".join(parts) + tail


def format_pa(v: float) -> str:
    """A modulus in Pa, kPa, MPa or GPa, three figures."""
    for k, u in ((1e9, "GPa"), (1e6, "MPa"), (1e3, "kPa")):
        if abs(v) >= k:
            return f"{v / k:.3g} {u}"
    return f"{v:.3g} Pa"
