"""`rig analyze --compare`: every named model fitted to the same records and ranked by the one
criterion with one noise."""

from __future__ import annotations

from dataclasses import dataclass

from rig.analysis.fitting.fit import FitResult, fit
from rig.analysis.stats import criterion
from rig.analysis.stats.noise import Noise
from rig.analysis.trials.data import PHASES, TrialData
from rig.models.catalogue import (
    build_model,
    named_models,
)
from rig.models.core import Effect


@dataclass
class Comparison:
    """Every named model fitted to the same records, ranked by one criterion with one noise."""

    results: list[FitResult]  # best first
    ranking: list[dict]  # model, parameters, bic, delta_bic, effective_samples (rig.analysis.stats.criterion)
    noise: Noise  # the one every model is judged against

    def json(self) -> dict:
        return {"criterion": criterion.DEFINITION, "noise_N": self.noise.std_N,
                "noise": self.noise.describe(), "noise_correlation_samples": self.noise.scale_samples,
                "ranking": self.ranking}


def compare(trials: list[TrialData], registry: dict[str, Effect]) -> Comparison:
    """Each named model fitted; one noise for all (the records' force at rest, else the residual of
    the model that fits best) and one BIC count (rig.analysis.stats.criterion)."""
    results = [fit(build_model(name, registry=registry), trials) for name in named_models(registry)]
    noise = min(results, key=lambda r: r.overall.rmse_N).noise  # measured with its own residual
    samples = [t.n for t in trials]
    rows = criterion.ranking({r.model.name: r.overall.n * r.overall.rmse_N ** 2 for r in results},
                             {r.model.name: len(r.model.params) for r in results}, samples, noise)
    order = {row["model"]: i for i, row in enumerate(rows)}
    return Comparison(sorted(results, key=lambda r: order[r.model.name]), rows, noise)


def format_compare(comparison: Comparison) -> str:
    """The comparison as a table, best first: each model's RMSE, mean, std, RMSE over the noise, dBIC and
    error by phase, then how the models were ranked."""
    results, noise_N = comparison.results, comparison.noise.std_N
    k, u = results[0].force_unit
    delta = {row["model"]: row["delta_bic"] for row in comparison.ranking}
    head = (f"{'model':<14}{'RMSE ' + u:>9}{'mean ' + u:>10}{'std ' + u:>9}{'/noise':>8}{'dBIC':>10}"
            + "".join(f"{p:>12}" for p in PHASES))
    lines = [head, "-" * len(head)]
    for r in results:
        ph = "".join(f"{(r.phases[p].rmse_N / k if r.phases[p] else float('nan')):>12.4g}" for p in PHASES)
        ratio = r.overall.rmse_N / noise_N if noise_N > 0 else float("inf")
        lines.append(f"{r.model.name:<14}{r.overall.rmse_N / k:>9.4g}{r.overall.mean_N / k:>+10.3g}"
                     f"{r.overall.std_N / k:>9.4g}{ratio:>8.1f}{delta[r.model.name]:>10.4g}{ph}"
                     + ("   adequate" if r.adequate else ""))
    lines.append(f"(sensor noise {noise_N / k:.4g} {u}, {comparison.noise.source}; "
                 f"{criterion.describe(comparison.noise, [t.n for t in results[0].trials])})")
    lines.append("")
    for r in results:
        params = ", ".join(f"{k} = {v:.4g}" for k, v in r.values.items())
        lines.append(f"{r.model.name}: {params}")
        for w in r.warnings:
            lines.append(f"    WARNING {w}")
    return "\n".join(lines)
