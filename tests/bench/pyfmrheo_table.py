"""rig's power-law Ting fit beside PyFMRheo's (pyfmrheo on PyPI, a benchmark-only peer: imported here
and in test_bench_pyfmrheo.py only, never by `rig`), on the same samples.

    python tests/bench/pyfmrheo_table.py [--all]     # a markdown table; --all: the 15 oocyte curves

PyFMRheo 0.1.3's Ting fit is `pyfmrheo.models.ting.TingModel(geometry, R, "analytical").fit(time, F,
delta, t0, idx_tm, smooth_w, v0t, v0r)` (what its routine `routines.TingFit.doTingFit` calls after
its own contact point and Hertz fit): E(t) = E0 (t/t0)^-betaE with t0 given (1 s here, as rig's),
the same paraboloid coefficient 4/3 sqrt(R)/(1 - nu^2) (nu = 0.5), fitted E0, betaE, tc (the contact
time) and F0 (the baseline). Its analytical model is a triangle: the indentation is v0t (t - tc) up
to the sample idx_tm, then falls at v0r; the depth samples are not used. While loading its force is
the exact Lee-Radok integral; after idx_tm it is Ting's closed form with 2F1(1, 1/2 - beta; 1/2; t1/t)
taken from Butler and Wood's saddle-point approximation (`utils.signal_processing.hyp2f1_apprx`).
It has no ramp-hold model: a hold is the limit v0r -> 0 of its retract (t1 -> tm, which is the exact
Lee-Radok hold), used here with v0r = 1e-9 v0t. Its routine doTingFit fits the first extend and the
last retract segments only (a stress relaxation's pause is left out), and its reader pyfmreader
0.1.3 cannot open the oocyte files (a renamed file: KeyError 'file_name'; with that worked around,
struct.error in loadJPKcurve), so the real curves are read with afmformats, as rig reads them.

Same samples: each record is written as a CSV (t_s, position_um, force_nN) for rig and the same
arrays go to TingModel.fit. The residual of each tool's fit is then measured by this script on
those samples (rig's fit evaluated with rig's own forward model, from its reported contact point
and zero).
"""

from __future__ import annotations

import contextlib
import math
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from rig.analysis.workflow.session import AnalyzeRequest, analyze  # noqa: E402
from tests.test_viscoelastic import DT, NOISE, OFFSET, POWER, SURFACE, V, reference_force  # noqa: E402
from tests.test_viscoelastic import R as SIM_R  # noqa: E402

OOCYTES = sorted((ROOT.parent / "shared" / "realdata" / "oocyte-cell1").glob("cell1-*.jpk-force"))
REAL_R = 10e-6
NU = 0.5
T0 = 1.0
SEEDS = (0, 1, 2)
TRUTHS = (POWER, {"E0_Pa": 1e3, "beta": 0.4})
AGREE = 0.05  # the 5 %


# ------------------------------------------------------------------------------ records

def sim_arrays(truth: dict, protocol: str, seed: int, cache: dict) -> tuple:
    """tests/test_viscoelastic.py's record (paraboloid R = 5 um, 3 um/s, touch at 1 um of travel, turn
    at 1.5 s), its independent quadrature: t, travel (m), force (N) and the sample of the turn.
    "ar" approach-retract, "rh" ramp-hold, "ramp" the approach-retract's loading alone (t <= 1.5 s)."""
    base = "rh" if protocol == "rh" else "ar"
    end = {"rh": 5.0, "ar": 3.0}[base]
    t = np.arange(0.0, end, DT)
    x = np.interp(t, [0.0, 1.5, end], [0.0, 1.5 * V, 1.5 * V if base == "rh" else 0.0])
    key = (tuple(truth.items()), base)
    if key not in cache:
        touch = SURFACE / V
        if base == "rh":
            dk = ([touch, 1.5, end], [0.0, 1.5 * V - SURFACE, 1.5 * V - SURFACE])
        else:
            dk = ([touch, 1.5, 3.0 - touch, end], [0.0, 1.5 * V - SURFACE, 0.0, 0.0])
        cache[key] = reference_force(t, *dk, truth, "paraboloid")
    F = cache[key]
    f = F + OFFSET + np.random.default_rng(seed).normal(0.0, NOISE * np.max(F), len(t))  # as simulated_record
    turn = round(1.5 / DT)
    if protocol == "ramp":
        t, x, f = t[: turn + 1], x[: turn + 1], f[: turn + 1]
    return t, x, f, turn


def real_arrays(path: Path, part: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, float]:
    """An oocyte curve read with afmformats: t, tip travel into the cell (height (measured) from its
    start, less the cantilever's deflection force/k), force, the sample at the end of the extend and
    the extend's speed from the header. part "extend": the 1 s extend alone (2048 Hz, uniform);
    "ramp-hold": the pause, the extend and the 30 s pause on rig's uniform grid (the median interval,
    1/256 s, linear interpolation: what rig does with mixed rates)."""
    import afmformats

    d = afmformats.load_data(str(path))[0]
    k = float(d.metadata["spring constant"])
    seg = np.asarray(d["segment"], dtype=int)
    t, h, f = (np.asarray(d[c], dtype=float) for c in ("time", "height (measured)", "force"))
    speed = float(d.metadata["speed approach"])
    keep = seg == 1 if part == "extend" else seg <= 2
    t, h, f, seg = t[keep], h[keep], f[keep], seg[keep]
    f0 = float(np.median(f[: max(len(f) // 50, 5)]))
    travel = -(h - h[0]) - (f - f0) / k
    if part != "extend":
        dt = float(np.median(np.diff(t)))
        tu = t[0] + dt * np.arange(int(np.floor((t[-1] - t[0]) / dt + 1e-9)) + 1)
        travel, f, t = np.interp(tu, t, travel), np.interp(tu, t, f), tu
        turn = int(np.searchsorted(tu, 2.0) - 1)  # the extend ends at 2 s
    else:
        turn = len(t) - 1
    return t, travel, f, turn, speed


def write_csv(path: Path, t: np.ndarray, x: np.ndarray, f: np.ndarray) -> Path:
    path.write_text("t_s,position_um,force_nN\n" + "\n".join(
        f"{a:.9f},{b * 1e6:.9f},{c * 1e9:.9f}" for a, b, c in zip(t, x, f, strict=True)) + "\n")
    return path


# ------------------------------------------------------------------------------ the two fits

def rig_fit(csv: Path, R: float) -> dict:
    out = analyze(AnalyzeRequest([str(csv)], model="ting_power", indenter=f"paraboloid:R={R * 1e6:g}um")).json
    p, rec = out["parameters"], out["records"][0]
    return {"E0": p["E0_Pa"]["value"], "beta": p["beta"]["value"], "E0_se": p["E0_Pa"]["stderr"],
            "beta_se": p["beta"]["stderr"], "cp": rec["contact_point_m"], "zero": rec["zero_N"],
            "rmse_own": out["fit"]["rmse_N"], "n_own": out["records"][0]["samples"]}


@contextlib.contextmanager
def exact_2f1(on: bool):
    """PyFMRheo's Ting model with scipy's exact 2F1 in place of its saddle-point approximation (a
    diagnostic, not PyFMRheo as shipped): the measured cause of the retract's and hold's bias."""
    import pyfmrheo.models.ting as pt
    from scipy.special import hyp2f1

    kept = pt.hyp2f1_apprx
    if on:
        pt.hyp2f1_apprx = hyp2f1
    try:
        yield
    finally:
        pt.hyp2f1_apprx = kept


def pyfm_fit(t: np.ndarray, x: np.ndarray, f: np.ndarray, turn: int, v0t: float, v0r: float, R: float,
             exact: bool = False) -> dict:
    """PyFMRheo's TingModel (analytical, paraboloid) on these samples, started and bounded as its
    doTingFit starts it: E0 from a Hertz estimate, betaE 0.25 (its start for soft samples) within
    0.01-0.49 (its bounds for a paraboloid), F0 within 100 pN of the baseline; tc from where the
    force first rises 2 % of its rise above the baseline, within +-0.3 s."""
    from pyfmrheo.models.ting import TingModel

    n0 = max(len(f) // 20, 5)
    base = float(np.median(f[:n0]))
    rise = float(np.max(f) - base)
    tc = float(t[int(np.argmax(f - base > 0.02 * rise))])
    dmax = v0t * max(t[turn] - tc, 1e-3)
    e_init = rise / (4 / 3 * math.sqrt(R) / (1 - NU ** 2) * dmax ** 1.5)
    m = TingModel("paraboloid", R, "analytical")
    m.poisson_ratio = NU
    m.E0_init, m.E0_min, m.E0_max = e_init, e_init / 1000, np.inf
    m.tc_init, m.tc_min, m.tc_max = tc, tc - 0.3, tc + 0.3
    m.betaE_init, m.betaE_min, m.betaE_max = 0.25, 0.01, 0.49
    m.F0_init, m.F0_min, m.F0_max = base, base - 100e-12, base + 100e-12
    delta = x - x[int(np.argmin(np.abs(t - tc)))]
    with warnings.catch_warnings(), exact_2f1(exact):
        warnings.simplefilter("ignore")
        m.fit(t, f, delta, t0=T0, idx_tm=turn, smooth_w=None, v0t=v0t, v0r=v0r)
        curve = m.eval(t, f, delta, T0, turn, None, v0t, v0r)
    return {"E0": float(m.E0), "beta": float(m.betaE), "tc": float(m.tc), "F0": float(m.F0), "curve": curve}


def compare(label: str, t, x, f, turn, v0t, v0r, R, tmp: Path, truth: dict | None = None) -> dict:
    """Both fits on the same samples. The residuals are compared on the samples rig analyses (all
    of them, except after the probe has left the specimen on an approach-retract's way out: a
    prefix of the record), rig's as it reports it, PyFMRheo's from its own model there."""
    csv = write_csv(tmp / f"{label.replace(' ', '_').replace('/', '_')}.csv", t, x, f)
    r = rig_fit(csv, R)
    p = pyfm_fit(t, x, f, turn, v0t, v0r, R)
    q = pyfm_fit(t, x, f, turn, v0t, v0r, R, exact=True)
    n = r["n_own"]
    row = {"case": label, "rig_E0": r["E0"], "rig_beta": r["beta"], "rig_E0_se": r["E0_se"],
           "rig_beta_se": r["beta_se"], "pyfm_E0": p["E0"], "pyfm_beta": p["beta"],
           "exact_E0": q["E0"], "exact_beta": q["beta"],
           "dE0": p["E0"] / r["E0"] - 1, "dbeta": p["beta"] / max(r["beta"], 1e-12) - 1,
           "exact_dE0": q["E0"] / r["E0"] - 1, "exact_dbeta": q["beta"] / max(r["beta"], 1e-12) - 1,
           "rmse_rig": r["rmse_own"], "rmse_pyfm": float(np.sqrt(np.mean((f[:n] - p["curve"][:n]) ** 2))),
           "rmse_exact": float(np.sqrt(np.mean((f[:n] - q["curve"][:n]) ** 2))), "n": n, "n_all": len(t),
           "truth": truth, "rig_cp_m": r["cp"], "pyfm_tc_s": p["tc"]}
    row["agree"] = abs(row["dE0"]) < AGREE and abs(row["dbeta"]) < AGREE
    row["exact_agree"] = abs(row["exact_dE0"]) < AGREE and abs(row["exact_dbeta"]) < AGREE
    if truth:
        row["rig_err"] = max(abs(r["E0"] / truth["E0_Pa"] - 1), abs(r["beta"] / truth["beta"] - 1))
        row["pyfm_err"] = max(abs(p["E0"] / truth["E0_Pa"] - 1), abs(p["beta"] / truth["beta"] - 1))
    return row


# ------------------------------------------------------------------------------ the rows

HOLD = 1e-9  # v0r / v0t standing for a hold in PyFMRheo's triangle


def simulated_rows(tmp: Path, seeds=SEEDS, truths=TRUTHS) -> list[dict]:
    rows, cache = [], {}
    for truth in truths:
        for protocol in ("ramp", "ar", "rh"):
            for seed in seeds:
                t, x, f, turn = sim_arrays(truth, protocol, seed, cache)
                v0r = V if protocol == "ar" else V * HOLD
                label = f"sim beta={truth['beta']} {protocol} seed {seed}"
                rows.append(compare(label, t, x, f, turn, V, v0r, SIM_R, tmp, truth))
    return rows


def real_rows(tmp: Path, paths=None) -> list[dict]:
    rows = []
    for path in (OOCYTES[:5] if paths is None else paths):
        for part in ("extend", "ramp-hold"):
            t, x, f, turn, speed = real_arrays(path, part)
            v0r = speed if part == "extend" else speed * HOLD
            rows.append(compare(f"{path.stem} {part}", t, x, f, turn, speed, v0r, REAL_R, tmp))
    return rows


def why(row: dict) -> str | None:
    """The measured explanation of a difference beyond 5 %, or None when there is none.

    - "2F1": PyFMRheo's own model with the exact 2F1 agrees with rig within 5 %, rig's residual on
      the same samples is no larger than that fit's (the same model), and, the truth known, rig's
      fit lands no farther from it than PyFMRheo's as shipped: the difference is PyFMRheo's
      approximation of 2F1 after the turn (retract or hold).
    - "undetermined": rig's standard errors say the record does not determine the parameters (above
      5 % of the value) and the difference is within two of them: e.g. the oocyte's 1 s extend
      alone, which starts in contact (a preload), where both tools put beta at their lower bound.

    Whether rig's residual is also below PyFMRheo's as shipped is reported (`lower_than_shipped`),
    not required: on the oocytes, which are not a power law (rig's README: 95x the noise), the
    approximated curve is a different law and fits some of them better.
    """
    if row["agree"]:
        return None
    same_model = row["rmse_rig"] <= row["rmse_exact"] * 1.001
    closer = not row.get("truth") or row["rig_err"] <= row["pyfm_err"]
    if same_model and closer and row["exact_agree"]:
        return "2F1"
    se_e, se_b = row["rig_E0_se"], row["rig_beta_se"]
    loose = se_e > AGREE * row["rig_E0"] or se_b > AGREE * max(row["rig_beta"], 1e-12)
    within = (abs(row["pyfm_E0"] - row["rig_E0"]) < 2 * se_e
              and abs(row["pyfm_beta"] - row["rig_beta"]) < 2 * se_b)
    if loose and within:
        return "undetermined"
    return None


def markdown(rows: list[dict]) -> str:
    head = ("| case | rig E0 (Pa) | PyFMRheo E0 (Pa) | dE0 | rig beta | PyFMRheo beta | dbeta | within 5 % | "
            "RMSE rig / PyFMRheo / PyFMRheo exact 2F1 (pN, same samples) | "
            "PyFMRheo exact 2F1: E0, beta (dE0, dbeta) | explained |")
    lines = [head, "|" + "---|" * 11]
    for r in rows:
        cells = [r["case"], f"{r['rig_E0']:.1f} +/- {r['rig_E0_se']:.2g}", f"{r['pyfm_E0']:.1f}",
                 f"{100 * r['dE0']:+.2f} %", f"{r['rig_beta']:.4f} +/- {r['rig_beta_se']:.2g}",
                 f"{r['pyfm_beta']:.4f}", f"{100 * r['dbeta']:+.1f} %" if r["rig_beta"] > 1e-3 else "n/a",
                 "yes" if r["agree"] else "no",
                 f"{r['rmse_rig'] * 1e12:.0f} / {r['rmse_pyfm'] * 1e12:.0f} / {r['rmse_exact'] * 1e12:.0f}",
                 f"{r['exact_E0']:.1f}, {r['exact_beta']:.4f} ({100 * r['exact_dE0']:+.2f} %, "
                 + (f"{100 * r['exact_dbeta']:+.2f} %)" if r["rig_beta"] > 1e-3 else "n/a)"),
                 "-" if r["agree"] else (why(r) or "NO")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    import importlib.metadata
    import tempfile

    print(f"PyFMRheo {importlib.metadata.version('pyfmrheo')}")
    with tempfile.TemporaryDirectory() as tmp:
        rows = simulated_rows(Path(tmp)) + real_rows(Path(tmp), OOCYTES if "--all" in sys.argv else None)
    print(markdown(rows))
