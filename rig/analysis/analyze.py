"""`rig analyze`: fit a model to trials, compare models, test on held-out trials, report."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rig.analysis.data import PHASES, TrialData, load_trial
from rig.analysis.fit import FitResult, error_table, evaluate, fit
from rig.errors import RigError
from rig.models.catalogue import CATALOGUE, NAMED_MODELS, build_model
from rig.models.core import Effect
from rig.models.plugins import check_plugin_effect, load_plugin


@dataclass
class Inputs:
    trials: list[TrialData]
    holdout: list[TrialData]
    registry: dict[str, Effect]


def load_inputs(paths: list[str], holdout: list[str], plugins: list[str]) -> Inputs:
    registry = dict(CATALOGUE)
    for p in plugins:
        for e in load_plugin(p):
            if e.name in CATALOGUE:
                raise RigError(f"{p}: effect '{e.name}' would replace the catalogue's; rename it")
            registry[e.name] = e
    trials = [load_trial(p) for p in paths]
    held = [load_trial(p) for p in holdout]
    for e in registry.values():
        if e.source == "plugin":
            m = build_model("linear_elastic", [e.name], registry)
            check_plugin_effect(e, lambda m=m: m.predict({p.name: p.init for p in m.params}, trials[0].motion))
    return Inputs(trials, held, registry)


def result_json(res: FitResult, paths: list[str]) -> dict:
    units = {p.name: p.unit for p in res.model.params}
    return {
        "model": res.model.name,
        "effects": res.model.effect_names,
        "trials": paths,
        "parameters": {k: {"value": v, "stderr": res.stderr.get(k), "unit": units[k]}
                       for k, v in res.values.items()},
        "fit": {"rmse_N": res.overall.rmse_N, "mean_N": res.overall.mean_N, "std_N": res.overall.std_N,
                "noise_N": res.noise_N, "noise_source": res.noise_source, "bic": res.bic,
                "seconds": res.seconds},
        "phases": {ph: (s.as_dict() if s else None) for ph, s in res.phases.items()},
        "per_trial": res.per_trial,
        "adequate": res.adequate,
        "warnings": res.warnings,
        "suggestions": [],
    }


def holdout_json(res: FitResult, held: list[TrialData]) -> list[dict]:
    out = []
    preds = evaluate(res.model, res.values, held)
    for t, p in zip(held, preds, strict=True):
        overall, phases = error_table([t], [t.force_N - p])
        out.append({"trial": t.name, **overall.as_dict(),
                    "phases": {k: (v.as_dict() if v else None) for k, v in phases.items()}})
    return out


def compare(trials: list[TrialData], registry: dict[str, Effect]) -> list[FitResult]:
    return [fit(build_model(name, registry=registry), trials) for name in NAMED_MODELS]


def format_compare(results: list[FitResult], noise_N: float) -> str:
    head = f"{'model':<14}{'RMSE N':>8}{'mean N':>9}{'std N':>8}" + "".join(f"{p:>12}" for p in PHASES)
    lines = [head, "-" * len(head)]
    for r in results:
        ph = "".join(f"{(r.phases[p].rmse_N if r.phases[p] else float('nan')):>12.4f}" for p in PHASES)
        lines.append(f"{r.model.name:<14}{r.overall.rmse_N:>8.4f}{r.overall.mean_N:>+9.4f}"
                     f"{r.overall.std_N:>8.4f}{ph}" + ("   adequate" if r.adequate else ""))
    lines.append(f"(sensor noise {noise_N:.4f} N)")
    lines.append("")
    for r in results:
        params = ", ".join(f"{k} = {v:.4g}" for k, v in r.values.items())
        lines.append(f"{r.model.name}: {params}")
        for w in r.warnings:
            lines.append(f"    WARNING {w}")
    return "\n".join(lines)


def format_holdout(rows: list[dict]) -> str:
    lines = ["held-out trials (parameters from the fit above)",
             f"  {'trial':<48}{'RMSE N':>8}{'mean N':>9}" + "".join(f"{p:>12}" for p in PHASES)]
    for r in rows:
        ph = "".join(f"{(r['phases'][p]['rmse_N'] if r['phases'][p] else float('nan')):>12.4f}" for p in PHASES)
        lines.append(f"  {r['trial'][:47]:<48}{r['rmse_N']:>8.4f}{r['mean_N']:>+9.4f}{ph}")
    return "\n".join(lines)


def fe_points(trials: list[TrialData], residuals: list[np.ndarray]) -> list[dict]:
    """The paper's f-e plot, one ellipse per trial: centre (force after 30 s of relaxation,
    mean error), radii (relaxation in the first 10 s, error std)."""
    out = []
    for t, r in zip(trials, residuals, strict=True):
        hold = np.flatnonzero(np.isin(t.phase, ["hold_early", "hold_late"]))
        if len(hold) == 0:
            continue
        t0 = t.motion.t_s[hold[0]]
        f_at = lambda dt, t=t, t0=t0: float(np.interp(t0 + dt, t.motion.t_s, t.force_N))  # noqa: E731
        window = 0.25
        f0 = float(np.mean(t.force_N[(t.motion.t_s >= t0) & (t.motion.t_s < t0 + window)]))
        f10 = float(np.mean(t.force_N[(t.motion.t_s >= t0 + 10 - window) & (t.motion.t_s < t0 + 10 + window)]))
        f30 = f_at(30.0)
        # the model error is measured - model; the paper plots the estimation error model - measured
        err = -r
        out.append({"trial": t.name, "force_30s_N": f30, "mean_error_N": float(np.mean(err)),
                    "relax_10s_N": f0 - f10, "std_error_N": float(np.std(err))})
    return out
