"""Trials for analysis: any record (the rig's logs, CSV, instrument files) on a uniform time
grid, with contact, direction of loading, baseline, phases and the record's own scales.

Nothing here has a scale of its own: thresholds are fractions of the record's force and
travel, windows are counted in samples from the record's own noise and speed, and the
length, force and time scales every fit is expressed in come from the record.

Phases: `ramp` (moving in), `hold_early` (the first sixth of a hold), `hold_late`,
`return` (moving out); several steps of a staircase are several ramps and holds; a hold
under force control, where the position creeps, is still a hold. From a rig log they come
from the protocol steps; otherwise from the motion itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rig.analysis.stats.noise import MIN_BASELINE, MIN_REST, from_baseline
from rig.analysis.trials.contact import detrend, end_of_contact, end_of_pull, find_contact, force_words
from rig.analysis.trials.motion import phases_from_motion, phases_from_steps, velocity
from rig.errors import SpecError
from rig.models.core import Motion
from rig.records import ReadOptions, Record, read_record
from rig.records.units import FORCE_DISPLAY, LENGTH_DISPLAY, display_unit
from rig.specs.frames import Frame

PHASES = ("ramp", "hold_early", "hold_late", "return")


@dataclass(frozen=True)
class Scales:
    """The record's own length, force and time scales (SI): every fit is expressed in them."""

    length_m: float
    force_N: float
    time_s: float

    @classmethod
    def joint(cls, trials: list[TrialData]) -> Scales:
        return cls(max(t.scales.length_m for t in trials), max(t.scales.force_N for t in trials),
                   float(np.median([t.scales.time_s for t in trials])))


@dataclass
class TrialData:
    """One record on a uniform time grid, as every fit sees it: the ``motion`` (time,
    indentation, velocity), the measured ``force_N`` and each sample's ``phase`` (ramp,
    hold_early, hold_late, return, or "" outside every phase).

    ``scales`` are the record's own force, length and time scales (from its data, never a
    tissue's), which relative parameter bounds and hidden-effect sizes are taken from.
    ``baseline_N`` and ``baseline_noise_N``: the force at rest before contact and its noise;
    ``contact_m`` and ``contact_estimated``: where contact was placed (an estimate from the force
    alone is refined by every fit, as a parameter of the record). ``held``: samples whose force
    a controller held, fitted in creep form (`rig.analysis.material.creep`), with ``held_force_N``,
    ``creep_weight_N_per_m`` and ``held_noise_ar`` for that form. ``force_unit`` and
    ``length_unit`` say how to show its numbers; ``notes`` and ``meta``: what loading it found
    and what the file says beyond its samples.
    """

    name: str
    motion: Motion
    force_N: np.ndarray
    phase: np.ndarray  # phase name per sample ("" = outside every phase)
    baseline_noise_N: float | None  # the noise of the quiet force at rest before contact, if enough
    source: str
    baseline_n: int = 0
    scales: Scales | None = None
    baseline_N: np.ndarray | None = None  # the force at rest before contact, as recorded
    force_unit: tuple[float, str] = (1.0, "N")  # how to show forces of this record
    length_unit: tuple[float, str] = (1e-3, "mm")
    notes: list[str] = field(default_factory=list)
    meta: dict = field(default_factory=dict)  # what the file says beyond its samples (Record.meta)
    contact_m: float | None = None  # where the analysis put contact, in the record's travel from its start
    # contact found from the force alone (an approach): only a first estimate, which every fit
    # refines as a parameter of the record (rig.analysis.fitting.fit), and the force kept as recorded
    contact_estimated: bool = False
    # per sample: the force was held by a controller (the rig's ramp_force and hold_force, an AFM's
    # creep-compliance pause), so the indentation is what responds: these samples are fitted in
    # creep form (rig.analysis.material.creep); None or all False: force form throughout
    held: np.ndarray | None = None
    # how a length residual on held samples counts against a force residual: the force noise over
    # the length noise (N/m), measured once from the first fit's creep residual (rig.analysis.material.creep)
    creep_weight_N_per_m: float | None = None
    # the force the tissue is taken to carry on held samples: the reading smoothed within each
    # held step (`held_force`); the measured force elsewhere
    held_force_N: np.ndarray | None = None
    # the spectrum of the position's noise on held samples (AR coefficients: the force loop's
    # jitter is correlated over its response time), what a right model's creep residual shows
    held_noise_ar: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.scales is None:
            self.scales = record_scales(self.motion, self.force_N, self.phase)

    @property
    def n(self) -> int:
        return len(self.force_N)

    @property
    def creep(self) -> bool:
        """Whether some samples are fitted in creep form."""
        return self.held is not None and bool(np.any(self.held))

    @property
    def quiet_n(self) -> int:
        """Samples at the start of the record where the force is at rest (its own approach
        before contact); 0 when the force at rest was recorded apart from it (a tare)."""
        b = self.baseline_N
        if b is None or not 0 < len(b) <= self.n or not np.array_equal(self.force_N[:len(b)], b):
            return 0
        return len(b)

    def mask(self, phase: str) -> np.ndarray:
        return self.phase == phase


def decimate(t: TrialData, stride: int) -> TrialData:
    """Every `stride`-th sample (the velocity is already smoothed), same scales and units."""
    m = t.motion
    sl = slice(None, None, stride)
    motion = Motion(m.t_s[sl], m.x_m[sl], m.v_m_s[sl], m.dt_s * stride, m.record)
    return replace(t, motion=motion, force_N=t.force_N[sl], phase=t.phase[sl], scales=t.scales,
                   held=t.held[sl] if t.held is not None else None,
                   held_force_N=t.held_force_N[sl] if t.held_force_N is not None else None)


SEGMENTS = ("all", "approach")
FORMS = ("auto", "creep", "force")
HELD_STEPS = ("ramp_force", "hold_force")  # the rig's force-controlled steps
# an AFM record whose pause holds the force by feedback: afmformats' modality for it
CREEP_MODALITY = "creep-compliance"


def load_trial(path: str | Path, options: ReadOptions | int | None = None, segment: str = "all", *,
               block: int | None = None, form: str = "auto") -> TrialData:
    """A record read (`options`, or a Mach-1 `block`) and prepared (`segment`: all or approach;
    `form`: see `prepare`)."""
    return prepare(read_record(path, options, block=block), str(path), segment, form)


def approach_only(rec: Record, where: str) -> Record:
    """The record up to the end of its approach: the instrument's own segment where it says so,
    else up to the first sample at the deepest point of the travel."""
    if rec.segment is not None and np.any(rec.segment == "approach"):
        keep = np.flatnonzero(rec.segment == "approach")
        end = int(keep[-1]) + 1
        start = int(keep[0])
    else:
        excursion = np.abs(rec.position_m - rec.position_m[0])
        start, end = 0, int(np.argmax(excursion >= np.max(excursion))) + 1
    if end - start < 10:
        raise SpecError(f"the approach holds {end - start} samples: too few to analyse", path=where)
    sl = slice(start, end)
    return Record(rec.name, rec.source, rec.t_s[sl], rec.position_m[sl], rec.force_N[sl], rec.frame,
                  rec.steps[sl] if rec.steps is not None else None, rec.baseline_force_N, rec.length_unit,
                  rec.force_unit, [*rec.notes, "the approach segment only"],
                  rec.segment[sl] if rec.segment is not None else None, dict(rec.meta))


def held_samples(rec: Record) -> np.ndarray | None:
    """Per sample, whether a controller held the force (None when the record says of none): the
    rig's force-controlled steps, or an AFM creep-compliance record's pause (its force held by the
    instrument's feedback while the height follows)."""
    if rec.steps is not None:
        held = np.isin(rec.steps, HELD_STEPS)
    elif rec.segment is not None and rec.meta.get("modality") == CREEP_MODALITY:
        held = rec.segment == "intermediate"
    else:
        return None
    return held if np.any(held) else None


def prepare(rec: Record, where: str = "", segment: str = "all", form: str = "auto", *,
            keep_pull: bool = False) -> TrialData:
    """Contact, sign, baseline, uniform grid, velocity and phases of one record (`segment`
    "approach": its approach alone, as AFM users fit an elastic contact). `form`: "auto" fits
    the samples where a controller held the force in creep form (the indentation predicted from
    the force), the rest in force form; "force" fits every sample in force form; "creep" is auto,
    refused on a record that holds no force."""
    where = where or rec.name
    if segment not in SEGMENTS:
        raise SpecError(f"segment '{segment}': expected one of {', '.join(SEGMENTS)}", path=where)
    if form not in FORMS:
        raise SpecError(f"form '{form}': expected one of {', '.join(FORMS)}", path=where)
    if segment == "approach":
        rec = approach_only(rec, where)
    if rec.n < 10:
        raise SpecError(f"{rec.n} samples: too few to analyse", path=where)
    held_rec = held_samples(rec) if form != "force" else None
    if form == "creep" and held_rec is None:
        raise SpecError("creep form asked for, but the record holds the force nowhere (no ramp_force or "
                        "hold_force step, no creep-compliance pause)", path=where)
    t, pos, f, steps = _uniform(rec.t_s, rec.position_m, rec.force_N, rec.steps)
    held = runs = None
    if held_rec is not None:
        held = _uniform_mask(rec.t_s, t, held_rec)
        # a new step (ramp_force, then hold_force) starts a new run: its force is smoothed apart
        kinds = steps if steps is not None else _uniform_mask(rec.t_s, t, rec.segment)
        runs = np.cumsum(np.r_[True, (kinds[1:] != kinds[:-1]) | (held[1:] != held[:-1])])
    dt = float(np.median(np.diff(t)))
    notes = list(rec.notes)
    contact_m = None
    estimated = False
    estimated_rest = False  # the baseline is the quiet part of the record's own approach
    if rec.frame is Frame.SURFACE:
        x = pos
        if np.max(x) <= 0.0:
            raise SpecError("no contact: the position never goes past its zero (the surface)", path=where)
        pre = np.arange(len(x)) < np.argmax(x > 0)
        tare = rec.baseline_force_N
        baseline = tare if tare is not None and len(tare) else f[pre]
    else:
        x, f, baseline, note, level = find_contact(t, pos, f, where)
        notes.append(note)
        contact_m = float(-x[0])  # x counts from contact: its first value is minus the travel to it
        estimated = level is not None
        estimated_rest = estimated
        end = end_of_contact(x, f - (level or 0.0))
        # a pull on the way out (the tip stuck) only where the adhesion effect can describe it
        pull = end_of_pull(f - (level or 0.0), end, baseline) if keep_pull else end
        if pull > end:
            notes.append(f"the specimen pulls on the probe on the way out (down to "
                         f"{force_words(float(np.min(f[end:pull]) - (level or 0.0)))}): analysed through the "
                         "pull-off, which the adhesion effect describes")
            end = pull
        if end < len(x):
            # once the probe is back out, or the force back at the baseline on the way out, the
            # sensor reads the free probe, not the push the models describe
            notes.append(f"analysed up to t = {t[end - 1] - t[0]:.4g} s, where the probe leaves the specimen "
                         "on the way out")
            t, x, f = t[:end], x[:end], f[:end]
            steps = steps[:end] if steps is not None else None
            held = held[:end] if held is not None else None
            runs = runs[:end] if runs is not None else None
    v = velocity(x, dt)
    phase = phases_from_steps(t, steps) if steps is not None else phases_from_motion(t, x, v)
    base = np.asarray(baseline, dtype=float)
    # a tare, or the rest before a surface the record knows, needs MIN_BASELINE; the quiet part of an
    # approach is measured from MIN_REST on: below, the noise would be read off the residual, where a
    # misfit shows too, and the errors jumped by orders of magnitude across 200 samples before contact
    enough = MIN_REST if estimated_rest else MIN_BASELINE
    quiet = from_baseline([base]) if len(base) >= enough else None
    noise = quiet.std_N if quiet else (float(np.std(detrend(base))) if len(base) >= 20 else None)
    m = Motion(t, x, v, dt)
    scales = record_scales(m, f, phase)
    fu = display_unit(scales.force_N, FORCE_DISPLAY)
    lu = display_unit(scales.length_m, LENGTH_DISPLAY)
    smoothed = None
    if held is not None:
        # creep form needs contact: a held sample out of contact has no indentation to predict
        held = held & (x > 0)
        if not np.any(held):
            held = None
        else:
            smoothed = held_force(f, held, runs)
            notes.append(f"creep form on {int(held.sum())} samples where the force was held (the indentation "
                         "predicted from the force, smoothed within each step); force form elsewhere")
    weight, held_ar = creep_weight(x, f, held, runs, noise, phase) if held is not None else (None, ())
    return TrialData(Path(rec.name).name, m, f, phase, noise, rec.source, len(base), scales,
                     base if len(base) >= enough else None, fu, lu, notes, dict(rec.meta), contact_m,
                     estimated, held, weight, smoothed, held_ar)


def creep_weight(x: np.ndarray, f: np.ndarray, held: np.ndarray, runs: np.ndarray,
                 noise_N: float | None, phase: np.ndarray) -> tuple[float, tuple[float, ...]]:
    """How a length residual on held samples counts against a force residual: the force noise over
    the length noise (N/m), so that either, divided by its own noise, enters one likelihood; and
    the length noise's spectrum (AR coefficients).

    Both from the record: the force noise at rest before contact (else the held force's own
    short-lag structure), the length noise the measured position's short-lag structure on the held
    samples, step by step (`rig.analysis.stats.noise.from_residual`: differences over a few dozen
    samples keep the noise and barely see the smooth creep; a step's corner would read as noise,
    so the steps too short to show it are left out). That is what a right model leaves there: on
    a simulated creep trial at two forces, the position solved with the true parameters missed
    the measured one by 0.066 mm RMS, and the position's own short-lag noise (the force loop's
    jitter and the encoder's steps) read 0.063 and 0.055 mm in the two holds.

    Only the holds count where there are any long enough (`phase`): in a force ramp the position
    runs ahead and turns within the lags the noise is read at, and one trend term shared with the
    holds cannot take it out. With a 157-sample ramp counted beside holds of 800 and 2500 samples,
    the length noise read 79 um where the holds alone read 46 and 40 um and a right model left 49
    and 31 um: every creep fit then read half the noise, and a missing effect half as strongly."""
    from rig.analysis.stats.noise import from_residual

    idx = [np.flatnonzero((runs == r) & held) for r in np.unique(runs[held])]
    holds = [i for i in idx if str(phase[i[len(i) // 2]]).startswith("hold")]
    long = ([i for i in holds if len(i) >= 128] or [i for i in idx if len(i) >= 128]
            or [max(idx, key=len)])
    length = from_residual([x[i] for i in long])
    sigma_x = length.std_N
    sigma_f = noise_N if noise_N else from_residual([f[i] for i in long]).std_N
    if not sigma_x > 0 or not sigma_f > 0:
        # a position without noise (a perfect record): the record's own secant stiffness
        return float(np.max(np.abs(f)) / max(float(np.max(np.abs(x))), 1e-300)), ()
    return float(sigma_f / sigma_x), length.ar


HELD_SMOOTHING = 0.01  # the held force's noise after smoothing, at most this share of its level
HELD_WINDOW_MAX = 101  # samples


def held_force(f: np.ndarray, held: np.ndarray, runs: np.ndarray) -> np.ndarray:
    """The force the tissue is taken to carry where a controller held it: the reading through a
    local cubic within each held step (Savitzky-Golay).

    Solved for the position, a model turns the force's noise into motion: the lag's inverse
    differentiates it (x moves by about tau / c times each reading's noise, c the damping) and a
    damping that grows with depth (x dx/dt) rectifies that motion into a steady push, so on a
    simulated creep trial with the true parameters the position solved from the raw reading was
    2.1 mm off (of 14), 0.08 mm after smoothing over 21 samples. What noise is left still pulls
    the time constants down: with the noise taken to 2 % of the force, the paper's model's tau1
    came out 5 % low over five seeds of a creep trial (at worst 2.3 standard errors); at 1 %
    (about 36 samples for a 40 mN load cell at 1 N), with the half step matched
    (`Model.predict_held`), 1.4 % low on average, 1.2 standard errors at worst. The window is the shortest (odd,
    from 5) that takes the noise, read from the run's own second differences, to HELD_SMOOTHING of
    the run's force, and at most a third of the run: a step's corners are kept (each step is
    smoothed on its own)."""
    from rig.records.afm import savgol_cubic

    out = np.array(f, dtype=float)
    for r in np.unique(runs[held]):
        idx = np.flatnonzero((runs == r) & held)
        y = f[idx]
        if len(idx) < 15:
            continue
        d2 = np.diff(y, 2)
        sigma = 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / np.sqrt(6.0)
        level = max(float(np.median(np.abs(y))), 1e-300)
        # a local cubic's value at its centre keeps about 2.25 / w of the noise's variance
        w = int(np.ceil(2.25 * (sigma / (HELD_SMOOTHING * level)) ** 2))
        w = min(max(w, 5), len(idx) // 3, HELD_WINDOW_MAX)
        w = w - 1 if w % 2 == 0 else w
        if w >= 5:
            smooth = savgol_cubic(y, w)
            # the run's last half window: a straight line through its last window, not the cubic's
            # extrapolation, whose end value carries several times the noise of its centre. That
            # value is where the model's lag leaves the held step (y = this force), and on into the
            # force-form samples after it: on a clean simulated creep trial the cubic's end left the
            # return 1.9x the noise, the line 1.0x
            h = w // 2
            i = np.arange(w, dtype=float)
            smooth[-h:] = np.polyval(np.polyfit(i, y[-w:], 1), i[-h:])
            out[idx] = smooth
    return out


def record_scales(m: Motion, f: np.ndarray, phase: np.ndarray) -> Scales:
    """Travel into the specimen, peak force, and the loading time (the first ramp's length)."""
    L = float(np.max(m.x_m)) if np.max(m.x_m) > 0 else float(np.ptp(m.x_m)) or 1.0
    F = float(np.max(np.abs(f))) or 1.0
    ramp = np.flatnonzero(phase == "ramp")
    if len(ramp) >= 2:
        ends = np.flatnonzero(np.diff(ramp) > 1)
        last = ramp[ends[0]] if len(ends) else ramp[-1]
        T = float(m.t_s[last] - m.t_s[ramp[0]])
    else:
        T = 0.0
    if T <= 0:
        T = float(m.t_s[-1] - m.t_s[0]) / 10.0
    return Scales(L, F, max(T, 2 * m.dt_s))


def _uniform(t, x, f, kinds):
    """Resample to a uniform grid (the median interval) when the sampling is not uniform to 1 %
    (instruments change rate between segments)."""
    d = np.diff(t)
    dt = float(np.median(d))
    if dt <= 0:
        raise SpecError("time does not advance")
    if np.max(np.abs(d - dt)) <= 0.01 * dt:
        return t, x, f, kinds
    tu = t[0] + dt * np.arange(int(np.floor((t[-1] - t[0]) / dt + 1e-9)) + 1)
    idx = np.clip(np.searchsorted(t, tu), 0, len(t) - 1)
    return tu, np.interp(tu, t, x), np.interp(tu, t, f), (kinds[idx] if kinds is not None else None)


def _uniform_mask(t_rec: np.ndarray, t: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A per-sample mask of the record carried to the uniform grid `t` (the nearest earlier sample)."""
    if len(t_rec) == len(t) and np.array_equal(t_rec, t):
        return mask.copy()
    idx = np.clip(np.searchsorted(t_rec, t), 0, len(t_rec) - 1)
    return mask[idx]


