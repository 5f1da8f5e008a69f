"""Text views for the daemon's clients: status, a live watch with a small trend, the log list."""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import TextIO

SPARK = "▁▂▃▄▅▆▇█"


def sparkline(values: list[float]) -> str:
    if not values:
        return ""
    lo, hi = min(values), max(values)
    span = hi - lo or 1.0
    return "".join(SPARK[min(int((v - lo) / span * (len(SPARK) - 1) + 0.5), len(SPARK) - 1)] for v in values)


def force_step_line(fig: dict) -> str:
    """One force step's figures (`rig.control.forcestats.StepFigures.as_dict`) on one line."""
    head = f"step {fig['index']} ({fig['kind']} {fig['setpoint_N']:.4g} N): "  # numbered as the log's events
    if fig["kind"] == "ramp_force":
        return head + ("reached" if fig.get("reached", True) else "SHORT of its target") + \
            (f" {fig['lag_s']:.2f} s after its planned end" if fig.get("lag_s") else " on time")
    rms = "" if fig.get("rms_over_noise") is None else f", RMS error {fig['rms_over_noise']:.2f} sigma"
    settle = "never settled" if fig.get("settle_s") is None else f"settled in {fig['settle_s']:.2f} s"
    return head + f"overshoot {100 * fig['overshoot_share']:+.1f} %, {settle}{rms}"


def format_status(reply: dict) -> str:
    state = reply["state"]
    snap = reply.get("snapshot") or {}
    lines = [f"state     {state}"]
    camp = reply.get("campaign")
    if camp:
        lines.append(f"campaign  specimen {camp.get('specimen')} (started {camp.get('started')} by "
                     f"{camp.get('user')}): {camp.get('phase')}; {camp.get('trials', 0)} trials")
    if state in ("running", "fault"):
        t = reply.get("trial", {})
        lines += [
            f"protocol  {t.get('protocol')}  (specimen {t.get('specimen')}, started {t.get('started')} "
            f"by {t.get('user')})",
            f"step      {snap['step'] + 1}/{snap['steps_total']} {snap['step_kind']}, "
            f"t = {snap['t_s']:.1f} s, about {snap['time_left_s']:.0f} s left",
            f"force     {snap['force_N']:.3f} N   position {snap['position_mm']:.3f} mm   "
            f"stiffness {snap['stiffness_N_per_m']:.1f} N/m",
            f"log       {t.get('log')}",
        ]
        if snap.get("force_model_N") is not None:
            lines.insert(-1, f"model     {snap['force_model_N']:.3f} N   error "
                             f"{snap['force_N'] - snap['force_model_N']:+.3f} N (measured - model)")
        for fig in (snap.get("force_steps") or ())[-3:]:
            lines.insert(-1, "force     " + force_step_line(fig))
        if snap.get("fault"):
            lines.append(f"FAULT     {snap['fault']}")
    elif snap:
        if "error" in snap:
            lines.append(f"devices   {snap['error']}")
        else:
            force = "-" if snap.get("force_N") is None else f"{snap['force_N']:.3f} N (untared)"
            alarm = f"   ALARM 0x{snap['alarm_code']:02X}" if snap.get("alarm_code") else ""
            lines.append(f"position  {snap['position_mm']:.3f} mm   force {force}{alarm}")
    left = reply.get("probe_in_contact")
    if left:
        lines.append(f"CONTACT   the probe is {left['depth_mm']:.2f} mm into the specimen (surface at "
                     f"{left['surface_mm']:.3f} mm), left there by {left['by']}: `rig return` raises it, "
                     "`rig start --from-contact` runs from there")
    last = reply.get("last")
    if last:
        lines.append(f"last      {last.get('outcome')}: '{last.get('protocol', '')}' "
                     f"{last.get('samples', '')} samples -> {last.get('log', '')}"
                     + (f"  ({last['fault']})" if last.get("fault") else ""))
    return "\n".join(lines)


class Watcher:
    """Redraws one block per update; plain lines when the output is not a terminal."""

    def __init__(self, out: TextIO, trend: int = 40) -> None:
        self.out = out
        self.tty = out.isatty()
        self.force: deque[float] = deque(maxlen=trend)
        self.pos: deque[float] = deque(maxlen=trend)
        self._drawn = 0

    def update(self, snap: dict | None, trial: dict, campaign: dict | None = None) -> None:
        head = [f"characterize {campaign['specimen']}: {campaign['phase']}"] if campaign else []
        if snap is None:  # a campaign before its first trial
            self._draw(head or ["waiting for the first trial"])
            return
        self.force.append(snap["force_N"])
        self.pos.append(snap["position_mm"])
        block = [
            *head,
            f"{trial.get('protocol', '')}  specimen {trial.get('specimen', '')}  "
            f"t = {snap['t_s']:6.1f} s  step {snap['step'] + 1}/{snap['steps_total']} {snap['step_kind']:<8}"
            f" ~{snap['time_left_s']:.0f} s left",
            f"  force    {snap['force_N']:8.3f} N   {sparkline(list(self.force))}",
            f"  position {snap['position_mm']:8.3f} mm  {sparkline(list(self.pos))}",
            f"  k        {snap['stiffness_N_per_m']:8.1f} N/m"
            + (f"   FAULT {snap['fault']}" if snap.get("fault") else ""),
        ]
        if snap.get("force_model_N") is not None:
            block.insert(len(head) + 2, f"  model    {snap['force_model_N']:8.3f} N   error "
                                        f"{snap['force_N'] - snap['force_model_N']:+.3f} N")
        self._draw(block)

    def _draw(self, block: list[str]) -> None:
        if self.tty and self._drawn:
            self.out.write(f"\x1b[{self._drawn}F")
        text = "\n".join(line + ("\x1b[K" if self.tty else "") for line in block) + "\n"
        self.out.write(text)
        self.out.flush()
        self._drawn = len(block)

    def finish(self, last: dict | None) -> None:
        camp = (last or {}).get("campaign")
        if camp:
            self.out.write(f"campaign {camp.get('status')}: {camp.get('reason', '')}; "
                           f"journal {camp.get('journal')}\n")
        if last:
            self.out.write(f"trial {last.get('outcome')}: {last.get('samples', '?')} samples -> "
                           f"{last.get('log', '')}\n")
        else:
            self.out.write("no trial is running\n")
        self.out.flush()


def trial_figures(entries) -> list[dict]:
    """Per entry of `list_trials`: its peak force, stiffness at the hold's end and estimator error
    (rig.views.replay.log_figures), read from the log's samples, and from its header the load
    cell's calibration date and the specimen's thickness and area; None each for a log being
    written or one that cannot be read, or a header without them."""
    import contextlib

    from rig.errors import RigError
    from rig.recording.logs import read_log
    from rig.views.replay import log_figures

    out = []
    for e in entries:
        figs = dict.fromkeys(("peak_force_N", "hold_end_stiffness_N_per_m", "estimator_error_rms_N"))
        cal, trial = {}, {}
        if e.outcome != "running":
            with contextlib.suppress(RigError, OSError, ValueError):
                log = read_log(e.path)
                cal, trial = log.metadata.get("calibration", {}), log.trial
                figs = log_figures(log)
        # what the header keeps beside them: the load cell's calibration, the specimen's size
        out.append({**figs, "calibration_date": cal.get("date") or None,
                    "thickness_mm": trial.get("thickness_mm") or None,
                    "area_mm2": trial.get("area_mm2") or None})
    return out


def _fig(v, fmt: str, unit: str) -> str:
    return "-" if v is None else f"{v:{fmt}} {unit}"


def format_logs(entries, out_dir: Path, figures: list[dict] | None = None) -> str:
    """The trials as a table, newest first; with `figures` (trial_figures) the peak force, the
    stiffness at the hold's end and the estimator's RMS error too."""
    if not entries:
        return f"no trial logs in {out_dir}"
    head = ("started", "specimen", "protocol", "duration", "outcome")
    more = ("peak force", "k at hold end", "est. error") if figures is not None else ()
    rows = [(*head, *more, "file")]
    for i, e in enumerate(entries):
        dur = f"{e.duration_s:.1f} s" if e.duration_s is not None else "-"
        outcome = e.outcome + (" (recovered)" if e.recovered else "")
        started = e.start_time[:19].replace("T", " ")
        # a campaign's trials lie in its folder: shown with it
        shown = str(e.path.relative_to(out_dir)) if e.path.is_relative_to(out_dir) else e.path.name
        extra = ()
        if figures is not None:
            f = figures[i]
            extra = (_fig(f["peak_force_N"], ".3f", "N"), _fig(f["hold_end_stiffness_N_per_m"], ".1f", "N/m"),
                     _fig(f["estimator_error_rms_N"], ".4f", "N"))
        rows.append((started, e.specimen, e.protocol[:36], dur, outcome, *extra, shown))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows)
