"""One `rig analyze` request carried out: fit, before and after an addition, comparison,
held-out trials, diagnosis, designed protocol, stepwise search, saved model, report; what it
finds as the JSON document (SI) and as the text a person reads (the record's units)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rig.analysis.diagnosis.explain import AUTO_STEPS, auto, explain, format_auto, format_explain
from rig.analysis.fitting.fit import FitResult, fit
from rig.analysis.intervals.systematic import Systematic, interval, systematic
from rig.analysis.material.creep import creep_json, format_creep
from rig.analysis.material.modulus import format_modulus, format_pa, modulus_vs_depth, plateau_drift
from rig.analysis.trials.data import PHASES
from rig.analysis.workflow.compare import compare, format_compare
from rig.analysis.workflow.inputs import caveats, elastic_only, load_inputs
from rig.analysis.workflow.report import write_report
from rig.analysis.workflow.results import _finite, format_holdout, format_placement, holdout_json, result_json
from rig.errors import RigError, did_you_mean
from rig.models.catalogue import CONTACT, build_model
from rig.records import ReadOptions


@dataclass
class AnalyzeRequest:
    """One `rig analyze` as fields: the ``inputs`` (files, or ``records`` already read), the
    ``model`` and the effects to ``add``, what to do beyond the fit (``explain``, ``auto``,
    ``compare``, ``design``, ``bootstrap``, ``profile``, ``save``, ``report``) and how to read the
    records (``indenter``, ``segment``, ``form``, ``curve``, the AFM calibration). The command
    line's options map onto these one to one."""

    inputs: list[str]
    model: str = "proposed"
    add: list[str] = field(default_factory=list)
    holdout: list[str] = field(default_factory=list)
    plugins: list[str] = field(default_factory=list)
    block: int | None = None
    compare: bool = False
    explain: bool = False
    auto: bool = False
    auto_steps: int | None = None  # with auto: at most this many steps (None: AUTO_STEPS)
    design: str | None = None  # where a designed protocol is written
    design_config: Any = None  # the rig (RigConfig) whose limits it must respect
    save: str | None = None
    report: str | None = None
    indenter: str | None = None  # spec string; else the record's own header
    poisson: float = 0.5
    segment: str = "auto"  # "approach", "all", or auto: the approach for an elastic contact (load_inputs)
    form: str = "auto"  # creep form where a controller held the force; "force": force form throughout
    curve: int | None = None  # an AFM map's curve, as the instrument numbers it
    spring_constant_N_per_m: float | None = None
    sensitivity_m_per_V: float | None = None
    bootstrap: int | None = None  # draws of the parametric bootstrap (rig.analysis.intervals.bootstrap)
    # profile-likelihood intervals: of the parameters named, or (True, or no names) of those that trade off
    profile: bool | list[str] | None = None
    progress: Any = None  # called with (draws done, draws) as the bootstrap goes
    records: list | None = None  # the inputs already read (rig.records.Record, one per input): a batch's
    row_only: bool = False  # a batch's row: the JSON without the modulus by depth, and no text


@dataclass
class Analysis:
    """What `analyze` gives: the result as JSON (``json``, what ``--json`` prints) and as the
    text the command prints (``text``)."""

    json: dict
    text: str


# The order the text's sections are printed in; each is written once, with its JSON (`_Sections`).
TEXT_ORDER = ("fit", "creep", "material", "compare", "holdout", "profile", "bootstrap", "explain", "design",
              "auto", "report", "saved")


class _Sections:
    """The JSON document and the text, filled together: each part of an analysis says its data
    and its words in one place. The words are a function, called only when text is wanted (a
    batch's row has none, and formatting a curve's report costs as much as parts of its fit)."""

    def __init__(self, out: dict, quiet: bool) -> None:
        self.json = out
        self.quiet = quiet
        self.text: dict[str, str] = {}

    def add(self, key: str, data: Any, text: Callable[[], str] | None = None) -> None:
        self.json[key] = data
        self.say(key, text)

    def say(self, key: str, text: Callable[[], str] | None) -> None:
        if text is not None and not self.quiet:
            words = text()
            if words:
                self.text[key] = words

    def joined(self) -> str:
        unplaced = set(self.text) - set(TEXT_ORDER)
        assert not unplaced, f"text without a place in TEXT_ORDER: {unplaced}"
        return "\n\n".join(self.text[k] for k in TEXT_ORDER if k in self.text)


def analyze(req: AnalyzeRequest) -> Analysis:
    """Run one `rig analyze`: read the records, build the model, fit it (with the systematic
    error and the modulus where the model holds an indenter's contact), and do what the request asks
    beyond that. Bad input raises `RigError` with what is wrong and where."""
    options = ReadOptions(curve=req.curve, spring_constant_N_per_m=req.spring_constant_N_per_m,
                          sensitivity_m_per_V=req.sensitivity_m_per_V, block=req.block)
    inputs = load_inputs(req.inputs, req.holdout, req.plugins, options, indenter=req.indenter,
                         poisson=req.poisson, segment=req.segment, records=req.records, form=req.form,
                         approach=elastic_only(req.model, req.add))
    model = build_model(req.model, req.add, inputs.registry)
    _refuse_early(req, model, inputs)
    before, res = _fitted(req, model, inputs)
    out = _Sections(result_json(res, req.inputs), quiet=req.row_only)
    out.say("fit", lambda: (format_before_after(before, res) if before is not None
                            else f"{res.report()}\nfitted in {res.seconds:.2f} s"))
    creep_rows = creep_json(res, inputs.indenter, inputs.poisson) if any(t.creep for t in res.trials) else []
    if creep_rows:
        out.add("creep", creep_rows, lambda: format_creep(creep_rows, res, inputs.indenter))
    sys_err = systematic(res) if res.model.has(CONTACT) and inputs.indenter is not None else None
    if sys_err is not None:
        out.add("systematic", sys_err.as_dict())
        for k, p in out.json["parameters"].items():
            p["sys"] = sys_err.error.get(k)
    material = material_json(res, inputs, depth=not req.row_only, sys_err=sys_err)
    if material:
        out.add("material", material, lambda: format_material(material, res))
    else:
        out.say("material", lambda: format_placement(res))
    if before is not None:
        out.add("before_add", result_json(before, req.inputs))
    comparison = compare(inputs.trials, inputs.registry) if req.compare else None
    if comparison:
        out.add("compare", [result_json(r, req.inputs) for r in comparison.results],
                lambda: format_compare(comparison))
        out.add("compare_ranking", comparison.json())
    held = holdout_json(res, inputs.holdout) if inputs.holdout else None
    if held:
        out.add("holdout", held, lambda: format_holdout(held, res.force_unit))
    if req.bootstrap:
        from rig.analysis.intervals.bootstrap import bootstrap, format_bootstrap

        boot = bootstrap(res, req.bootstrap, progress=req.progress)
        out.add("bootstrap", boot.as_dict(), lambda: format_bootstrap(boot, res))
    if req.profile is not None and req.profile is not False:
        _profile(req, res, out)
    ex = explain(res, inputs.registry) if req.explain else None
    if ex is not None:
        out.add("suggestions", [s.as_dict() for s in ex.suggestions])
        out.say("explain", lambda: format_explain(ex))
        out.add("indistinguishable", ex.indistinguishable)
        out.add("diagnosis", ex.verdict())
        out.add("effective_samples", ex.n_eff)
    if req.design:
        _design(req, ex, out)
    steps = auto(res, inputs.registry, max_steps=req.auto_steps or AUTO_STEPS) if req.auto else None
    if steps is not None:
        out.add("auto", [_auto_step(s) for s in steps],
                lambda: "stepwise: add the best effect while the error falls (criterion: BIC on effective "
                        f"samples)\n{format_auto(steps)}")
        out.add("auto_final", result_json(steps[-1]["fit"], req.inputs))
    if req.save:
        from rig.models.saved import from_fit, save

        saved = str(save(from_fit(res, req.inputs), req.save))
        out.add("saved", saved,
                lambda: f"model saved: {saved} (run it in the loop: rig run PROTOCOL --model {saved})")
    if req.report:
        path = str(write_report(res, req.report, compare=comparison.results if comparison else None,
                                holdout=held, text=format_compare(comparison) if comparison else "",
                                before=before, steps=steps,
                                explain_text=format_explain(ex) if ex else "",
                                creep_text=format_creep(creep_rows, res, inputs.indenter),
                                material_text=format_material(material, res) if material else ""))
        out.add("report", path, lambda: f"report: {path}")
    return Analysis(out.json, out.joined())


def _refuse_early(req: AnalyzeRequest, model, inputs) -> None:
    """What the request cannot do, said before any fit."""
    if req.save:
        from rig.models.saved import savable

        why = savable(model)
        if why:
            raise RigError(f"--save: {why}")
    if model.has("contact_point") and len(inputs.trials) + len(inputs.holdout) > 1:
        # the material report (E, its depth profile, the contact) is one curve's
        raise RigError(f"the {req.model} model fits one curve at a time (each has its own contact point): "
                       "give one record, or pick one curve of a map with --curve")


def _fitted(req: AnalyzeRequest, model, inputs) -> tuple[FitResult | None, FitResult]:
    """The fit, and with --add the model's fit before the addition."""
    before = fit(build_model(req.model, [], inputs.registry), inputs.trials) if req.add else None
    res = fit(model, inputs.trials)
    if before is not None:
        # from the model's own fit, the added effect at its starting value changes little: the
        # error can only fall from there, where a start from the catalogue may find a worse optimum
        warm = fit(model, inputs.trials, starts=1, initial=before.values)
        res = min(res, warm, key=lambda r: r.overall.rmse_N)
    return before, res


def _profile(req: AnalyzeRequest, res: FitResult, out: _Sections) -> None:
    """--profile: of the parameters named, or (none named) of those that trade off."""
    from rig.analysis.intervals.profile import format_intervals, intervals

    asked = req.profile if isinstance(req.profile, list) and req.profile else None
    if asked:
        unknown = [n for n in asked if n not in res.values]
        if unknown:
            raise RigError(f"--profile {unknown[0]}: not a parameter of the {res.model.name} model"
                           f"{did_you_mean(unknown[0], list(res.values))} (its parameters: "
                           f"{', '.join(res.values)})")
    profiled = intervals(res, asked)
    out.add("profile", {iv.name: iv.as_dict() for iv in profiled},
            lambda: format_intervals(profiled, res, asked=asked is not None))


def _design(req: AnalyzeRequest, ex, out: _Sections) -> None:
    from rig.analysis.diagnosis.design import NOTHING_TO_SETTLE, design, format_design, write_design

    d = design(ex, req.design_config)
    if d is None:
        out.add("design", {"file": None, "text": NOTHING_TO_SETTLE}, lambda: f"design: {NOTHING_TO_SETTLE}")
    else:
        out.add("design", {"file": str(write_design(d, req.design)), **d.as_dict()},
                lambda: format_design(d, req.design))


def _auto_step(s: dict) -> dict:
    return {"step": s["step"], "added": s["added"], "removed": s.get("removed"), "model": s["fit"].model.name,
            "rmse_N": s["fit"].overall.rmse_N,
            "phases": {k: (v.rmse_N if v else None) for k, v in s["fit"].phases.items()},
            "delta_bic": s["delta_bic"], "adequate": s["fit"].adequate, "why": s.get("why", ""),
            "stopped": s.get("stopped", "")}


def format_before_after(before: FitResult, after: FitResult) -> str:
    """The fit before and after an addition side by side (the errors overall and by phase, and
    whether each is adequate), how far the error falls, then the new fit's report."""
    k, u = after.force_unit
    added = [e for e in after.model.effect_names if e not in before.model.effect_names]
    rows = [("", before.model.name, after.model.name),
            (f"RMSE ({u})", f"{before.overall.rmse_N / k:.4g}", f"{after.overall.rmse_N / k:.4g}"),
            (f"mean ({u})", f"{before.overall.mean_N / k:+.4g}", f"{after.overall.mean_N / k:+.4g}"),
            (f"std ({u})", f"{before.overall.std_N / k:.4g}", f"{after.overall.std_N / k:.4g}")]
    for ph in PHASES:
        a, b = before.phases[ph], after.phases[ph]
        rows.append((f"{ph} RMSE", f"{a.rmse_N / k:.4g}" if a else "-", f"{b.rmse_N / k:.4g}" if b else "-"))
    rows.append(("adequate", str(before.adequate).lower(), str(after.adequate).lower()))
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    lines = [f"adding {', '.join(added)}: before and after (noise {after.force_text(after.noise_N)})"]
    lines += [f"  {r[0]:<{w0}}  {r[1]:>{w1}}  {r[2]}" for r in rows]
    drop = 1 - after.overall.rmse_N / before.overall.rmse_N
    lines.append(f"  error {'falls' if drop > 0 else 'rises'} by {abs(drop) * 100:.1f} %")
    lines.append("")
    lines.append(after.report())
    return "\n".join(lines)


def material_json(res: FitResult, inputs, depth: bool = True, sys_err: Systematic | None = None) -> dict:
    """The indenter, Poisson's ratio, the contact point and the modulus by depth (SI; `depth`
    False leaves it out), when the model holds the indenter's elastic contact; the instrument's
    own result where a file has one.

    Every error is named for what it is: `_stat` the statistical (the noise's, given the model),
    `_sys` the systematic (how far the fit's own choices move the value beyond their noise:
    rig.analysis.intervals.systematic; 0 where none did, None where not measured), `_interval` the two
    together, value +/- (1.96 stat + sys)."""
    if not res.model.has(CONTACT) or inputs.indenter is None:
        return {}
    e_stat = _finite(res.stderr.get("E_Pa"))
    e_sys = sys_err.error.get("E_Pa") if sys_err is not None else None
    out: dict = {"indenter": inputs.indenter.spec(), "indenter_description": inputs.indenter.describe(),
                 "indenter_from": inputs.indenter_from, "poisson": inputs.poisson,
                 "E_Pa": res.values["E_Pa"], "E_Pa_stat": e_stat, "E_Pa_sys": e_sys,
                 "E_Pa_interval": interval(res.values["E_Pa"], e_stat, e_sys),
                 "E_Pa_sys_from": sys_err.why("E_Pa") if sys_err is not None else None,
                 "E_Pa_sys_not_made": list(sys_err.not_made) if sys_err is not None else [],
                 "E_Pa_refits": [{"choice": c.name, "E_Pa": c.values["E_Pa"],
                                  "counted": c.counted.get("E_Pa", False)}
                                 for c in sys_err.choices if "E_Pa" in c.values]
                 if sys_err is not None else None}
    t0 = res.trials[0]
    out["segment"] = "approach" if "the approach segment only" in t0.notes else "all"
    out["caveats"] = caveats(t0)
    placed = res.placements()  # hertz fits one record
    if "contact_point_m" in placed[0]:
        # the contact point in the record's own travel from its first sample
        out["contact_point_m"] = [row["contact_point_m"] for row in placed]
        out["contact_point_m_stat"] = placed[0]["contact_point_m_stderr"]
        x_c = next((k for k in res.values if k.partition("@")[0] == "x_c_m"), None)
        out["contact_point_m_sys"] = sys_err.error.get(x_c) if sys_err is not None and x_c else None
    if depth:
        rows = modulus_vs_depth(res)
        out["modulus_vs_depth"] = rows
        out["modulus_drift"] = plateau_drift(rows)
    own = [{"trial": t.name, **t.meta["instrument_result"]} for t in res.trials
           if t.meta.get("instrument_result")]
    if own:
        out["instrument_result"] = own
    return out


def _law_differs(theirs: str | None, spec: str) -> str:
    """Why this fit's E and the instrument's may differ by law alone ('' when they use the same)."""
    if not theirs or "hertz" not in theirs.lower() or not spec.startswith("sphere"):
        return ""
    return ("the instrument fitted Hertz's paraboloid; this fit uses the header's sphere through Sneddon's "
            "exact law, which differs with depth over radius: give --indenter paraboloid to fit as it did")


def format_material(m: dict, res: FitResult) -> str:
    """The modulus in words: E with its statistical and systematic errors and interval, the indenter
    and where it came from, the refits behind the systematic error, and the contact point."""
    err, sys = m["E_Pa_stat"], m.get("E_Pa_sys")
    e = f" +/- {format_pa(err)} (stat)" if err is not None else ""  # finite or None (material_json)
    if sys is not None:
        e += f" +/- {format_pa(sys)} (sys)" if sys > 0 else " +/- 0 (sys)"
    lines = [f"material   E = {format_pa(m['E_Pa'])}{e}  ({m['indenter_description']}, "
             f"from {m['indenter_from']}; Poisson's ratio {m['poisson']:g})"]
    iv = m.get("E_Pa_interval")
    if iv is not None and sys is not None:
        lines.append(f"           95 % interval {format_pa(iv[0])} to {format_pa(iv[1])} (1.96 stat + sys)")
        refits = m.get("E_Pa_refits") or []
        if refits:
            lines.append("refits     " + ", ".join(f"{r['choice']} {format_pa(r['E_Pa'])}"
                                                  + ("*" if r["counted"] else "") for r in refits))
            if any(r["counted"] for r in refits):
                lines.append("           (* moved beyond its noise: counted in sys; stat is the noise's, given "
                             "the model)")
        for why in m.get("E_Pa_sys_not_made") or []:
            lines.append(f"           not refitted {why}: sys leaves that choice out")
    if "contact_point_m" in m:
        k, u = res.trials[0].length_unit
        cp = ", ".join(f"{c / k:.4g}" for c in m["contact_point_m"])
        ce, cs = m.get("contact_point_m_stat"), m.get("contact_point_m_sys")
        lines.append(f"contact    at {cp} {u} of travel"
                     + (f" +/- {ce / k:.2g} {u} (stat)" if ce is not None else "")
                     + (f" +/- {cs / k:.2g} {u} (sys)" if cs else "")
                     + " (fitted; x_c_m above counts it from the first estimate)")
    if m.get("segment"):
        lines.append("fitted on  " + ("the approach (the default for an elastic contact on a curve with "
                                      "segments; --segment all adds the retract)" if m["segment"] == "approach"
                                      else "the whole record, approach and retract"))
    for c in m.get("caveats", []):
        lines.append(f"CAVEAT     {c}")
    depth = format_modulus(m.get("modulus_vs_depth", []), res.trials[0].length_unit)
    if depth:
        lines.append(depth)
    for own in m.get("instrument_result", []):
        if own.get("E_Pa") is not None:
            ratio = m["E_Pa"] / own["E_Pa"] - 1.0
            how = ", ".join(x for x in (own.get("model"), f"Poisson {own['poisson']:g}"
                                         if own.get("poisson") is not None else None) if x)
            lines.append(f"instrument {own['trial']}: its own fit gives E = {format_pa(own['E_Pa'])}"
                         + (f" ({how})" if how else "")
                         + f"; this fit {ratio * 100:+.1f} %")
            law = _law_differs(own.get("model"), m["indenter"])
            if law:
                lines.append(f"CAVEAT     {law}")
    return "\n".join(lines)

