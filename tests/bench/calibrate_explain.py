"""Calibration of `--explain` by simulation: how large must a hidden effect be to be named,
and how often is something named when nothing is hidden?

Every run simulates the trials of `tests/test_explain.py` (two ramps to 30 mm at 1.5 and
3 mm/s, a 30 s hold, 60 s for a second relaxation branch; the specimen cycles through A, B,
C) with one hidden effect at a multiple of the size that test uses, or none (a control),
fits the proposed model and runs `explain`. Seeds start at 100, apart from the tests'.

An effect's size is given in units of the sensor noise: the RMS over the trials of the force
it adds (the same trials simulated without noise, with and without it), over the noise's
standard deviation. A run finds the effect when the verdict's `best` is it (`+wrong`: it
named another); on a control any `best` is a false suggestion. Every candidate's dBIC and
error drop are stored, so the table can be recomputed for other thresholds without
simulating again (`table --min-drop ...`).

    python tests/bench/calibrate_explain.py run --out calib.jsonl [--seeds 5] [--controls 50] [--jobs 2]
    python tests/bench/calibrate_explain.py table calib.jsonl [--decisive-bic -10] [--min-drop 0.05]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if __name__ == "__main__":  # run as a script: the tests package lives at the repository root
    sys.path.insert(0, str(ROOT))

from rig.analysis.diagnosis import explain as ex_mod  # noqa: E402
from rig.analysis.fitting.fit import fit  # noqa: E402
from rig.analysis.trials.data import load_trial  # noqa: E402
from rig.models import CATALOGUE, build_model  # noqa: E402
from rig.recording.logs import read_log  # noqa: E402
from rig.specs.config import RigConfig  # noqa: E402
from tests.conftest import run_sim  # noqa: E402
from tests.test_explain import SPECIMENS, SPEEDS, _default, _protocol  # noqa: E402

# Each hidden effect of tests/test_explain.py, its size parameter and the value that test uses.
# Compliance grows as the frame softens: its multiple divides the frame's stiffness.
EFFECTS = {
    "relaxation2": ("k_m_N_per_m", 60.0, {"tau_m_s": 40.0}),
    "drift": ("rate_N_per_s", 0.004, {}),
    "offset": ("force_N", 0.3, {}),
    "contact_offset": ("x0_mm", 1.5, {}),
    "delay": ("delay_s", 0.08, {}),
    "friction": ("force_N", 0.15, {}),
    "compliance": ("k_frame_N_per_m", 2000.0, {}),
}
MULTIPLES = (0.25, 0.5, 1.0)
SEED0 = 100
SPECIMEN_CYCLE = "ABC"


def effect_params(effect: str, multiple: float) -> dict:
    name, ref, fixed = EFFECTS[effect]
    value = ref / multiple if effect == "compliance" else ref * multiple
    return {name: value, **fixed}


def hold_s(effect: str | None, seed: int) -> float:
    if effect is None:  # controls on both protocols the effects are run on
        return 60.0 if seed % 2 else 30.0
    return 60.0 if effect == "relaxation2" else 30.0


def simulate(tmp: Path, specimen: str, effects: dict, seed: int, hold: float, noise: bool = True) -> list[Path]:
    paths = []
    for i, v in enumerate(SPEEDS):
        cfg = RigConfig()
        for k, val in SPECIMENS[specimen].items():
            setattr(cfg.sim.tissue, k, val)
        for name, params in effects.items():
            setattr(cfg.sim.effects, name, type(_default(name))(**params))
        if not noise:
            cfg.sim.loadcell.noise_N = 0.0
        cfg.sim.seed = seed * 10 + i
        paths.append(run_sim(_protocol(v, hold), cfg, tmp, name=f"{v}-{'n' if noise else 'q'}.mcap").log_path)
    return paths


def effect_size(effect: str, multiple: float, specimen: str) -> float:
    """RMS of the force the effect adds over the trials, in units of the sensor noise."""
    with tempfile.TemporaryDirectory() as d:
        hold = hold_s(effect, 0)
        a, b = Path(d, "with"), Path(d, "without")
        a.mkdir()
        b.mkdir()
        with_fx = simulate(a, specimen, {effect: effect_params(effect, multiple)}, 0, hold, noise=False)
        without = simulate(b, specimen, {}, 0, hold, noise=False)
        diffs = []
        for p, q in zip(with_fx, without, strict=True):
            f, g = read_log(p).samples["force_N"], read_log(q).samples["force_N"]
            n = min(len(f), len(g))
            diffs.append(f[:n] - g[:n])
    return float(np.sqrt(np.mean(np.concatenate(diffs) ** 2)) / RigConfig().sim.loadcell.noise_N)


def one_run(job: tuple[str | None, float, int]) -> dict:
    effect, multiple, seed = job
    specimen = SPECIMEN_CYCLE[seed % len(SPECIMEN_CYCLE)]
    hold = hold_s(effect, seed)
    effects = {effect: effect_params(effect, multiple)} if effect else {}
    t0 = time.process_time()
    with tempfile.TemporaryDirectory() as d:
        trials = [load_trial(p) for p in simulate(Path(d), specimen, effects, seed, hold)]
        base = fit(build_model("proposed"), trials)
        ex = ex_mod.explain(base, dict(CATALOGUE))
    return {"effect": effect, "multiple": multiple, "seed": seed, "specimen": specimen, "hold_s": hold,
            "params": effects.get(effect, {}), "adequate": base.adequate, "n_eff": ex.n_eff,
            "rmse_over_noise": base.overall.rmse_N / base.noise_N, "best": ex.best,
            "ranked": [{"effect": s.effect, "delta_bic": s.delta_bic, "rmse_drop": s.rmse_drop,
                        "meaningless": bool(s.meaningless)} for s in ex.ranked],
            "cpu_s": time.process_time() - t0}


def size_job(job: tuple[str, float, str]) -> dict:
    effect, multiple, specimen = job
    return {"size": {"effect": effect, "multiple": multiple, "specimen": specimen,
                     "noise_units": effect_size(effect, multiple, specimen)}}


def run(out: Path, seeds: int, controls: int, jobs: int, effects: list[str],
        multiples: tuple[float, ...]) -> None:
    done = set()
    if out.exists():  # resume: keep what is there
        for rec in map(json.loads, out.read_text().splitlines()):
            if "size" in rec:
                s = rec["size"]
                done.add(("size", s["effect"], s["multiple"], s["specimen"]))
            else:
                done.add((rec["effect"], rec["multiple"], rec["seed"]))
    sizes = [(e, m, sp) for e in effects for m in multiples for sp in SPECIMEN_CYCLE
             if ("size", e, m, sp) not in done]
    runs = [(None, 0.0, SEED0 + s) for s in range(controls)]
    runs += [(e, m, SEED0 + s) for s in range(seeds) for e in effects for m in multiples]
    runs = [r for r in runs if r not in done]
    t0 = time.perf_counter()
    with out.open("a") as fh, ProcessPoolExecutor(jobs) as pool:
        for rec in pool.map(size_job, sizes):
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
        for i, rec in enumerate(pool.map(one_run, runs), 1):
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            print(f"[{time.perf_counter() - t0:6.0f} s] {i}/{len(runs)} {rec['effect']} x{rec['multiple']:g} "
                  f"seed {rec['seed']}: best {rec['best']}", flush=True)


def best_of(rec: dict, decisive_bic: float, min_drop: float, suggest_bic: float) -> str | None:
    """The verdict's `best` under other thresholds (the candidates are ranked by dBIC)."""
    for s in rec["ranked"]:
        if s["meaningless"] or s["rmse_drop"] < min_drop:
            continue
        if s["delta_bic"] < (decisive_bic if rec["adequate"] else suggest_bic):
            return s["effect"]
    return None


def summarise(records: list[dict], decisive_bic: float = ex_mod.DECISIVE_BIC, min_drop: float = ex_mod.MIN_DROP,
              suggest_bic: float = ex_mod.SUGGEST_BIC, power: float = 0.9) -> dict:
    """Top-1 rate per effect and size, the smallest size found `power` of the time (at that
    size and every larger one), and the false-suggestion rate on the controls."""
    sizes: dict[tuple[str, float], list[float]] = {}
    for r in records:
        if "size" in r:
            s = r["size"]
            sizes.setdefault((s["effect"], s["multiple"]), []).append(s["noise_units"])
    runs = [r for r in records if "size" not in r]
    controls = [r for r in runs if r["effect"] is None]
    false = [r for r in controls if best_of(r, decisive_bic, min_drop, suggest_bic) is not None]
    table = {}
    for effect in EFFECTS:
        rows = []
        for m in sorted({r["multiple"] for r in runs if r["effect"] == effect}):
            cell = [r for r in runs if r["effect"] == effect and r["multiple"] == m]
            bests = [best_of(r, decisive_bic, min_drop, suggest_bic) for r in cell]
            found = sum(b == effect for b in bests)
            wrong = sum(b not in (None, effect) for b in bests)
            name, value = next(iter(cell[0]["params"].items()))
            rows.append({"multiple": m, "param": name, "value": value, "found": found, "wrong": wrong,
                         "runs": len(cell),
                         "noise_units": float(np.mean(sizes[(effect, m)])) if (effect, m) in sizes else None})
        smallest = None
        for row in reversed(rows):  # from the largest size down, while the rate holds
            if row["found"] < power * row["runs"]:
                break
            smallest = row
        if rows:
            table[effect] = {"rows": rows, "smallest": smallest}
    return {"thresholds": {"decisive_bic": decisive_bic, "min_drop": min_drop, "suggest_bic": suggest_bic},
            "effects": table, "false": len(false), "controls": len(controls),
            "false_best": sorted(best_of(r, decisive_bic, min_drop, suggest_bic) for r in false)}


def format_table(summary: dict) -> str:
    th = summary["thresholds"]
    lines = [f"thresholds: DECISIVE_BIC {th['decisive_bic']:g}, SUGGEST_BIC {th['suggest_bic']:g}, "
             f"MIN_DROP {th['min_drop']:g}",
             "| effect | named first at each size: value (size in noise units) found/runs, +wrong | "
             "smallest size found >= 90 % |",
             "|---|---|---|"]
    for effect, t in summary["effects"].items():
        cells = "; ".join(f"{r['value']:.3g}"
                          + (f" ({r['noise_units']:.2f})" if r["noise_units"] is not None else "")
                          + f" {r['found']}/{r['runs']}" + (f" +{r['wrong']}" if r["wrong"] else "")
                          for r in t["rows"])
        s = t["smallest"]
        small = (f"{s['param']} = {s['value']:.3g} ({s['noise_units']:.2f} x noise)" if s and s["noise_units"]
                 else (f"{s['param']} = {s['value']:.3g}" if s else "not reached"))
        lines.append(f"| {effect} | {t['rows'][0]['param']}: {cells} | {small} |")
    n, k = summary["controls"], summary["false"]
    rate = f"{100 * k / n:.1f} %" if n else "-"
    lines.append(f"false suggestions on clean controls: {k}/{n} ({rate})"
                 + (f": {', '.join(summary['false_best'])}" if k else ""))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--seeds", type=int, default=5)
    r.add_argument("--controls", type=int, default=50)
    r.add_argument("--jobs", type=int, default=2)
    r.add_argument("--effects", nargs="*", default=list(EFFECTS))
    r.add_argument("--multiples", type=float, nargs="*", default=list(MULTIPLES))
    t = sub.add_parser("table")
    t.add_argument("results", type=Path)
    t.add_argument("--decisive-bic", type=float, default=ex_mod.DECISIVE_BIC)
    t.add_argument("--suggest-bic", type=float, default=ex_mod.SUGGEST_BIC)
    t.add_argument("--min-drop", type=float, default=ex_mod.MIN_DROP)
    args = ap.parse_args(argv)
    if args.cmd == "run":
        run(args.out, args.seeds, args.controls, args.jobs, args.effects, tuple(args.multiples))
        args = argparse.Namespace(results=args.out, decisive_bic=ex_mod.DECISIVE_BIC,
                                  suggest_bic=ex_mod.SUGGEST_BIC, min_drop=ex_mod.MIN_DROP)
    records = [json.loads(line) for line in args.results.read_text().splitlines()]
    print(format_table(summarise(records, args.decisive_bic, args.min_drop, args.suggest_bic)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
