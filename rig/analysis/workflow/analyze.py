"""`rig analyze`: fit a model to trials, compare models, test on held-out trials, report."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from rig.analysis.fitting.fit import FitResult, error_table, evaluate, fit, with_record_params
from rig.analysis.stats import criterion
from rig.analysis.stats.noise import Noise
from rig.analysis.trials.data import PHASES, SEGMENTS, TrialData, prepare
from rig.errors import RigError, SpecError
from rig.models.catalogue import (
    CATALOGUE,
    CONTACT,
    CONTACT_POINT,
    NAMED_MODELS,
    build_model,
    contact_effect,
    named_models,
)
from rig.models.contact import Indenter, parse_indenter
from rig.models.core import Effect, Model, Param
from rig.models.instrument import ADHESION, BOTTOM_EFFECTS, BOTTOM_SHAPES, bottom_effect
from rig.models.plugins import check_plugin_effect, load_plugin
from rig.models.viscoelastic import MODELS as VISCOELASTIC_EFFECTS
from rig.records import ReadOptions, Record, read_record


@dataclass
class Inputs:
    trials: list[TrialData]
    holdout: list[TrialData]
    registry: dict[str, Effect]
    indenter: Indenter | None = None
    indenter_from: str = ""  # where the geometry came from: the command line, a file's header, a config
    poisson: float = 0.5


ROUND = ("paraboloid", "sphere")  # a bare shape that takes a file's radius


def _named_indenter(trials: list[Record]) -> tuple[Indenter, str] | None:
    """The indenter the records name (an instrument's header, a rig log's config), and where from;
    records that name different ones are refused rather than one of them chosen."""
    found = [(parse_indenter(t.meta["indenter"]), t) for t in trials if t.meta.get("indenter")]
    if not found:
        return None
    if len({ind for ind, _ in found}) > 1:
        raise RigError("the records name different indenters (" + ", ".join(f"{Path(t.name).name}: {ind.spec()}"
                       for ind, t in found) + "): analyse them apart, or give --indenter")
    ind, t = found[0]
    name = Path(t.name).name
    where = f"the config in {name}" if t.source == "mcap" else f"the header of {name}"
    return ind, where


def load_inputs(paths: list[str], holdout: list[str], plugins: list[str],
                options: ReadOptions | int | None = None, *, indenter: str | None = None,
                poisson: float = 0.5, segment: str = "all", records: list[Record] | None = None,
                form: str = "auto", approach: bool = False) -> Inputs:
    """The records prepared, and the catalogue with the user's effects and, when the indenter
    is known (`indenter`, else the first record that names its own), its elastic contact.
    `records`, when given, are the inputs already read (one per path: a batch reads a map once).
    `segment` "auto": an instrument's approach segment alone where the record has one and
    `approach` says the model is an elastic contact alone (what AFM tools fit), else all of it."""
    if not (math.isfinite(poisson) and -1.0 < poisson <= 0.5):
        raise RigError(f"--poisson {poisson:g}: Poisson's ratio lies in (-1, 0.5] (0.5: incompressible, "
                       "the usual choice for tissue and cells)")
    registry = dict(CATALOGUE)
    for p in plugins:
        for e in load_plugin(p):
            if e.name in CATALOGUE:
                raise RigError(f"{p}: effect '{e.name}' would replace the catalogue's; rename it")
            registry[e.name] = e
    recs = records if records is not None else [read_record(p, options) for p in paths]
    if segment not in (*SEGMENTS, "auto"):
        raise RigError(f"--segment {segment}: expected auto, {' or '.join(SEGMENTS)}")
    ind, source = None, ""
    named = _named_indenter(recs)
    shape = (indenter or "").strip().lower()
    if shape in ROUND and named and named[0].kind in ROUND:
        # a round shape alone takes its size from the file: `--indenter paraboloid` on a file that
        # names a sphere fits Hertz's approximation with the sphere's radius
        ind = parse_indenter(f"{shape}:R={named[0].R_m}m")
        source = f"--indenter, its radius from {named[1]}"
    elif indenter:
        try:
            ind, source = parse_indenter(indenter), "--indenter"
        except SpecError as exc:
            raise RigError(f"--indenter: {exc.message}") from None
    elif named:
        ind, source = named
    if ind is not None:
        registry[CONTACT] = contact_effect(ind, poisson)
        registry[CONTACT_POINT.name] = CONTACT_POINT
    # a pull on the way out is kept where adhesion can describe it: with an indenter's contact
    pull = ind is not None
    trials = [prepare(r, str(p), _segment(r, segment, approach), form, keep_pull=pull)
              for r, p in zip(recs, paths, strict=True)]
    thick = {t.meta.get("thickness_m") for t in trials}
    if ind is not None and ind.kind in BOTTOM_SHAPES and len(thick) == 1 and None not in thick:
        # the specimen's thickness, which the logs' header keeps: the bottom effect's, not fitted
        h = thick.pop()
        registry.update({n: bottom_effect(ind, poisson, bonded, h) for n, bonded in BOTTOM_EFFECTS.items()})
    held = []
    for p in holdout:
        r = read_record(p, options)
        held.append(prepare(r, str(p), _segment(r, segment, approach), "force" if form == "force" else "auto",
                            keep_pull=pull))
    for e in registry.values():
        if e.source == "plugin":
            m = build_model("linear_elastic", [e.name], registry)
            check_plugin_effect(e, lambda m=m: m.predict({p.name: p.init for p in m.params}, trials[0].motion))
    return Inputs(trials, held, registry, ind, source, poisson)


def _segment(rec: Record, segment: str, approach: bool) -> str:
    """The segment `prepare` is given for `rec` (see `load_inputs`)."""
    if segment != "auto":
        return segment
    has = rec.segment is not None and bool(np.any(rec.segment == "approach"))
    return "approach" if approach and has else "all"


# what a reader of the file recorded that qualifies every number fitted to it (rig.records): said in
# the text, the table and the map report, not only in --json's notes
CAVEAT_PHRASES = ("no spring constant", "t_s is the sample number", "does not mark the approach",
                  "no time column")


def caveats(t: TrialData) -> list[str]:
    """The record's notes that qualify what is fitted to it (no spring constant, time as the
    sample number, segments guessed)."""
    return [n for n in t.notes if any(p in n for p in CAVEAT_PHRASES)]


def elastic_only(model: str, add: list[str]) -> bool:
    """Whether a model is an indenter's elastic contact with nothing that needs the way out: no
    adhesion (the pull-off), no viscoelastic contact (the relaxation it shows on the retract)."""
    names = NAMED_MODELS.get(model, [model]) + list(add)
    return CONTACT in names and not any(n == ADHESION or n in VISCOELASTIC_EFFECTS.values() for n in names)


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


def format_holdout(rows: list[dict], unit: tuple[float, str] = (1.0, "N")) -> str:
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
