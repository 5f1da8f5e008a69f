"""What `rig probe` found: each device's answers, the bus timing, and the problems, each with
the config fields to look at; as text for a person or JSON for a script."""

from __future__ import annotations

import statistics
from dataclasses import asdict, dataclass, field

EXIT_OK, EXIT_PROBLEMS, EXIT_SILENT = 0, 1, 3  # all well; problems; a device does not answer


@dataclass
class Problem:
    device: str  # slider, loadcell or timing
    message: str
    fields: list[str]  # the config fields to look at
    hint: str = ""  # what else to do when no field fixes it (a drive alarm, a cable)


@dataclass
class Timing:
    what: str
    times_ms: list[float] = field(default_factory=list)
    failed: int = 0

    def summary(self) -> dict:
        t = self.times_ms
        return {"what": self.what, "count": len(t) + self.failed, "failed": self.failed,
                "median_ms": round(statistics.median(t), 3) if t else None,
                "worst_ms": round(max(t), 3) if t else None}


@dataclass
class ProbeReport:
    target: str
    period_ms: float
    seconds: float
    slider: dict = field(default_factory=dict)
    loadcell: dict = field(default_factory=dict)
    timing: list[Timing] = field(default_factory=list)
    worst_tick_ms: float | None = None
    problems: list[Problem] = field(default_factory=list)
    slider_answers: bool = False
    loadcell_answers: bool = False

    def problem(self, device: str, message: str, fields: list[str], hint: str = "") -> None:
        self.problems.append(Problem(device, message, fields, hint))

    def exit_status(self) -> int:
        if not (self.slider_answers and self.loadcell_answers):
            return EXIT_SILENT
        return EXIT_PROBLEMS if self.problems else EXIT_OK

    def as_dict(self) -> dict:
        return {"target": self.target, "period_ms": self.period_ms, "seconds": self.seconds,
                "slider_answers": self.slider_answers, "loadcell_answers": self.loadcell_answers,
                "slider": self.slider, "loadcell": self.loadcell,
                "timing": [t.summary() for t in self.timing], "worst_tick_ms": self.worst_tick_ms,
                "problems": [asdict(p) for p in self.problems], "exit_status": self.exit_status()}

    def format(self) -> str:
        s, c = self.slider, self.loadcell
        out = [f"probing   {self.target}", f"slider    {s.get('link', '?')}"]
        out.append(f"  answers       {'yes' if self.slider_answers else 'NO'}" + (
            f": unit {s['device_id']}" if self.slider_answers else f" ({s.get('why', 'no answer')})"))
        if "status" in s:
            out.append(f"  status        {s['status']}")
        if "position_mm" in s:
            out.append(f"  position      {s['position_mm']:.3f} mm ({s['position_steps']} steps at "
                       f"{s['steps_per_mm']:g} steps/mm)")
        if "comm_timeout" in s:
            out.append(f"  comm timeout  {s['comm_timeout']}")
        out.append(f"load cell {c.get('link', '?')}")
        out.append(f"  answers       {'yes' if self.loadcell_answers else 'NO'}"
                   + (f": {c['summary']}" if c.get("summary") else ""))
        for i, (raw, parsed) in enumerate(c.get("examples", [])):
            label = "lines" if i == 0 else ""
            out.append(f"  {label:<13} {raw:<22} -> {parsed}")
        if self.timing:
            out.append(f"bus timing over {self.seconds:g} s at the loop's {1000 / self.period_ms:g} Hz "
                       f"(period {self.period_ms:g} ms)")
            for t in self.timing:
                d = t.summary()
                if d["median_ms"] is None:
                    out.append(f"  {t.what:<16} {d['count']:4d} x  all failed")
                    continue
                out.append(f"  {t.what:<16} {d['count']:4d} x  median {d['median_ms']:6.2f} ms  "
                           f"worst {d['worst_ms']:6.2f} ms  {d['failed']} failed")
            if self.worst_tick_ms is not None:
                out.append(f"  worst tick       {self.worst_tick_ms:.2f} ms of bus time "
                           f"({100 * self.worst_tick_ms / self.period_ms:.0f} % of the period)")
        if self.problems:
            out.append(f"problems ({len(self.problems)})")
            for p in self.problems:
                out.append(f"  - {p.device}: {p.message}")
                if p.fields:
                    out.append(f"    config: {', '.join(p.fields)}")
                if p.hint:
                    out.append(f"    {p.hint}")
        verdict = {EXIT_OK: "OK: both devices answer, no problems",
                   EXIT_PROBLEMS: "both devices answer, with the problems above",
                   EXIT_SILENT: "FAILED: " + " and ".join(
                       n for n, ok in (("the slider", self.slider_answers),
                                       ("the load cell", self.loadcell_answers)) if not ok)
                   + " did not answer"}[self.exit_status()]
        out.append(verdict)
        return "\n".join(out)
