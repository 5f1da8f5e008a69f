"""Reports: measured and model force with the phases shaded and the residual below, error by
phase, the paper's f-e ellipse plot for several trials, and a report.md tying them together."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rig.analysis.fitting.fit import FitResult, predict_position
from rig.analysis.trials.data import PHASES
from rig.analysis.workflow.results import fe_points
from rig.models.catalogue import CONTACT
from rig.views.plots import figure, save, shade_spans, trial_labels

PHASE_COLOURS = {"ramp": "#cfe3f7", "hold_early": "#d8f0d2", "hold_late": "#eaf7e6", "return": "#f7d9d4"}


def _shade(ax, t: np.ndarray, phase: np.ndarray) -> None:
    shade_spans(ax, t, phase, PHASE_COLOURS)


def phases_present(phase: np.ndarray) -> list[str]:
    """The phases the record has, in PHASES order (an approach-only curve has no hold, no return)."""
    have = set(np.asarray(phase).tolist())
    return [p for p in PHASES if p in have]


def fit_figure(res: FitResult, k: int, title_extra: str = ""):
    """Measured and model force against time, the phases the record has shaded, the residual
    below: a matplotlib Figure (nothing written)."""
    from matplotlib.patches import Patch

    tr = res.trials[k]
    t = tr.motion.t_s
    kf, u = tr.force_unit
    fig = figure(figsize=(10, 6.5))
    ax, axr = fig.subplots(2, 1, sharex=True, height_ratios=[3, 1.3])
    _shade(ax, t, tr.phase)
    ax.plot(t, tr.force_N / kf, color="k", lw=0.7, label="measured")
    ax.plot(t, res.predictions[k] / kf, color="tab:red", lw=1.4, label=f"model: {res.model.name}")
    ax.set_ylabel(f"force ({u})")
    handles, labels = ax.get_legend_handles_labels()
    present = phases_present(tr.phase)
    handles += [Patch(color=PHASE_COLOURS[p]) for p in present]
    ax.legend(handles, labels + present, fontsize=8, ncol=len(present) + 2 if len(present) < 3 else 3,
              loc="best")
    ax.set_title(f"{tr.name}{title_extra}\nRMSE {res.force_text(res.per_trial[k]['rmse_N'])} "
                 f"(noise {res.force_text(res.noise_N)})", fontsize=9)
    _shade(axr, t, tr.phase)
    axr.plot(t, res.residuals[k] / kf, color="tab:blue", lw=0.6)
    axr.axhline(0, color="k", lw=0.6)
    for s in (-2, 2):
        axr.axhline(s * res.noise_N / kf, color="grey", lw=0.6, ls="--")
    axr.set_ylabel(f"residual ({u})\nmeasured - model")
    axr.set_xlabel("time (s)")
    return fig


def plot_trial_fit(res: FitResult, k: int, out: Path, title_extra: str = "") -> Path:
    """Trial `k`'s measured and model force with its phases and residual, saved to `out`."""
    return save(fit_figure(res, k, title_extra), out)


def has_contact(res: FitResult, k: int) -> bool:
    """Whether record k has an indentation to draw force against: an elastic contact law, a
    fitted contact point, or a contact the analysis found in the record (an AFM curve)."""
    names = {p.rpartition("@")[0] or p for p in res.values}
    return res.model.has(CONTACT) or "x_c_m" in names or res.trials[k].contact_m is not None


def contact_curve(res: FitResult, k: int) -> dict | None:
    """Record k against its indentation (SI): `indentation_m` past the fitted contact point,
    `separation_m` (tip-sample separation, -indentation; None unless the cantilever's deflection
    was taken off the travel), `force_N`, `model_N`, `residual_N`, `branch` per sample
    ("approach", "dwell", "retract"), `contact_force_N` (the model's force at the contact point)
    and `contact_travel_m` (the contact in the record's travel from its start, when known).
    None for a record with no contact to measure from."""
    if not has_contact(res, k):
        return None
    tr = res.trials[k]
    x = tr.motion.x_m
    xc = res.contact_m(k)
    d = x - xc
    deepest = int(np.argmax(x))
    idx = np.arange(len(x))
    dwell = np.char.startswith(np.asarray(tr.phase, dtype=str), "hold")
    branch = np.where(dwell, "dwell", np.where(idx <= deepest, "approach", "retract"))
    app = np.flatnonzero(branch == "approach")
    near = app[np.argmin(np.abs(d[app]))] if len(app) else int(np.argmin(np.abs(d)))
    meta = tr.meta or {}
    deflection = bool(meta.get("spring_constant_N_per_m")) or meta.get("position_column") == "tip position"
    return {"indentation_m": d, "separation_m": -d if deflection else None, "force_N": tr.force_N,
            "model_N": res.predictions[k], "residual_N": res.residuals[k], "branch": branch,
            "contact_force_N": float(res.predictions[k][near]),
            "contact_travel_m": None if tr.contact_m is None else tr.contact_m + xc}


BRANCH_COLOURS = {"approach": "tab:blue", "dwell": "tab:green", "retract": "tab:orange"}


def contact_figure(res: FitResult, k: int):
    """Force against indentation (and against tip-sample separation where the record has the
    cantilever's deflection) with the fit overlaid, the residual below, the contact point marked,
    approach and retract in their colours: a matplotlib Figure, or None (no contact)."""
    c = contact_curve(res, k)
    if c is None:
        return None
    tr = res.trials[k]
    kf, fu = tr.force_unit
    kl, lu = tr.length_unit
    d = c["indentation_m"]
    d_max = float(np.max(d))
    panels = [("indentation", d, d >= -0.3 * d_max if d_max > 0 else np.ones(len(d), bool))]
    if c["separation_m"] is not None:
        panels.append(("tip-sample separation", c["separation_m"], np.ones(len(d), bool)))
    fig = figure(figsize=(6.2 * len(panels), 6.5))
    axes = fig.subplots(2, len(panels), sharex="col", height_ratios=[3, 1.3], squeeze=False)
    where = (f"{c['contact_travel_m'] / kl:.4g} {lu} of travel" if c["contact_travel_m"] is not None
             else "indentation 0")
    for j, (name, xs, sel) in enumerate(panels):
        ax, axr = axes[0][j], axes[1][j]
        for b, colour in BRANCH_COLOURS.items():
            on = sel & (c["branch"] == b)
            if not on.any():
                continue
            ax.plot(xs[on] / kl, c["force_N"][on] / kf, ".", ms=2, color=colour, alpha=0.6,
                    label=f"measured, {b}")
            axr.plot(xs[on] / kl, c["residual_N"][on] / kf, ".", ms=1.5, color=colour)
        model = np.where(sel, c["model_N"], np.nan)  # one line, approach then retract, gaps left out
        ax.plot(xs / kl, model / kf, color="tab:red", lw=1.3, label=f"model: {res.model.name}")
        ax.axvline(0, color="k", lw=0.8, ls=":")
        ax.plot([0], [c["contact_force_N"] / kf], "o", ms=7, mfc="none", mec="k", mew=1.4,
                label=f"contact point (fitted, {where})")
        ax.set_ylabel(f"force ({fu})")
        ax.legend(fontsize=8, loc="upper left" if name == "indentation" else "upper right")
        ax.set_title(f"force against {name}", fontsize=9)
        axr.axhline(0, color="k", lw=0.6)
        axr.axvline(0, color="k", lw=0.8, ls=":")
        for s in (-2, 2):
            axr.axhline(s * res.noise_N / kf, color="grey", lw=0.6, ls="--")
        axr.set_ylabel(f"residual ({fu})\nmeasured - model")
        axr.set_xlabel(f"{name} ({lu})" + ("  (< 0: in contact)" if name != "indentation" else ""))
    fig.suptitle(f"{tr.name}: RMSE {res.force_text(res.per_trial[k]['rmse_N'])} "
                 f"(noise {res.force_text(res.noise_N)})", fontsize=9)
    return fig


def plot_contact(res: FitResult, k: int, out: Path) -> Path | None:
    """Trial `k`'s force against indentation near its contact, saved to `out`; None where the model has no
    contact point."""
    fig = contact_figure(res, k)
    return None if fig is None else save(fig, out)


def plot_creep(res: FitResult, k: int, out: Path) -> Path | None:
    """Where the force was held (creep form): the measured and the predicted position, and the
    miss below; None for a record fitted in force form throughout."""
    tr = res.trials[k]
    x_pred = predict_position(res.model, res.values, tr)
    if x_pred is None:
        return None
    t = tr.motion.t_s
    kl, u = tr.length_unit
    held = tr.held
    fig = figure(figsize=(10, 6))
    ax, axr = fig.subplots(2, 1, sharex=True, height_ratios=[3, 1.3])
    _shade(ax, t, tr.phase)
    ax.plot(t, tr.motion.x_m / kl, color="k", lw=0.7, label="measured position")
    ax.plot(t[held], x_pred[held] / kl, ".", ms=1.5, color="tab:red",
            label=f"model ({res.model.name}) from the force")
    ax.set_ylabel(f"position ({u})")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(f"{tr.name}: creep form where the force was held", fontsize=9)
    _shade(axr, t, tr.phase)
    axr.plot(t[held], (tr.motion.x_m - x_pred)[held] / kl, ".", ms=1.5, color="tab:blue")
    axr.axhline(0, color="k", lw=0.6)
    axr.set_ylabel(f"miss ({u})\nmeasured - model")
    axr.set_xlabel("time (s)")
    return save(fig, out)


def plot_phase_errors(results: list[FitResult], out: Path) -> Path:
    """Each model's RMSE by phase as grouped bars, saved to `out`."""
    fig = figure(figsize=(9, 4.5))
    ax = fig.subplots()
    width = 0.8 / max(len(results), 1)
    x = np.arange(len(PHASES))
    kf, u = results[0].force_unit
    for i, r in enumerate(results):
        vals = [r.phases[p].rmse_N / kf if r.phases[p] else 0.0 for p in PHASES]
        ax.bar(x + i * width - 0.4 + width / 2, vals, width, label=r.model.name)
    ax.axhline(results[0].noise_N / kf, color="k", ls="--", lw=1, label="sensor noise")
    ax.set_xticks(x, PHASES)
    ax.set_ylabel(f"RMSE ({u})")
    ax.set_yscale("log")
    ax.set_title("error by phase")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return save(fig, out)


def fe_figure(res: FitResult):
    """The paper's f-e plot (a Figure), or None for fewer than two trials with a hold."""
    from matplotlib.patches import Ellipse

    pts = fe_points(res.trials, res.residuals)
    if len(pts) < 2:
        return None
    kf, u = res.force_unit
    fig = figure(figsize=(7, 5.5))
    ax = fig.subplots()
    xs = [p["force_30s_N"] / kf for p in pts]
    ys = [p["mean_error_N"] / kf for p in pts]
    rxs = [p["relax_10s_N"] / kf for p in pts]
    rys = [p["std_error_N"] / kf for p in pts]
    floor = 1e-3 * max(max(xs), 1e-300)  # an ellipse never thinner than a thousandth of the force
    names = trial_labels([p["trial"] for p in pts])  # specimen, protocol, speed: what tells trials apart
    for i, _p in enumerate(pts):
        c = f"C{i % 10}"
        ax.add_patch(Ellipse((xs[i], ys[i]), 2 * max(rxs[i], floor), 2 * rys[i], fill=False, color=c, lw=1.5))
        ax.plot(xs[i], ys[i], "o", color=c, label=names[i])
    rx = max(rxs)
    ry = max(abs(y) + r for y, r in zip(ys, rys, strict=True))
    ax.set_xlim(min(xs) - 1.3 * rx, max(xs) + 1.3 * rx)
    ax.set_ylim(-1.3 * ry, 1.3 * ry)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel(f"measured force at mid-hold, 30 s of a 60 s hold ({u})")
    ax.set_ylabel(f"mean estimation error ({u})")
    ax.set_title(f"f-e plot, model {res.model.name}: radii = relaxation in the first sixth of the hold (x), "
                 "error std (y)", fontsize=9)
    ax.legend(fontsize=7)
    return fig


def plot_fe(res: FitResult, out: Path) -> Path | None:
    """The paper's force-against-error ellipses of several trials, saved to `out`; None for fewer
    than two trials with a hold."""
    fig = fe_figure(res)
    return None if fig is None else save(fig, out)


def residual_steps_figure(fits: list[tuple[str, FitResult]]):
    """The residual of each step's model, one row per step, for every trial side by side (a Figure)."""
    n_trials = len(fits[0][1].trials)
    names = trial_labels([t.name for t in fits[0][1].trials], width=36)
    fig = figure(figsize=(4.2 * n_trials, 1.9 * len(fits) + 0.9))
    axes = fig.subplots(len(fits), n_trials, sharey=True, squeeze=False)
    for i, (label, r) in enumerate(fits):
        for k in range(n_trials):
            ax = axes[i][k]
            tr = r.trials[k]
            _shade(ax, tr.motion.t_s, tr.phase)
            kf, u = tr.force_unit
            ax.plot(tr.motion.t_s, r.residuals[k] / kf, lw=0.5, color="tab:blue")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_title(f"{label}: RMSE {r.force_text(r.per_trial[k]['rmse_N'])}", fontsize=8)
            if k == 0:
                ax.set_ylabel(f"residual ({u})", fontsize=8)
            if i == len(fits) - 1:
                ax.set_xlabel(f"time (s)\n{names[k]}", fontsize=8)
    return fig


def plot_residual_steps(fits: list[tuple[str, FitResult]], out: Path) -> Path:
    """The residual of each step of a stepwise search, one panel a step, saved to `out`."""
    return save(residual_steps_figure(fits), out, dpi=100)


def write_report(res: FitResult, out_dir: str | Path, *, compare: list[FitResult] | None = None,
                 holdout: list[dict] | None = None, text: str = "", before: FitResult | None = None,
                 steps: list[dict] | None = None, explain_text: str = "", creep_text: str = "",
                 material_text: str = "") -> Path:
    """The figures of a fit (and of what the request did beyond it: a comparison, held-out trials, a before
    and after, the stepwise search) and report.md tying them together with the text, in `out_dir`;
    report.md's path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = [plot_trial_fit(res, k, out / f"fit_{k + 1}.png") for k in range(len(res.trials))]
    contact_pngs = [p for k in range(len(res.trials))
                    if (p := plot_contact(res, k, out / f"indentation_{k + 1}.png")) is not None]
    phase_png = plot_phase_errors(compare or [res], out / "phase_errors.png")
    fe_png = plot_fe(res, out / "fe_plot.png")
    md = [f"# Model analysis: {res.model.name}", "",
          f"Trials: {', '.join(t.name for t in res.trials)}", "",
          "```", res.report(), "```", ""]
    if material_text:  # the material line the terminal prints: E, its errors, the contact, E by depth
        md += ["## Material", "", "```", material_text, "```", ""]
    if creep_text:
        creep_pngs = [p for k in range(len(res.trials))
                      if (p := plot_creep(res, k, out / f"creep_{k + 1}.png")) is not None]
        md += ["## Creep form", "", "Where a controller held the force the model predicts the position from "
               "the force; the miss is a length.", "", "```", creep_text, "```", ""]
        md += [f"![{p.stem}]({p.name})" for p in creep_pngs] + [""]
    if compare:
        md += ["## All named models", "", "```", text, "```", ""]
    if holdout:
        kf, u = res.force_unit
        md += ["## Held-out trials", "", f"| trial | RMSE ({u}) | mean ({u}) | " + " | ".join(PHASES) + " |",
               "|---|---|---|" + "---|" * len(PHASES)]
        for h in holdout:
            ph = " | ".join(f"{h['phases'][p]['rmse_N'] / kf:.4g}" if h["phases"][p] else "-" for p in PHASES)
            md.append(f"| {h['trial']} | {h['rmse_N'] / kf:.4g} | {h['mean_N'] / kf:+.4g} | {ph} |")
        md.append("")
    if before is not None:
        png = plot_residual_steps([(before.model.name, before), (res.model.name, res)],
                                  out / "before_after.png")
        md += ["## Before and after adding", "",
               f"RMSE {before.force_text(before.overall.rmse_N)} -> {res.force_text(res.overall.rmse_N)}", "",
               f"![before and after]({png.name})", ""]
    if explain_text:
        md += ["## What is missing", "", "```", explain_text, "```", ""]
    if steps:
        from rig.analysis.diagnosis.explain import format_auto

        labels = [("start" if s["added"] is None and not s.get("removed") else
                   (f"+{s['added']}" if s["added"] else f"-{s['removed']}"), s["fit"]) for s in steps]
        png = plot_residual_steps(labels, out / "auto_steps.png")
        md += ["## Stepwise", "", "```", format_auto(steps), "```", "", f"![residual at each step]({png.name})",
               ""]
    md += ["## Error by phase", "", f"![error by phase]({phase_png.name})", ""]
    if fe_png:
        md += ["## f-e plot", "", "One ellipse per trial: centre at the force after 30 s of relaxation "
               "(mid-hold for other holds) and the mean estimation error; radii: relaxation in the first "
               "10 s (the first sixth of the hold) and the error's standard deviation.", "",
               f"![f-e plot]({fe_png.name})", ""]
    if contact_pngs:
        md += ["## Force against indentation", "", "Past the fitted contact point (marked), the fit over the "
               "measured force, approach and retract apart, the residual below"
               + (" (and against the tip-sample separation, the cantilever's deflection taken off)"
                  if any(contact_curve(res, k)["separation_m"] is not None for k in range(len(res.trials))
                         if has_contact(res, k)) else "") + ".", ""]
        md += [f"![{p.stem}]({p.name})" for p in contact_pngs] + [""]
    md += ["## Fits", ""] + [f"![{p.stem}]({p.name})" for p in figs]
    (out / "report.md").write_text("\n".join(md) + "\n")
    return out / "report.md"
