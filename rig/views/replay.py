"""Replay a trial log: summary, estimator error, a re-run of the estimator, a plot."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rig.control.estimator import StiffnessRLS
from rig.errors import RigError, SpecError
from rig.recording.logs import TrialLog
from rig.specs.config import RigConfig, parse_config
from rig.specs.frames import Frame
from rig.views.plots import figure, save, shade_spans, trial_labels


@dataclass
class HoldCheck:
    """Final stiffness estimate against measured force / position over the last second of a hold."""

    stiffness_N_per_m: float
    measured_N_per_m: float

    @property
    def rel_diff(self) -> float:
        return (self.stiffness_N_per_m - self.measured_N_per_m) / self.measured_N_per_m


DEFAULT_RATE_HZ = 100.0
DEFAULT_LATE_TOLERANCE_MS = 5.0


def config_of(log: TrialLog) -> RigConfig | None:
    """The config the trial ran with (attached to the log), or None if it cannot be read."""
    return stored_config(log)[0]


def stored_config(log: TrialLog) -> tuple[RigConfig | None, str]:
    """The config the trial ran with, or None and why it cannot be used."""
    text = log.attachments.get("config.yaml")
    if text is None:
        return None, "the log carries no config.yaml"
    try:
        return parse_config(text.decode(), f"{log.path}!config.yaml"), ""
    except SpecError as exc:
        return None, f"its config.yaml does not parse ({exc})"
    except UnicodeDecodeError as exc:
        return None, f"its config.yaml is not UTF-8 text ({exc.reason} at byte {exc.start})"


def rerun_estimator(log: TrialLog, config: RigConfig) -> np.ndarray:
    """Run the online estimator again over the logged positions and forces, each position
    measured from the zero the loop's estimator used (the working zero after that tick)."""
    est = config.estimator
    rls = StiffnessRLS.from_config(est, config.loop.rate_Hz)
    x = log.frames.estimator_x_mm / 1000.0
    f = log.samples["force_N"]
    out = np.empty(log.n)
    x_prev = 0.0
    for i in range(log.n):
        out[i] = rls.update(x_prev, f[i]).stiffness_N_per_m
        x_prev = x[i]
    return out


def hold_check(log: TrialLog, window_s: float = 1.0) -> HoldCheck | None:
    kinds = np.array(log.step_kind)
    idx = np.flatnonzero(np.isin(kinds, ("hold", "hold_force")))
    if len(idx) == 0:
        return None
    end = idx[-1]
    # the last hold segment: walk back while still in the same step
    step = log.samples["step"]
    seg = idx[step[idx] == step[end]]
    t = log.samples["t_s"]
    sel = seg[t[seg] >= t[end] - window_s]
    x = float(np.mean(log.position_mm(Frame.SURFACE)[sel])) / 1000.0
    if x <= 0:
        return None
    measured = float(np.mean(log.samples["force_N"][sel])) / x
    return HoldCheck(float(log.samples["stiffness_N_per_m"][end]), measured)


def summarize(log: TrialLog) -> dict:
    if log.n == 0:
        raise RigError(f"{log.path}: the log holds no samples")
    s = log.samples
    meta = log.trial
    config, why = stored_config(log)
    tol_ms = config.loop.late_tolerance_ms if config else DEFAULT_LATE_TOLERANCE_MS
    rate_Hz = config.loop.rate_Hz if config else DEFAULT_RATE_HZ
    contact = log.contact
    err = s["error_N"][contact] if contact.any() else np.zeros(0)
    faults = [e for e in log.events if e.get("kind") == "fault"]
    out: dict = {
        "log": str(log.path),
        "complete": log.complete,
        "outcome": log.outcome,
        "specimen": meta.get("specimen", ""),
        "operator": meta.get("operator", ""),
        "protocol": meta.get("protocol_name", ""),
        "start_time": meta.get("start_time", ""),
        "duration_s": float(s["t_s"][-1]),
        "samples": log.n,
        "late_ticks": int(np.sum(s["late_ms"] > tol_ms)),
        "missed_ticks": _missed(s, rate_Hz),
        "faults": [{"t_s": f["t_s"], "message": f["message"]} for f in faults],
        "estimator": {
            "contact_samples": int(contact.sum()),
            "error_mean_N": float(np.mean(err)) if len(err) else None,
            "error_std_N": float(np.std(err)) if len(err) else None,
            "error_max_abs_N": float(np.max(np.abs(err))) if len(err) else None,
            "error_rms_N": float(np.sqrt(np.mean(err ** 2))) if len(err) else None,
            "final_stiffness_N_per_m": float(s["stiffness_N_per_m"][-1]),
        },
        "peak_force_N": float(np.max(s["force_N"])),
    }
    # force control: each force step's figures, and what the operator was told of them
    out["force_steps"] = [{"message": e["message"], **e.get("data", {})} for e in log.events
                          if e.get("kind") == "force_step"]
    out["notices"] = [e["message"] for e in log.events if e.get("kind") in NOTICE_EVENTS]
    if log.read_error and not log.complete:
        out["truncated"] = log.read_error
    if config is None:
        out["warnings"] = [f"{why}: late and missed ticks counted at the defaults ({DEFAULT_RATE_HZ:g} Hz, "
                           f"{DEFAULT_LATE_TOLERANCE_MS:g} ms late), the estimator not re-run"]
    if "calibration" in log.metadata:
        out["calibration"] = dict(log.metadata["calibration"])
    size = specimen_size(log, out["peak_force_N"])
    if size:
        out["specimen_size"] = size
    hc = hold_check(log)
    if hc:
        out["estimator"]["hold_end"] = {"stiffness_N_per_m": hc.stiffness_N_per_m,
                                        "measured_N_per_m": hc.measured_N_per_m,
                                        "rel_diff": hc.rel_diff}
    if "model.json" in log.attachments and "force_model_N" in s:
        out["model"] = model_check(log, rate_Hz)
    if config is not None:
        again = rerun_estimator(log, config)
        diff = float(np.max(np.abs(again - s["stiffness_N_per_m"])))
        out["estimator"]["rerun_max_diff_N_per_m"] = diff
        out["estimator"]["reproduced"] = bool(diff <= 1e-6 * max(1.0, float(np.max(np.abs(again)))))
    return out


def specimen_size(log: TrialLog, peak_force_N: float) -> dict:
    """The specimen's dimensions the header keeps (rig.specs.specimen), and what they turn the
    trial's figures into: with the area the peak stress (peak force / area, Pa), with the
    thickness the peak strain (the deepest indentation from the surface / thickness); {} when
    the header gives neither."""
    from rig.specs.specimen import from_header

    dims = from_header(log.trial)
    if not dims:
        return {}
    out: dict = dict(dims)
    if "area_mm2" in dims:
        out["peak_stress_Pa"] = peak_force_N / (dims["area_mm2"] * 1e-6)
    if "thickness_mm" in dims:
        depth_mm = max(float(np.max(log.position_mm(Frame.SURFACE))), 0.0)
        out["peak_indentation_mm"] = depth_mm
        out["peak_strain"] = depth_mm / dims["thickness_mm"]
    return out


def model_check(log: TrialLog, rate_Hz: float) -> dict:
    """The model that ran in the loop: its error by step kind, and the same model evaluated
    offline (vectorised, `Model.predict`) on the logged positions against the logged values."""
    from rig.models.online import offline_force
    from rig.models.saved import loads

    saved = loads(log.attachments["model.json"].decode(), f"{log.path}:model.json")
    s = log.samples
    online = s["force_model_N"]
    offline = offline_force(saved.model, saved.values, s["t_s"], s["position_mm"] / 1000.0, 1.0 / rate_Hz)
    diff = float(np.max(np.abs(offline - online)))
    out = {"model": saved.model.name, "offline_max_diff_N": diff, "offline_agrees": diff <= 1e-9,
           "force_source": log.trial.get("force_source", "load cell")}
    if "model_error_N" in s:
        err = s["model_error_N"]
        kinds = np.array(log.step_kind)
        by_kind = {}
        for kind in ("ramp", "hold", "return"):
            sel = kinds == kind
            if sel.any():
                by_kind[kind] = {"rmse_N": float(np.sqrt(np.mean(err[sel] ** 2))),
                                 "mean_N": float(np.mean(err[sel])), "samples": int(sel.sum())}
        hold = np.flatnonzero(kinds == "hold")
        if len(hold):  # the paper's early and late hold (first sixth / the rest)
            cut = hold[0] + max(len(hold) // 6, 1)
            for name, sel in (("hold_early", hold[hold < cut]), ("hold_late", hold[hold >= cut])):
                if len(sel):
                    by_kind[name] = {"rmse_N": float(np.sqrt(np.mean(err[sel] ** 2))),
                                     "mean_N": float(np.mean(err[sel])), "samples": len(sel)}
        out["error_by_phase"] = by_kind
        out["rmse_N"] = float(np.sqrt(np.mean(err ** 2)))
    return out


def _missed(s: dict, rate_Hz: float) -> int:
    """Skipped slots: ticks sit on a fixed grid once their logged lateness is taken off."""
    if len(s["t_s"]) < 2:
        return 0
    slots = np.round((s["t_s"] - s["late_ms"] / 1000.0) * rate_Hz)
    return int(np.sum(np.maximum(np.diff(slots) - 1, 0)))


# the events a completed trial's operator is told of (`TrialResult.notices`)
NOTICE_EVENTS = ("force_step_warning", "setpoint_missed", "force_limit_depth", "force_depth_budget",
                 "calibration_warning", "calibration_range")


def format_summary(d: dict) -> str:
    e = d["estimator"]
    lines = [
        f"log        {d['log']}" + ("" if d["complete"] else "   (cut short: read up to the last flush)"),
        f"specimen   {d['specimen'] or '-'}    operator {d['operator'] or '-'}",
        f"protocol   {d['protocol']}",
        f"started    {d['start_time']}",
        f"outcome    {d['outcome']}",
        f"duration   {d['duration_s']:.2f} s, {d['samples']} samples, "
        f"{d['late_ticks']} late, {d['missed_ticks']} missed",
        f"peak force {d['peak_force_N']:.3f} N",
    ]
    c = d.get("calibration")
    if c:
        lines.append(f"calibrated {c.get('date', '?')[:10]}: sensitivity {c.get('sensitivity')} +/- "
                     f"{c.get('sensitivity_u')}, linearity {c.get('linearity_N')} N "
                     f"({c.get('linearity_pct')} % of {c.get('range_N', '').replace(' ', '-')} N)")
    z = d.get("specimen_size")
    if z:
        given = [f"thickness {z['thickness_mm']:g} mm" if "thickness_mm" in z else "",
                 f"area {z['area_mm2']:g} mm^2" if "area_mm2" in z else ""]
        lines.append(f"size       {', '.join(g for g in given if g)}")
        if "peak_stress_Pa" in z:
            lines.append(f"stress     peak {z['peak_stress_Pa'] / 1e3:.4g} kPa (peak force / area)")
        if "peak_strain" in z:
            lines.append(f"strain     peak {z['peak_strain']:.4g} ({z['peak_indentation_mm']:.3f} mm deepest "
                         "indentation / thickness)")
    for f in d["faults"]:
        lines.append(f"FAULT      t={f['t_s']:.2f} s: {f['message']}")
    for w in d.get("warnings", ()):
        lines.append(f"WARNING    {w}")
    for i, f in enumerate(d.get("force_steps", ())):
        lines.append(f"{'force step' if i == 0 else '':11}{f['message']}")
    for n in d.get("notices", ()):
        lines.append(f"NOTICE     {n}")
    if e["error_mean_N"] is not None:
        lines.append(f"estimator  error mean {e['error_mean_N']:+.4f} N, std {e['error_std_N']:.4f} N, "
                     f"max |e| {e['error_max_abs_N']:.3f} N over {e['contact_samples']} contact samples")
    if "hold_end" in e:
        h = e["hold_end"]
        lines.append(f"hold end   k = {h['stiffness_N_per_m']:.2f} N/m vs measured F/x = "
                     f"{h['measured_N_per_m']:.2f} N/m ({h['rel_diff'] * 100:+.2f} %)")
    if "model" in d:
        m = d["model"]
        lines.append(f"model      {m['model']} ran in the loop ({m['force_source']}); offline on the logged "
                     f"positions it {'agrees' if m['offline_agrees'] else 'DOES NOT agree'} "
                     f"(max diff {m['offline_max_diff_N']:.1e} N)")
        if "error_by_phase" in m:
            parts = ", ".join(f"{k} {v['rmse_N']:.4f}" for k, v in m["error_by_phase"].items())
            lines.append(f"           error RMSE {m['rmse_N']:.4f} N; by phase (N): {parts}")
    if "reproduced" in e:
        verdict = "reproduces" if e["reproduced"] else "DOES NOT reproduce"
        lines.append(f"re-run     the estimator {verdict} the logged estimates "
                     f"(max diff {e['rerun_max_diff_N_per_m']:.2e} N/m)")
    return "\n".join(lines)


_STEP_COLOURS = {"tare": "#dddddd", "approach": "#f3e6c0", "ramp": "#cfe3f7", "hold": "#d8f0d2",
                 "ramp_force": "#ddd0f2", "hold_force": "#c8ece6", "return": "#f7d9d4", "fault": "#ff9e9e"}


def shade_steps(ax, t: np.ndarray, kinds: list[str]) -> None:
    """Shade the background of `ax` by step kind."""
    shade_spans(ax, t, kinds, _STEP_COLOURS, alpha=0.5)


def _legend_outside(ax, handles=None, labels=None) -> None:
    """The legend right of the axes: it never covers a sample (the peak where a limit tripped)."""
    if handles is None:
        handles, labels = ax.get_legend_handles_labels()
    ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, borderaxespad=0.0)


def log_figure(log: TrialLog):
    """A trial's force (with a force-controlled step's setpoint), position and stiffness estimate
    against time, its steps shaded, a fault marked where it tripped: a matplotlib Figure."""
    from matplotlib.patches import Patch

    s = log.samples
    t = s["t_s"]
    fig = figure(figsize=(11, 8))
    axes = fig.subplots(3, 1, sharex=True)
    ax = axes[0]
    shade_steps(ax, t, log.step_kind)
    ax.plot(t, s["force_N"], lw=0.8, color="k", label="measured")
    ax.plot(t, s["force_pred_N"], lw=0.8, color="tab:orange", alpha=0.8,
            label="RLS prediction k(t-1) x(t-1)")
    setpoint = s.get("force_cmd_N")
    if setpoint is not None and np.any(np.isfinite(setpoint)):
        ax.plot(t, setpoint, lw=1.4, color="tab:purple", ls="--", label="force setpoint")
    faults = [e for e in log.events if e.get("kind") == "fault"]
    for e in faults:
        f = (e.get("data") or {}).get("force_N")
        if f is None:
            f = float(np.interp(e["t_s"], t, s["force_N"]))
        ax.plot([e["t_s"]], [f], "X", ms=9, color="r", mec="k", label=f"fault: {e['message']}"[:70])
    ax.set_ylabel("force (N)")
    handles, labels = ax.get_legend_handles_labels()
    kinds_present = [k for k in _STEP_COLOURS if k in set(log.step_kind)]
    handles += [Patch(color=_STEP_COLOURS[k], alpha=0.5) for k in kinds_present]
    labels += kinds_present
    _legend_outside(ax, handles, labels)
    meta = log.trial
    ax.set_title(f"{meta.get('protocol_name', '')}  |  specimen {meta.get('specimen', '-')}\n"
                 f"{Path(log.path).name}", fontsize=9)
    ax = axes[1]
    shade_steps(ax, t, log.step_kind)
    ax.plot(t, log.position_mm(Frame.SURFACE), lw=1.0, label="feedback")
    ax.plot(t, log.position_cmd_mm(Frame.SURFACE), lw=0.8, ls="--", label="commanded")
    ax.set_ylabel("indentation (mm)")
    _legend_outside(ax)
    ax = axes[2]
    shade_steps(ax, t, log.step_kind)
    k = np.where(log.contact, s["stiffness_N_per_m"], np.nan)
    ax.plot(t, k, lw=1.0, color="tab:green")
    ax.set_ylabel("stiffness k (N/m)")
    ax.set_xlabel("time (s)")
    for e in faults:
        for a in axes:
            a.axvline(e["t_s"], color="r", lw=1.2)
    return fig


def plot_log(log: TrialLog, out: str | Path) -> None:
    save(log_figure(log), out)


# ---------------------------------------------------------------- several logs
TABLE_COLUMNS = ("trial", "specimen", "protocol", "outcome", "peak force", "k at hold end", "est. error",
                 "duration")


def log_figures(log: TrialLog) -> dict:
    """The figures a day's table compares, from the samples alone (no re-run): the peak force,
    the stiffness estimate at the end of the last hold, the estimator's RMS error over the contact
    samples (SI; None where the log has no hold or no contact)."""
    s = log.samples
    if log.n == 0:
        return {"peak_force_N": None, "hold_end_stiffness_N_per_m": None, "estimator_error_rms_N": None}
    contact = log.contact
    err = s["error_N"][contact] if contact.any() else np.zeros(0)
    hc = hold_check(log)
    return {"peak_force_N": float(np.max(s["force_N"])),
            "hold_end_stiffness_N_per_m": hc.stiffness_N_per_m if hc else None,
            "estimator_error_rms_N": float(np.sqrt(np.mean(err ** 2))) if len(err) else None}


def table_row(d: dict) -> dict:
    """One row of the summary table of several logs, from `summarize`."""
    e = d["estimator"]
    return {"trial": Path(d["log"]).name, "specimen": d["specimen"], "protocol": d["protocol"],
            "outcome": d["outcome"] + ("" if d["complete"] else " (cut short)"),
            "peak_force_N": d["peak_force_N"],
            "hold_end_stiffness_N_per_m": e["hold_end"]["stiffness_N_per_m"] if "hold_end" in e else None,
            "estimator_error_rms_N": e.get("error_rms_N"), "duration_s": d["duration_s"]}


def _num(v, fmt: str, unit: str) -> str:
    return "-" if v is None else f"{v:{fmt}} {unit}"


def format_table(rows: list[dict]) -> str:
    """The summary table of several logs: one line per trial, aligned columns."""
    lines = [TABLE_COLUMNS]
    for r in rows:
        lines.append((r["trial"], r["specimen"] or "-", r["protocol"] or "-", r["outcome"],
                      _num(r["peak_force_N"], ".3f", "N"), _num(r["hold_end_stiffness_N_per_m"], ".1f", "N/m"),
                      _num(r["estimator_error_rms_N"], ".4f", "N"), _num(r["duration_s"], ".2f", "s")))
    widths = [max(len(str(row[i])) for row in lines) for i in range(len(TABLE_COLUMNS))]
    right = {4, 5, 6, 7}  # numbers line up on the right
    return "\n".join("  ".join(str(c).rjust(w) if i in right else str(c).ljust(w)
                               for i, (c, w) in enumerate(zip(row, widths, strict=True))).rstrip()
                     for row in lines)


def log_labels(logs: list[TrialLog]) -> list[str]:
    """What tells trials apart: specimen and protocol (its speed in its name), the start time
    added where two would read alike; from the file's name for a log without that metadata."""
    fallback = trial_labels([Path(log.path).name for log in logs], width=60)
    base = [f"{log.trial.get('specimen') or '-'}  {log.trial.get('protocol_name')}"
            if log.trial.get("protocol_name") else fallback[i] for i, log in enumerate(logs)]
    return [f"{b}  ({log.trial.get('start_time', '')[11:19]})" if base.count(b) > 1 else b
            for b, log in zip(base, logs, strict=True)]


def compare_figure(logs: list[TrialLog]):
    """Several logs on one Figure: force against time, and force against indentation (the
    load-displacement curve), one colour per trial, labelled by specimen and protocol."""
    names = log_labels(logs)
    fig = figure(figsize=(12, 5.2))
    ax_t, ax_x = fig.subplots(1, 2)
    for i, (log, name) in enumerate(zip(logs, names, strict=True)):
        s = log.samples
        c = f"C{i % 10}"
        ax_t.plot(s["t_s"], s["force_N"], lw=0.8, color=c, label=name)
        ax_x.plot(log.position_mm(Frame.SURFACE), s["force_N"], lw=0.8, color=c, label=name)
        for e in log.events:
            if e.get("kind") == "fault":
                ax_t.axvline(e["t_s"], color=c, lw=1.0, ls="--")
    ax_t.set(xlabel="time (s)", ylabel="force (N)", title="force against time")
    ax_x.set(xlabel="indentation (mm)", ylabel="force (N)", title="force against indentation")
    for ax in (ax_t, ax_x):
        ax.grid(alpha=0.3)
    handles, labels = ax_t.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=min(len(logs), 3), fontsize=8)
    return fig


def plot_compare(logs: list[TrialLog], out: str | Path) -> Path:
    return save(compare_figure(logs), out)
