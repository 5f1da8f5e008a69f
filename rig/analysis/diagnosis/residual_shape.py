"""What a structured residual looks like, in words a researcher can act on.

When no effect (or not the best one) brings the error down to the sensor noise, the verdict
describes what is left: where it sits (one phase, or spread out), whether it oscillates at a
frequency, grows with depth, drifts with time, or differs between trials (such as trials at
different speeds). Each test compares the residual's structured part, its energy above the
noise, with what the noise alone would give; the scales are the record's own.
"""

from __future__ import annotations

import numpy as np

from rig.analysis.trials.data import PHASES, TrialData

CONFINED_SHARE = 0.7  # a phase holding this much of the excess energy ...
CONFINED_SAMPLES = 0.5  # ... with at most this share of the samples is where the residual sits
PERIODIC_SHARE = 0.25  # a spectral peak carrying this much of the residual's variance
PERIODIC_OVER_MEDIAN = 20.0  # ... and standing this far above the spectrum's median
DEPTH_RANK = 0.5  # rank correlation of the residual's size with depth in contact
TRIAL_SPREAD = 0.5  # trials whose mean residuals differ by this share of the structured RMSE
PARTIAL_SHARE = 0.5  # an addition removing less of the error above the noise explains only part


def not_the_answer(base_rmse_N: float, rmse_N: float, noise_N: float, trials: list[TrialData],
                   residuals: list[np.ndarray]) -> str:
    """Why an addition that still leaves a structured residual is not the answer ("" when it is):
    it removes less than half of the error above the noise, or the trials it must serve with one
    parameter set still disagree (opposite or unequal errors in the same phase), which the right
    mechanism would not leave."""
    excess0 = base_rmse_N ** 2 - noise_N ** 2
    share = 1.0 - (rmse_N ** 2 - noise_N ** 2) / excess0 if excess0 > 0 else 0.0
    if share < PARTIAL_SHARE:
        return f"it accounts for only {max(share, 0.0) * 100:.0f} % of the error above the noise"
    if _between_trials(trials, residuals, noise_N):
        return "the trials still disagree: its one parameter set does not serve them all"
    return ""


def describe(trials: list[TrialData], residuals: list[np.ndarray], noise_N: float,
             fmt=lambda v: f"{v:.4g} N") -> str:
    """One line on the shape of a residual that is more than noise ("" when nothing stands out)."""
    parts = [p for p in (_periodic(trials, residuals), _confined(trials, residuals, noise_N, fmt),
                         _with_depth(trials, residuals), _between_trials(trials, residuals, noise_N),
                         _with_time(trials, residuals)) if p]
    return "; ".join(parts)


def _excess(r: np.ndarray, noise_N: float) -> float:
    return max(float(np.sum(r ** 2)) - len(r) * noise_N ** 2, 0.0)


def _confined(trials, residuals, noise_N: float, fmt) -> str:
    by_phase = {ph: np.concatenate([r[t.mask(ph)] for t, r in zip(trials, residuals, strict=True)])
                for ph in PHASES}
    n_all = sum(len(r) for r in residuals)
    excess = {ph: _excess(r, noise_N) for ph, r in by_phase.items() if len(r)}
    total = sum(excess.values())
    if total <= 0:
        return ""
    ph = max(excess, key=excess.get)
    share, samples = excess[ph] / total, len(by_phase[ph]) / n_all
    rmse = float(np.sqrt(np.mean(by_phase[ph] ** 2)))
    mean = float(np.mean(by_phase[ph]))
    structured = np.sqrt(excess[ph] / len(by_phase[ph]))
    # a one-sided error says which way the model is off; an oscillation does not
    sign = ("" if abs(mean) < 0.5 * structured else
            "; the measured force above the model" if mean > 0 else "; the measured force below the model")
    if share >= CONFINED_SHARE and samples <= CONFINED_SAMPLES:
        return (f"confined to the {ph} phase ({share * 100:.0f} % of the structured error in "
                f"{samples * 100:.0f} % of the samples; RMSE {fmt(rmse)} there{sign})")
    return f"largest in the {ph} phase ({share * 100:.0f} % of the structured error{sign})"


def _periodic(trials, residuals) -> str:
    """A line in the spectrum of the residual, averaged over trials on a common frequency grid."""
    from scipy.signal import periodogram  # imports scipy.stats: 0.7 s a plain fit need not pay

    found = []
    for t, r in zip(trials, residuals, strict=True):
        if len(r) < 64:
            continue
        f, p = periodogram(r - np.mean(r), fs=1.0 / t.motion.dt_s, detrend="linear")
        f, p = f[1:], p[1:]
        k = int(np.argmax(p))
        # the peak's share of the variance: the bins of its line (a window's leakage included)
        line = float(np.sum(p[max(k - 1, 0):k + 2]))
        if line >= PERIODIC_SHARE * float(np.sum(p)) and p[k] >= PERIODIC_OVER_MEDIAN * float(np.median(p)) \
                and f[k] * len(r) * t.motion.dt_s >= 3:  # at least three periods in the record
            found.append(f[k])
    if found and len(found) * 2 > len(trials):
        return f"periodic at {float(np.median(found)):.2g} Hz"
    return ""


def _with_depth(trials, residuals) -> str:
    from scipy.stats import spearmanr

    x = np.concatenate([t.motion.x_m[t.mask("ramp")] for t in trials])
    r = np.concatenate([res[t.mask("ramp")] for t, res in zip(trials, residuals, strict=True)])
    if len(r) < 20 or np.ptp(x) <= 0:
        return ""
    # the structured part of the ramp residual, smoothed over a few samples, against depth
    w = max(3, len(r) // 50)
    smooth = np.convolve(r, np.ones(w) / w, mode="same")
    rho = spearmanr(x, np.abs(smooth)).statistic
    if np.isfinite(rho) and rho >= DEPTH_RANK:
        return "growing with depth during the ramp"
    return ""


def _between_trials(trials, residuals, noise_N: float) -> str:
    """Trials that disagree in the same phase: what one shared parameter set cannot serve."""
    if len(trials) < 2:
        return ""
    for ph in ("hold_early", "hold_late", "ramp"):
        means = [float(np.mean(r[t.mask(ph)])) for t, r in zip(trials, residuals, strict=True)
                 if np.any(t.mask(ph))]
        if len(means) < 2:
            continue
        r_all = np.concatenate([r[t.mask(ph)] for t, r in zip(trials, residuals, strict=True)])
        structured = np.sqrt(max(float(np.mean(r_all ** 2)) - noise_N ** 2, 0.0))
        if structured <= 0 or np.ptp(means) < TRIAL_SPREAD * 2 * structured:
            continue
        speeds = [t.motion.loading_speed_m_s for t in trials]
        order = np.argsort(speeds)
        signs = {np.sign(means[i]) for i in order}
        what = "of opposite sign" if len(signs) > 1 else "of different size"
        if np.ptp(speeds) > 0.1 * max(speeds):
            return (f"{what} in the {ph} phase of trials at different speeds (mean "
                    + ", ".join(f"{means[i]:+.3g}" for i in order) + " from the slowest to the fastest): "
                    "what differs between the trials is not shared by one parameter set")
        return f"{what} in the {ph} phase of different trials: not shared by one parameter set"
    return ""


def _with_time(trials, residuals) -> str:
    """A slow trend across the whole record, also out of contact."""
    slopes = []
    for t, r in zip(trials, residuals, strict=True):
        tt = t.motion.t_s - t.motion.t_s[0]
        if len(r) < 20 or np.ptp(tt) <= 0:
            return ""
        a, b = np.polyfit(tt, r, 1)
        trend = a * tt + b
        if np.sum(trend ** 2) < 0.5 * np.sum(r ** 2) or np.sum((r - trend) ** 2) > 0.5 * np.sum(r ** 2):
            return ""
        slopes.append(a)
    same_sign = slopes and all(s * slopes[0] > 0 for s in slopes)
    return "drifting with time over the whole record" if same_sign else ""
