"""What a fit in creep form says in its own terms: the position it predicts where the force was
held, its miss as a length, and the creep compliance J(t) where the indenter is known.

A record's held samples (`TrialData.held`) are fitted in creep form: the model predicts the
position from the force (`rig.models.creep`) and the fit weighs the miss by the record's creep
weight (force noise over length noise, `rig.analysis.trials.data.creep_weight`). Here the miss is
given back as a length, step by step (each run of held samples: a force ramp, a force hold).

Creep compliance: under a force held at F, an elastic contact's law F = E g(d) (g the
indenter's geometric factor, `rig.models.contact.geometry_factor`) becomes, for a linear
viscoelastic material by the correspondence principle (Lee and Radok 1960, for a load that
does not fall), g(d(t)) = F J(t). So J(t) = g(d(t)) / F(t), read from the measured indentation
and from the model's, in 1/Pa; 1/J is the apparent modulus at each moment of the hold.
"""

from __future__ import annotations

import numpy as np

from rig.analysis.fitting.fit import FitResult, predict_position
from rig.models.contact import Indenter, geometry_factor

J_TIMES = (0.0, 0.25, 0.5, 1.0)  # where in each held step J(t) is given (fraction of the step)


def _runs(held: np.ndarray, phase: np.ndarray) -> list[np.ndarray]:
    """The held steps: runs of held samples, a force ramp apart from the hold it leads to."""
    stage = np.where(phase == "ramp", 1, 2) * held
    edges = np.flatnonzero(np.diff(stage)) + 1
    return [r for r in np.split(np.arange(len(held)), edges) if held[r[0]]]


def creep_json(res: FitResult, indenter: Indenter | None = None, poisson: float = 0.5) -> list[dict]:
    """Per record fitted partly in creep form: its held samples, the position's miss there (RMSE,
    against the length noise), and per held step the creep measured and predicted and, with an
    indenter, J(t) at J_TIMES of the step."""
    out = []
    for k, (t, r) in enumerate(zip(res.trials, res.residuals, strict=True)):
        if not t.creep:
            continue
        x_pred = predict_position(res.model, res.values, t)
        w = t.creep_weight_N_per_m
        miss = r[t.held] / w
        noise_m = res.noise_N / w
        row: dict = {"trial": t.name, "held_samples": int(t.held.sum()), "weight_N_per_m": w,
                     "position_rmse_m": float(np.sqrt(np.mean(miss ** 2))), "length_noise_m": noise_m,
                     "rmse_over_noise": float(np.sqrt(np.mean(miss ** 2)) / noise_m) if noise_m > 0 else None,
                     "steps": []}
        x0 = res.contact_m(k)
        for run in _runs(t.held, t.phase):
            ts, xm, xp, f = t.motion.t_s[run], t.motion.x_m[run], x_pred[run], t.held_force_N[run]
            step = {"t_start_s": float(ts[0] - t.motion.t_s[0]), "t_end_s": float(ts[-1] - t.motion.t_s[0]),
                    "force_N": float(np.median(f)), "creep_m": float(xm[-1] - xm[0]),
                    "creep_model_m": float(xp[-1] - xp[0]),
                    "position_rmse_m": float(np.sqrt(np.mean((xm - xp) ** 2)))}
            if indenter is not None and len(run) > 1:
                at = [min(round(q * (len(run) - 1)), len(run) - 1) for q in J_TIMES]
                F = np.maximum(f[at], np.finfo(float).tiny)
                step["J_t_s"] = [float(ts[i] - ts[0]) for i in at]
                step["J_per_Pa"] = (geometry_factor(indenter, xm[at] - x0, poisson) / F).tolist()
                step["J_model_per_Pa"] = (geometry_factor(indenter, xp[at] - x0, poisson) / F).tolist()
            row["steps"].append(step)
        out.append(row)
    return out


def format_creep(rows: list[dict], res: FitResult, indenter: Indenter | None = None) -> str:
    """Creep form in the record's own units: the position's miss, each held step's creep, J(t)."""
    if not rows:
        return ""
    k, u = res.trials[0].length_unit
    lines = []
    for row in rows:
        ratio = row["rmse_over_noise"]
        lines.append(f"creep form {row['trial']}: {row['held_samples']} samples where the force was held; "
                     f"position RMSE {row['position_rmse_m'] / k:.4g} {u} (length noise "
                     f"{row['length_noise_m'] / k:.3g} {u}"
                     + (f", {ratio:.2g}x" if ratio is not None else "") + ")")
        for s in row["steps"]:
            text = (f"  held {s['t_start_s']:.4g}-{s['t_end_s']:.4g} s at {res.force_text(s['force_N'])}: "
                    "crept "
                    f"{s['creep_m'] / k:.4g} {u} (model {s['creep_model_m'] / k:.4g} {u})")
            if "J_per_Pa" in s:
                text += "; J(t) " + ", ".join(f"{t:.3g} s: {j:.3g} (model {jm:.3g})" for t, j, jm in
                                              zip(s["J_t_s"], s["J_per_Pa"], s["J_model_per_Pa"], strict=True))
                text += " 1/Pa"
            lines.append(text)
    if indenter is None:
        lines.append("  (creep compliance J(t) needs the indenter: give --indenter, or probe: in the rig "
                     "config)")
    return "\n".join(lines)
