"""Hertz (paraboloid) on every curve of every shared AFM file: `rig analyze --model hertz` against
nanite 4.2.3, the AFM community's reference (GPL: a benchmark-only peer, imported only here and in
test_bench_nanite.py), as a markdown table for the README.

    python tests/bench/nanite_table.py [../shared/realdata]

nanite is run as its users run it: `nanite.IndentationGroup(path, meta_override=...)`, the
preprocessing `compute_tip_position, correct_force_offset, correct_tip_offset,
correct_split_approach_retract` (the order nanite.preproc.autosort keeps), the initial
parameters from `idnt.get_initial_fit_parameters` with R and nu set, and
`fit_model(model_key="hertz_para", segment="approach")` once with `weight_cp=0` (plain least
squares, as rig fits) and once with nanite's default `weight_cp` (the micrometre around the
contact point down-weighted).

Which fit leaves the lower residual is judged on nanite's own data: the samples of the approach
segment nanite fitted (after its split correction) and their force. Both models are evaluated on
those samples. rig's model is mapped exactly into them: for each of nanite's samples the same
sample of rig's own record (matched by its time, or by its index when the file has no time), rig's
travel there minus rig's fitted contact point (`material.contact_point_m`, from the approach's
first sample) is the depth, and E g(depth) + `offset_N` + the baseline rig had subtracted (taken
from `rig.analysis.trials.data.prepare`, the same step `rig analyze` runs), with rig's sign, is the
force; the residual is the file's force minus that. Every step of the mapping is checked to be
exact (to 1e-6 of the range): rig's trial is its record shifted, the two forces are one up to
nanite's offset, and nanite's tip position is rig's travel up to sign and a constant (a footnote
names any curve where it is not; on these files it always is, the Chiaro's own tip-position column
included). The same figures on the instrument's approach alone (without the retract samples
nanite's split correction adds) and the two contact points are given for every curve whose E
differs by more than 3 %.
"""

from __future__ import annotations

import math
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import afmformats.errors
import nanite
import nanite.fit
import numpy as np

from rig.analysis.trials.data import prepare
from rig.analysis.workflow.session import AnalyzeRequest, analyze
from rig.errors import RigError
from rig.models.contact import contact_force, parse_indenter
from rig.records import ReadOptions, list_curves, read_record

ROOT = Path(__file__).resolve().parents[3] / "shared" / "realdata"
AFM = "afm-fd"
R_M = 10e-6
NU = 0.5
INDENTER = "paraboloid:R=10um"
PREPROCESSING = ["compute_tip_position", "correct_force_offset", "correct_tip_offset",
                 "correct_split_approach_retract"]
# what the user gives for files that do not hold their calibration (realdata/README.md)
OVERRIDES = {"fmt-ntmdt-txt-fd_": {"spring constant": 0.055, "sensitivity": 61.0},
             "fmt-afm-workshop-fd_mapping_": {"spring constant": 20.0, "sensitivity": 1e-8}}
CHIARO = "fmt-chiaro-txt_AEBP1_Indentation_002.txt"
# nanite's and afmformats' errors derive from BaseException, not Exception
WITHIN = 0.03  # rig's E within 3 % of nanite's (weight_cp=0)
TOL = 1e-6  # of a range: two arrays that are one up to rounding
FAILURES = (Exception, nanite.fit.FitKeyError, nanite.fit.FitDataError, afmformats.errors.MissingMetaDataError,
            afmformats.errors.AFMFileFormatError)


def afm_dir(root: Path = ROOT) -> Path:
    return root / AFM


def override(path: Path) -> dict | None:
    return next((v for k, v in OVERRIDES.items() if path.name.startswith(k)), None)


def read_options(path: Path, curve: int | None = None) -> ReadOptions:
    o = override(path) or {}
    return ReadOptions(curve=curve, spring_constant_N_per_m=o.get("spring constant"),
                       sensitivity_m_per_V=o.get("sensitivity"))


def curves(root: Path = ROOT) -> list[tuple[Path, int]]:
    """(file, curve number as the instrument numbers it) for every curve of every file."""
    out = []
    for path in sorted(afm_dir(root).iterdir()):
        out += [(path, c.enum) for c in list_curves(path, read_options(path))]
    return out


@dataclass
class NaniteFit:
    E_Pa: float
    contact_point_m: float
    baseline_N: float
    tip_m: np.ndarray  # nanite's tip position and force over the approach it fitted
    force_N: np.ndarray
    model_N: np.ndarray
    time_s: np.ndarray | None  # the file's time of those samples, when it has one
    index: np.ndarray  # their indices in nanite's (the file's) order
    n_total: int  # samples of the whole curve


@dataclass
class RigFit:
    json: dict
    E_Pa: float
    E_stderr: float | None  # statistical: the noise's, given the model
    # systematic: how far the fit's range and baseline move it (rig.analysis.intervals.systematic)
    E_sys: float | None
    x0_m: float  # contact point in rig's travel from the approach's first sample
    offset_N: float


@dataclass
class Compared:
    """Both fitted models on nanite's samples (the approach it fitted)."""

    rig_rmse_N: float
    nanite_rmse_N: float
    n: int
    # the same, on those of the samples the instrument itself marks as the approach (rig's data):
    # nanite's split correction adds the first samples of the retract where the force still rises
    rig_rmse_approach_N: float
    nanite_rmse_approach_N: float
    n_added: int  # samples nanite's split correction moved from the retract into the approach
    axes_differ: float  # largest difference of nanite's tip axis and rig's travel once shifted, by the range
    rig_contact_m: float  # the fitted contact points in rig's travel from the approach's first sample
    nanite_contact_m: float


@dataclass
class Row:
    path: Path
    curve: int
    label: str
    rig: RigFit | None = None
    nanite0: NaniteFit | None = None
    nanite_default: NaniteFit | None = None
    failed: list[str] = field(default_factory=list)  # "rig: why", "nanite: why"
    same: Compared | None = None

    @property
    def diff(self) -> float | None:
        if self.rig is None or self.nanite0 is None:
            return None
        return self.rig.E_Pa / self.nanite0.E_Pa - 1.0


def _why(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text[:140]}" if text else type(exc).__name__


def load_nanite(path: Path, curve: int):
    """nanite's Indentation of the curve, as a user opens it."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        group = nanite.IndentationGroup(path, meta_override=override(path))
    return next(d for d in group if int(d.enum) == curve)


def fit_nanite(idnt, R_m: float, weight_cp: float) -> NaniteFit:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        idnt.apply_preprocessing(PREPROCESSING)
        params = idnt.get_initial_fit_parameters(model_key="hertz_para").copy()
        params["R"].set(value=R_m)
        params["nu"].set(value=NU)
        idnt.fit_model(model_key="hertz_para", params_initial=params, weight_cp=weight_cp, segment="approach")
    fp = idnt.fit_properties
    if not fp.get("success", False):
        raise RuntimeError("nanite's fit did not run (fewer samples than parameters)")
    p = fp["params_fitted"]
    used = np.flatnonzero(np.asarray(idnt["fit range"], dtype=bool))
    return NaniteFit(float(p["E"].value), float(p["contact_point"].value), float(p["baseline"].value),
                     np.array(idnt["tip position"][used]), np.array(idnt["force"][used]),
                     np.array(idnt["fit"][used]),
                     np.array(idnt["time"][used]) if "time" in idnt.columns else None, used, len(idnt))


def fit_rig(path: Path, curve: int, indenter: str) -> RigFit:
    o = read_options(path, curve)
    j = analyze(AnalyzeRequest(inputs=[str(path)], model="hertz", indenter=indenter, segment="approach",
                               curve=curve, spring_constant_N_per_m=o.spring_constant_N_per_m,
                               sensitivity_m_per_V=o.sensitivity_m_per_V)).json
    m = j["material"]
    return RigFit(j, m["E_Pa"], m["E_Pa_stat"], m.get("E_Pa_sys"), m["contact_point_m"][0],
                  j["parameters"]["offset_N"]["value"])


def _shift(a: np.ndarray, b: np.ndarray) -> tuple[int, float, float]:
    """The sign s and constant c of a = s b + c, and the largest departure from it."""
    best = None
    for s in (1, -1):
        c = float(np.median(a - s * b))
        dev = float(np.max(np.abs(a - s * b - c)))
        if best is None or dev < best[2]:
            best = (s, c, dev)
    return best


def rig_on_nanite_data(path: Path, curve: int, rig: RigFit, nf: NaniteFit) -> Compared:
    """rig's fitted model on nanite's samples, beside nanite's own (see the module's doc)."""
    rec = read_record(path, read_options(path, curve))
    trial = prepare(rec, str(path), "approach")
    app = rec.segment == "approach"
    ta, pa, fa = rec.t_s[app], rec.position_m[app], rec.force_N[app]
    # rig's trial is its record's approach turned, shifted (and maybe resampled): recover how
    pi, fi = np.interp(trial.motion.t_s, ta, pa), np.interp(trial.motion.t_s, ta, fa)
    s_x, _, dev_x = _shift(trial.motion.x_m, pi)
    s_f, minus_base, dev_f = _shift(trial.force_N, fi)
    if dev_x > TOL * (float(np.ptp(pi)) or 1.0) or dev_f > TOL * (float(np.ptp(fi)) or 1.0):
        raise RuntimeError(f"rig's trial is not a shifted copy of its record (x {dev_x:.2g} m, "
                           f"f {dev_f:.2g} N)")
    base = -minus_base  # trial force = s_f raw - base
    # nanite's samples in rig's record
    if nf.time_s is not None:
        r = np.clip(np.searchsorted(rec.t_s, nf.time_s), 0, rec.n - 1)
        ok = rec.t_s[r] == nf.time_s
    else:
        if rec.n != nf.n_total:
            raise RuntimeError("no time column and rig's record is not sample for sample nanite's")
        r, ok = nf.index, np.ones(len(nf.index), bool)
    r = r[ok]
    # the same force, up to nanite's offset correction, or the samples are not the same
    _, _, dev_nf = _shift(rec.force_N[r], nf.force_N[ok])
    if dev_nf > TOL * (float(np.ptp(nf.force_N)) or 1.0):
        raise RuntimeError(f"rig's and nanite's forces differ on the same samples by {dev_nf:.2g} N")
    ind = parse_indenter(rig.json["material"]["indenter"])
    depth = s_x * (rec.position_m[r] - pa[0]) - rig.x0_m
    pred = s_f * (contact_force(ind, rig.E_Pa, depth, rig.json["material"]["poisson"]) + rig.offset_N + base)
    r_rig = rec.force_N[r] - pred
    r_nan = nf.force_N[ok] - nf.model_N[ok]
    s_t, c_t, axes = _shift(rec.position_m[r], nf.tip_m[ok])  # rig's travel = s_t tip + c_t
    inst = rec.segment[r] == "approach"

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2))) if len(x) else math.nan

    return Compared(rms(r_rig), rms(r_nan), len(r), rms(r_rig[inst]), rms(r_nan[inst]),
                    int(np.count_nonzero(~inst)), axes / (float(np.ptp(nf.tip_m)) or 1.0), rig.x0_m,
                    s_x * (s_t * nf.contact_point_m + c_t - pa[0]))


def fit_row(path: Path, curve: int, *, chiaro_header_radius: bool = False) -> Row:
    """Every fit of one curve: rig and nanite (weight_cp=0 and default) at R = 10 µm, or at the
    Chiaro header's radius (rig: `--indenter paraboloid`)."""
    R_m, indenter, label = R_M, INDENTER, str(curve)
    if chiaro_header_radius:
        R_m = parse_indenter(read_record(path).meta["indenter"]).R_m
        indenter, label = "paraboloid", f"{curve}, R = {R_m * 1e6:g} µm (header)"
    row = Row(path, curve, label)
    try:
        row.rig = fit_rig(path, curve, indenter)
    except (RigError, *FAILURES) as exc:
        row.failed.append(f"rig: {_why(exc)}")
    try:
        idnt = load_nanite(path, curve)
        row.nanite0 = fit_nanite(idnt, R_m, 0)
        row.nanite_default = fit_nanite(idnt, R_m, nanite.fit.FP_DEFAULT["weight_cp"])
    except FAILURES as exc:
        row.failed.append(f"nanite: {_why(exc)}")
    if row.rig is not None and row.nanite0 is not None:
        try:
            row.same = rig_on_nanite_data(path, curve, row.rig, row.nanite0)
        except FAILURES as exc:
            row.failed.append(f"comparison: {_why(exc)}")
    return row


def instrument_E(path: Path) -> float | None:
    own = read_record(path).meta.get("instrument_result") or {}
    return own.get("E_Pa")


# -- formatting --------------------------------------------------------------------------------

def fmt_pa(v: float | None) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    for k, u in ((1e9, "GPa"), (1e6, "MPa"), (1e3, "kPa")):
        if abs(v) >= k:
            return f"{v / k:.4g} {u}"
    return f"{v:.4g} Pa"


def fmt_n(v: float | None) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    for k, u in ((1e-6, "µN"), (1e-9, "nN"), (1e-12, "pN")):
        if abs(v) >= k:
            return f"{v / k:.4g} {u}"
    return f"{v / 1e-15:.4g} fN"


def fmt_pct(v: float | None) -> str:
    return "-" if v is None else f"{v * 100:+.1f}"


HEADER = ("| file | curve | E rig (± stat ± sys) | E nanite, weight_cp=0 | diff % | "
          "E nanite, default weight_cp | RMSE rig | RMSE nanite | could not fit |\n"
          "|---|---|---|---|---|---|---|---|---|")


def markdown_row(row: Row) -> str:
    e_rig = "-"
    if row.rig is not None:
        se, sys_ = row.rig.E_stderr, row.rig.E_sys
        e_rig = fmt_pa(row.rig.E_Pa) + (f" ± {fmt_pa(se)}" if se is not None else "") + \
            (f" ± {fmt_pa(sys_)}" if sys_ else " ± 0" if sys_ is not None else "")
    same = row.same
    cells = [row.path.name, row.label, e_rig, fmt_pa(row.nanite0 and row.nanite0.E_Pa), fmt_pct(row.diff),
             fmt_pa(row.nanite_default and row.nanite_default.E_Pa), fmt_n(same and same.rig_rmse_N),
             fmt_n(same and same.nanite_rmse_N), "; ".join(row.failed).replace("|", "/") or "-"]
    return "| " + " | ".join(cells) + " |"


def explain(row: Row) -> str:
    """What lies behind a difference in E: the residuals on nanite's data and on the instrument's
    approach alone, the samples nanite's split correction added, the two contact points, and
    whether rig's contact point sits at its bound."""
    lines = []
    if row.rig is not None:
        e, se = row.rig.E_Pa, row.rig.E_stderr
        lines.append(f"rig E {fmt_pa(e)}" + (f" ± {fmt_pa(se)} ({se / e * 100:.0f} %)" if se else ""))
        lines += [f"rig warns: {w}" for w in row.rig.json.get("warnings", []) if "bound" in w]
    if row.nanite0 is not None:
        lines.append(f"nanite E {fmt_pa(row.nanite0.E_Pa)} (weight_cp=0), "
                     f"{fmt_pa(row.nanite_default.E_Pa) if row.nanite_default else '-'} (default weight_cp)")
    c = row.same
    if c is not None:
        lines.append(f"RMSE on nanite's approach ({c.n} samples): rig {fmt_n(c.rig_rmse_N)}, "
                     f"nanite {fmt_n(c.nanite_rmse_N)}")
        lines.append(f"RMSE on the instrument's approach alone ({c.n - c.n_added} samples; nanite's split "
                     f"correction adds {c.n_added} of the retract): rig {fmt_n(c.rig_rmse_approach_N)}, "
                     f"nanite {fmt_n(c.nanite_rmse_approach_N)}")
        lines.append(f"contact point from the approach's first sample: rig {c.rig_contact_m * 1e6:.4g} µm, "
                     f"nanite {c.nanite_contact_m * 1e6:.4g} µm")
    return "\n".join(lines)


def main(root: Path = ROOT) -> None:
    if not afm_dir(root).is_dir():
        sys.exit(f"no AFM files at {afm_dir(root)}")
    rows = []
    print(HEADER, flush=True)
    for path, curve in curves(root):
        rows.append(fit_row(path, curve))
        print(markdown_row(rows[-1]), flush=True)
        if path.name == CHIARO:
            rows.append(fit_row(path, curve, chiaro_header_radius=True))
            print(markdown_row(rows[-1]), flush=True)
    print()
    print("RMSE: both fitted models on the same samples and forces, nanite's approach after its split "
          "correction (how: the docstring of tests/bench/nanite_table.py).")
    for row in rows:
        if row.same is not None and row.same.axes_differ > TOL:
            print(f"\n{row.path.name} curve {row.label}: nanite's tip position and rig's travel are not the "
                  f"same axis (they differ by {row.same.axes_differ:.2g} of the range, shifted); each model "
                  "is evaluated on its own axis at the same samples and forces.")
    for row in rows:
        if row.diff is not None and abs(row.diff) > WITHIN:
            body = explain(row).replace("\n", "; ")
            print(f"\n{row.path.name} curve {row.label}, {fmt_pct(row.diff)} %: {body}.")
    chiaro = [r for r in rows if r.path.name == CHIARO and "header" in r.label]
    if chiaro:
        r = chiaro[0]
        own = instrument_E(r.path)
        print()
        print("| Chiaro, header's radius | E | vs the instrument's own |\n|---|---|---|")
        print(f"| instrument (header) | {fmt_pa(own)} | |")
        for who, e in (("rig `--indenter paraboloid`", r.rig and r.rig.E_Pa),
                       ("nanite, weight_cp=0", r.nanite0 and r.nanite0.E_Pa),
                       ("nanite, default weight_cp", r.nanite_default and r.nanite_default.E_Pa)):
            print(f"| {who} | {fmt_pa(e)} | {fmt_pct(e / own - 1.0) if e and own else '-'} |")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT)
