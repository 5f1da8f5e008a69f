"""Reports: measured and model force with the phases shaded and the residual below, error by
phase, the paper's f-e ellipse plot for several trials, and a report.md tying them together."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rig.analysis.analyze import fe_points
from rig.analysis.data import PHASES
from rig.analysis.fit import FitResult, predict_position
from rig.views.plots import pyplot, shade_spans

PHASE_COLOURS = {"ramp": "#cfe3f7", "hold_early": "#d8f0d2", "hold_late": "#eaf7e6", "return": "#f7d9d4"}


def _shade(ax, t: np.ndarray, phase: np.ndarray) -> None:
    shade_spans(ax, t, phase, PHASE_COLOURS)


def plot_trial_fit(res: FitResult, k: int, out: Path, title_extra: str = "") -> Path:
    from matplotlib.patches import Patch

    plt = pyplot()
    tr = res.trials[k]
    t = tr.motion.t_s
    kf, u = tr.force_unit
    fig, (ax, axr) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True, height_ratios=[3, 1.3],
                                  constrained_layout=True)
    _shade(ax, t, tr.phase)
    ax.plot(t, tr.force_N / kf, color="k", lw=0.7, label="measured")
    ax.plot(t, res.predictions[k] / kf, color="tab:red", lw=1.4, label=f"model: {res.model.name}")
    ax.set_ylabel(f"force ({u})")
    handles, labels = ax.get_legend_handles_labels()
    handles += [Patch(color=PHASE_COLOURS[p]) for p in PHASES]
    ax.legend(handles, labels + list(PHASES), fontsize=8, ncol=3, loc="upper right")
    ax.set_title(f"{tr.name}{title_extra}\nRMSE {res.f(res.per_trial[k]['rmse_N'])} "
                 f"(noise {res.f(res.noise_N)})", fontsize=9)
    _shade(axr, t, tr.phase)
    axr.plot(t, res.residuals[k] / kf, color="tab:blue", lw=0.6)
    axr.axhline(0, color="k", lw=0.6)
    for s in (-2, 2):
        axr.axhline(s * res.noise_N / kf, color="grey", lw=0.6, ls="--")
    axr.set_ylabel(f"residual ({u})\nmeasured - model")
    axr.set_xlabel("time (s)")
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_creep(res: FitResult, k: int, out: Path) -> Path | None:
    """Where the force was held (creep form): the measured and the predicted position, and the
    miss below; None for a record fitted in force form throughout."""
    tr = res.trials[k]
    x_pred = predict_position(res.model, res.values, tr)
    if x_pred is None:
        return None
    plt = pyplot()
    t = tr.motion.t_s
    kl, u = tr.length_unit
    held = tr.held
    fig, (ax, axr) = plt.subplots(2, 1, figsize=(10, 6), sharex=True, height_ratios=[3, 1.3],
                                  constrained_layout=True)
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
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_phase_errors(results: list[FitResult], out: Path) -> Path:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 4.5), constrained_layout=True)
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
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_fe(res: FitResult, out: Path) -> Path | None:
    from matplotlib.patches import Ellipse

    pts = fe_points(res.trials, res.residuals)
    if len(pts) < 2:
        return None
    plt = pyplot()
    kf, u = res.force_unit
    fig, ax = plt.subplots(figsize=(7, 5.5), constrained_layout=True)
    xs = [p["force_30s_N"] / kf for p in pts]
    ys = [p["mean_error_N"] / kf for p in pts]
    rxs = [p["relax_10s_N"] / kf for p in pts]
    rys = [p["std_error_N"] / kf for p in pts]
    floor = 1e-3 * max(max(xs), 1e-300)  # an ellipse never thinner than a thousandth of the force
    for i, p in enumerate(pts):
        c = f"C{i % 10}"
        ax.add_patch(Ellipse((xs[i], ys[i]), 2 * max(rxs[i], floor), 2 * rys[i], fill=False, color=c, lw=1.5))
        ax.plot(xs[i], ys[i], "o", color=c, label=p["trial"][:40])
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
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_residual_steps(fits: list[tuple[str, FitResult]], out: Path) -> Path:
    """The residual of each step's model, one row per step, for every trial side by side."""
    plt = pyplot()
    n_trials = len(fits[0][1].trials)
    fig, axes = plt.subplots(len(fits), n_trials, figsize=(4.2 * n_trials, 1.9 * len(fits) + 0.6),
                             sharey=True, squeeze=False, constrained_layout=True)
    for i, (label, r) in enumerate(fits):
        for k in range(n_trials):
            ax = axes[i][k]
            tr = r.trials[k]
            _shade(ax, tr.motion.t_s, tr.phase)
            kf, u = tr.force_unit
            ax.plot(tr.motion.t_s, r.residuals[k] / kf, lw=0.5, color="tab:blue")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_title(f"{label}: RMSE {r.f(r.per_trial[k]['rmse_N'])}", fontsize=8)
            if k == 0:
                ax.set_ylabel(f"residual ({u})", fontsize=8)
            if i == len(fits) - 1:
                ax.set_xlabel(f"time (s), {tr.name[:30]}", fontsize=8)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def write_report(res: FitResult, out_dir: str | Path, *, compare: list[FitResult] | None = None,
                 holdout: list[dict] | None = None, text: str = "", before: FitResult | None = None,
                 steps: list[dict] | None = None, explain_text: str = "", creep_text: str = "",
                 material_text: str = "") -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = [plot_trial_fit(res, k, out / f"fit_{k + 1}.png") for k in range(len(res.trials))]
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
               f"RMSE {before.f(before.overall.rmse_N)} -> {res.f(res.overall.rmse_N)}", "",
               f"![before and after]({png.name})", ""]
    if explain_text:
        md += ["## What is missing", "", "```", explain_text, "```", ""]
    if steps:
        from rig.analysis.explain import format_auto

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
    md += ["## Fits", ""] + [f"![{p.stem}]({p.name})" for p in figs]
    (out / "report.md").write_text("\n".join(md) + "\n")
    return out / "report.md"
