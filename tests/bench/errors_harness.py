"""Coverage of the reported errors on synthetic Hertz curves of known truth, through the whole
pipeline a user runs (a CSV written, read, prepared, fitted): the cases of the errors' issue.

A case is (name, noise, misfit a, samples before contact). The force is the paraboloid's Hertz
law times (1 + a d/d_max), 1700 samples in contact at 1 nm each, noise NOISE_N (its kind: white,
AR(1) rho, white plus a walk whose end-to-end SD is x times the noise, or any of these twice as
loud in contact). For a = 0 the truth is the noiseless curve's fit (E, contact, zero); for a > 0
the three E of the same model fitted to the noiseless curve over the whole approach and cut at
50 % and 75 % of its peak force, which the interval (1.96 stat + sys) must hold."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from rig.analysis.fitting.fit import fit
from rig.analysis.intervals.systematic import interval, systematic
from rig.analysis.workflow.inputs import load_inputs
from rig.models.catalogue import build_model

E_TRUE, R_M, NOISE_N = 12e3, 5e-6, 50e-12
CONTACT_SAMPLES = 1700


def ar1(rng: np.random.Generator, n: int, rho: float) -> np.ndarray:
    e = rng.normal(size=n + 2000)
    x = np.empty_like(e)
    x[0] = e[0]
    for i in range(1, len(e)):
        x[i] = rho * x[i - 1] + e[i]
    x = x[2000:]
    return x * np.sqrt(1 - rho ** 2)


def noise(kind: str, arg: float, n: int, seed: int, loud: np.ndarray | None = None) -> np.ndarray:
    rng = np.random.default_rng(10_000 + seed)
    if kind == "white":
        u = rng.normal(size=n)
    elif kind == "ar1":
        u = ar1(rng, n, arg)
    elif kind == "walk":
        u = rng.normal(size=n) + np.cumsum(rng.normal(size=n)) * arg / np.sqrt(n)
    elif kind == "loud-white":
        u = rng.normal(size=n) * np.where(loud, 2.0, 1.0)
    elif kind == "loud-ar1":  # white at rest, AR(1) arg twice as loud in contact
        u = np.where(loud, 2.0 * ar1(rng, n, arg), rng.normal(size=n))
    else:
        raise ValueError(kind)
    return u * NOISE_N


def write(path: Path, t: np.ndarray, pos: np.ndarray, f: np.ndarray) -> Path:
    rows = "\n".join(f"{a:.6f},{b * 1e6:.9f},{c * 1e9:.12f}" for a, b, c in zip(t, pos, f, strict=True))
    path.write_text("t_s,position_um,force_nN\n" + rows + "\n")
    return path


def curve(pre: int, misfit: float):
    t = np.arange(pre + CONTACT_SAMPLES) * 1e-3
    pos = 1e-6 * t
    d = np.clip(pos - pre * 1e-9, 0.0, None)
    f = 4.0 / 3.0 * E_TRUE / 0.75 * np.sqrt(R_M) * d ** 1.5 * (1 + misfit * d / d.max())
    return t, pos, f, d > 0


def hertz(path: Path):
    inp = load_inputs([str(path)], [], [], indenter="paraboloid:R=5um")
    return fit(build_model("hertz", registry=inp.registry), inp.trials)


_TRUTH: dict[tuple[float, int], tuple[list[float], float]] = {}


def truth(misfit: float, pre: int, tmp: str, seed: int) -> tuple[list[float], float]:
    """The noiseless curve's three E (whole, to 50 %, to 75 % of the peak) and its contact, in
    the travel from the first sample; once a process."""
    if (misfit, pre) not in _TRUTH:
        t, pos, f, _ = curve(pre, misfit)
        res = hertz(write(Path(tmp) / f"clean-{misfit}-{pre}-{seed}.csv", t, pos, f))
        s0 = systematic(res)
        targets = [res.values["E_Pa"]] + [c.values["E_Pa"] for c in s0.choices if "% of peak" in c.name]
        _TRUTH[(misfit, pre)] = (targets, res.values["x_c_m"] + res.trials[0].contact_m)
    return _TRUTH[(misfit, pre)]


def one_seed(seed: int, kind: str, arg: float, misfit: float, pre: int, tmp: str) -> dict:
    t, pos, f, loud = curve(pre, misfit)
    targets, contact = truth(misfit, pre, tmp, seed)
    y = f + noise(kind, arg, len(t), seed, loud)
    res = hertz(write(Path(tmp) / f"n-{kind}-{arg}-{misfit}-{pre}-{seed}.csv", t, pos, y))
    found = systematic(res)
    E, stat, sys_ = res.values["E_Pa"], res.stderr["E_Pa"], found.error["E_Pa"]
    lo, hi = interval(E, stat, sys_)
    x_c = res.values["x_c_m"] + res.trials[0].contact_m - contact
    return {"E": E, "stat": stat, "sys": sys_, "held": [lo <= v <= hi for v in targets],
            "stat_held": abs(E - targets[0]) <= 1.96 * stat,
            "contact_held": abs(x_c) <= 1.96 * (res.stderr["x_c_m"] or 0.0),
            "adequate": res.adequate, "verdict": res.verdict()}


def run(kind: str, arg: float, misfit: float, pre: int, seeds: int) -> dict:
    from tests.conftest import per_seed

    with tempfile.TemporaryDirectory() as tmp:
        rows = per_seed(one_seed, range(seeds), kind, arg, misfit, pre, tmp)
    E = np.array([r["E"] for r in rows])
    stat = np.array([r["stat"] for r in rows])
    sd = float(np.std(E))
    return {"case": f"{kind} {arg:g}, misfit {misfit:g}, {pre} before contact", "seeds": seeds,
            "held": np.mean([r["held"] for r in rows], axis=0),
            "stat_held": np.mean([r["stat_held"] for r in rows]),
            "contact_held": np.mean([r["contact_held"] for r in rows]),
            "stat_over_scatter": (float(np.min(stat)) / sd, float(np.median(stat)) / sd,
                                  float(np.max(stat)) / sd),
            "sys_zero": float(np.mean([r["sys"] == 0 for r in rows])),
            "adequate": float(np.mean([r["adequate"] for r in rows]))}


def show(r: dict) -> str:
    lo, med, hi = r["stat_over_scatter"]
    held = "/".join(f"{h * 100:.0f}" for h in r["held"])
    return (f"{r['case']:<44} interval holds {held:>11} %; stat alone {r['stat_held'] * 100:3.0f} %, contact "
            f"{r['contact_held'] * 100:3.0f} %; stat/scatter {lo:.2g}-{med:.2g}-{hi:.2g}; sys 0 on "
            f"{r['sys_zero'] * 100:3.0f} %; adequate {r['adequate'] * 100:3.0f} %")


if __name__ == "__main__":
    kind, arg, misfit, pre, seeds = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), \
        int(sys.argv[5])
    print(show(run(kind, arg, misfit, pre, seeds)), flush=True)
