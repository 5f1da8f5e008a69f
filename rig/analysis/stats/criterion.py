"""One criterion for every comparison of models: BIC on one effective sample count.

    BIC = N_eff ln(RSS / N) + k ln(N_eff),  N_eff = sum over records of n_i / L

L is the noise's integral time scale (samples per independent value, from its measured spectrum:
rig.analysis.stats.noise), so N_eff is a property of the records and their sensor, the same for every
model fitted to them. That is what makes differences of BIC mean something: a force unit adds
N_eff ln(c^2) to every model's BIC alike, and drops out of every difference. (A count taken
from each model's own residual weighs that constant differently per model: the ranking then
depends on the unit the forces happen to be in, and two nearly equal misfits can get counts
37x apart.)

`--explain` compares a model with its candidates the same way, at one count for all of them:
the base model's residual count (rig.analysis.diagnosis.explain).
"""

from __future__ import annotations

import math

from rig.analysis.stats.noise import Noise

DEFINITION = ("N_eff ln(RSS / N) + k ln(N_eff), N_eff = the records' samples over the noise's correlation "
              "time, one count for every model")


def noise_count(samples: list[int], noise: Noise) -> float:
    """Independent samples in records of `samples` each, carrying `noise` (at least 10)."""
    return max(sum(samples) / max(noise.scale_samples, 1.0), 10.0)


def ranking(rss: dict[str, float], params: dict[str, int], samples: list[int], noise: Noise) -> list[dict]:
    """Models (name: RSS in N^2, name: parameter count) ranked by BIC on one count, best first,
    with each BIC's difference from the best."""
    n = sum(samples)
    n_eff = noise_count(samples, noise)
    rows = [{"model": m, "parameters": params[m], "bic": bic(rss[m], n, params[m], n_eff)} for m in rss]
    rows.sort(key=lambda r: r["bic"])
    for r in rows:
        r["delta_bic"] = r["bic"] - rows[0]["bic"]
        r["effective_samples"] = n_eff
    return rows


def describe(noise: Noise, samples: list[int]) -> str:
    """The criterion in words, with this record's effective sample count and the noise's correlation time."""
    return (f"ranked by BIC = N_eff ln(RSS / N) + k ln(N_eff), one N_eff for every model: "
            f"{noise_count(samples, noise):.4g} of {sum(samples)} samples, the noise correlated over "
            f"{noise.scale_samples:.3g}")


def bic(rss: float, n: int, k: int, n_eff: float) -> float:
    """BIC on the effective number of independent residuals, N_eff = N / L:

        BIC = N_eff ln(RSS / N) + k ln(N_eff)

    A white residual keeps N_eff = N (the textbook BIC); a correlated one counts each
    independent stretch once instead of every sample. Two models are compared at the same
    N_eff (the simpler model's), so their difference is N_eff ln(RSS_1 / RSS_0) + dk ln(N_eff)."""
    return float(n_eff * math.log(max(rss / max(n, 1), 1e-300)) + k * math.log(max(n_eff, 1.0)))


def delta_bic(rss_ratio: float, dk: int, n_eff: float) -> float:
    """`bic` of a model with `dk` more parameters and `rss_ratio` times the RSS, minus the
    simpler model's, both at the simpler model's N_eff."""
    return bic(rss_ratio, 1, dk, n_eff) - bic(1.0, 1, 0, n_eff)
