"""What one fit says, as the JSON of `rig analyze --json` and the lines beside its report: where
each record's contact was placed, the held-out records' errors, the force-indentation points."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from rig.analysis.fitting.fit import FitResult, error_table, evaluate, fit, with_record_params
from rig.analysis.trials.data import PHASES, TrialData
from rig.models.core import Model, Param


def _finite(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


def result_json(res: FitResult, paths: list[str]) -> dict:
    """What `rig analyze --json` says of one fit: the result's own data (`FitResult.as_dict`),
    the files it was fitted to, and room for the suggestions the command adds."""
    d = res.as_dict()
    return {"model": d.pop("model"), "effects": d.pop("effects"), "trials": paths, **d, "suggestions": []}


def format_placement(res: FitResult) -> str:
    """One line per record whose contact the fit placed: where, and its zero."""
    k, u = res.trials[0].length_unit
    kf, uf = res.force_unit
    lines = []
    for t, row in zip(res.trials, res.placements(), strict=True):
        if "contact_point_m" not in row or not t.contact_estimated:
            continue
        se = row["contact_point_m_stderr"]
        at = row["contact_point_m"]
        at = 0.0 if abs(at) < 1e-9 * res.scales.length_m else at  # the first sample, not 3e-15 of a µm
        text = f"contact    {t.name}: at {at / k:.4g} {u} of travel"
        text += f" +/- {se / k:.2g} {u}" if se is not None else ""
        if "zero_N" in row:
            ze = row["zero_N_stderr"]
            text += f"; force at rest {row['zero_N'] / kf:.4g}"
            text += f" +/- {ze / kf:.2g}" if ze is not None else ""
            text += f" {uf}"
        lines.append(text + " (fitted)")
    return "\n".join(lines)


def holdout_json(res: FitResult, held: list[TrialData]) -> list[dict]:
    """The fitted model's error on records it was not fitted to. A held-out record that does not
    know its surface is placed first: its own contact point and zero fitted, the model's
    parameters held where the fit put them."""
    out = []
    for t in held:
        placed: dict = {}
        if t.contact_estimated:
            own = fit(_frozen(with_record_params(res.model, [t]), res.values), [t])
            values, model = own.values, own.model
            placed = own.placements()[0]
        else:
            values, model = res.values, res.model.for_records(1)
        (p,) = evaluate(model, values, [t])
        overall, phases = error_table([t], [t.force_N - p])
        out.append({"trial": t.name, **overall.as_dict(), **placed,
                    "phases": {k: (v.as_dict() if v else None) for k, v in phases.items()}})
    return out


def format_holdout(rows: list[dict], unit: tuple[float, str] = (1.0, "N")) -> str:
    """The held-out trials' errors as a table (RMSE, mean and by phase) in `unit`."""
    k, u = unit
    lines = ["held-out trials (parameters from the fit above)",
             f"  {'trial':<48}{'RMSE ' + u:>9}{'mean ' + u:>10}" + "".join(f"{p:>12}" for p in PHASES)]
    for r in rows:
        ph = "".join(f"{(r['phases'][p]['rmse_N'] / k if r['phases'][p] else float('nan')):>12.4g}"
                     for p in PHASES)
        lines.append(f"  {r['trial'][:47]:<48}{r['rmse_N'] / k:>9.4g}{r['mean_N'] / k:>+10.3g}{ph}")
    return "\n".join(lines)


def fe_points(trials: list[TrialData], residuals: list[np.ndarray]) -> list[dict]:
    """The paper's f-e plot, one ellipse per trial: centre (force after 30 s of relaxation,
    mean error), radii (relaxation in the first 10 s, error std).

    The paper's holds last 60 s; for other holds the same fractions are used: the early
    phase (a sixth of the hold) for "10 s" and half the hold for "30 s"."""
    out = []
    for t, r in zip(trials, residuals, strict=True):
        early = np.flatnonzero(t.phase == "hold_early")
        hold = np.flatnonzero(np.isin(t.phase, ["hold_early", "hold_late"]))
        if len(early) < 2 or len(hold) < 4:
            continue
        ts = t.motion.t_s
        run = hold[: int(np.argmax(np.diff(hold) > 1)) + 1] if np.any(np.diff(hold) > 1) else hold
        t0, t_early, t_half = ts[run[0]], ts[early[0]] + (ts[early[-1]] - ts[early[0]]), \
            ts[run[0]] + 0.5 * (ts[run[-1]] - ts[run[0]])
        window = max(3, len(early) // 40)
        f0 = float(np.mean(t.force_N[run[0]:run[0] + window]))
        k_early = int(np.searchsorted(ts, t_early))
        f_early = float(np.mean(t.force_N[max(k_early - window, 0):k_early + window]))
        f_half = float(np.interp(t_half, ts, t.force_N))
        # the model error is measured - model; the paper plots the estimation error model - measured
        err = -r
        out.append({"trial": t.name, "force_30s_N": f_half, "mean_error_N": float(np.mean(err)),
                    "relax_10s_N": f0 - f_early, "std_error_N": float(np.std(err)),
                    "hold_s": float(ts[run[-1]] - t0)})
    return out


def _frozen(model: Model, values: dict[str, float]) -> Model:
    """`model` with the parameters `values` holds fixed there (bounds a billionth apart), all but
    the record's own."""
    def hold(p: Param) -> Param:
        if p.name not in values:
            return p
        v = values[p.name]
        tol = max(abs(v) * 1e-9, 1e-300)
        return replace(p, init=v, lo=v - tol, hi=v + tol, relative=False)

    # the record's own parameters (its contact point and zero) are what is left to fit
    return Model([e if e.of_record else replace(e, params=tuple(map(hold, e.params)))
                  for e in model.effects], model.name, model.records)
