"""Pictures of a batch (`rig analyze --each --report DIR`): each parameter on the instrument's
grid, the error over the noise, which effect is missing where, histograms, and report.md.

A map is drawn per file that carries grid positions; curves without one (single curves, a folder
of files) get the histograms and the summary only. Cells are drawn where the instrument put
them: in µm from the file's positions (`x_m`, `y_m`) where it gives them, else on its grid
indices (`grid_x`, `grid_y`); a curve that could not be analysed is hatched, so a hole in a map
is never read as a value. Moduli are in kPa; the contact height (topography) is each curve's
fitted contact point, in µm above the map's lowest.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rig.views.plots import figure, save

NO_EFFECT = "(none)"


def _finite(rows: list[dict], col: str) -> list[float]:
    return [float(r[col]) for r in rows if isinstance(r.get(col), int | float)
            and not isinstance(r.get(col), bool) and math.isfinite(float(r[col]))]


def _grid(rows: list[dict]) -> tuple[list[int], list[int]] | None:
    gx = sorted({int(r["grid_x"]) for r in rows if r.get("grid_x") not in (None, "")})
    gy = sorted({int(r["grid_y"]) for r in rows if r.get("grid_y") not in (None, "")})
    return (gx, gy) if len(gx) * len(gy) > 1 else None


UM = 1e-6


@dataclass
class Layout:
    """Where a map's cells go on the page. With the instrument's positions (`x_m`, `y_m`): every
    grid index from the first to the last (a map cut from a larger one keeps its gaps), placed in
    µm, `pitch_um` per grid step; without: the grid indices the rows have, one unit apart."""

    gx: list[int]
    gy: list[int]
    origin_um: tuple[float, float] | None = None  # position of grid index (0, 0)
    pitch_um: tuple[float, float] | None = None  # per grid step along x and y (signed)

    @property
    def in_um(self) -> bool:
        return self.pitch_um is not None

    def centre(self, ix: int, iy: int) -> tuple[float, float]:
        """The centre of cell (grid_x, grid_y) in the axes' coordinates."""
        if self.pitch_um is None:
            return float(self.gx.index(ix)), float(self.gy.index(iy))
        return (self.origin_um[0] + self.pitch_um[0] * ix, self.origin_um[1] + self.pitch_um[1] * iy)

    @property
    def cell(self) -> tuple[float, float]:
        return (abs(self.pitch_um[0]), abs(self.pitch_um[1])) if self.pitch_um else (1.0, 1.0)

    @property
    def extent(self) -> list[float] | None:
        if self.pitch_um is None:
            return None
        (x0, y0), (x1, y1) = self.centre(self.gx[0], self.gy[0]), self.centre(self.gx[-1], self.gy[-1])
        hx, hy = self.pitch_um[0] / 2, self.pitch_um[1] / 2
        return [x0 - hx, x1 + hx, y0 - hy, y1 + hy]


def _pitch(idx: list[float], pos: list[float]) -> tuple[float, float] | None:
    """Origin and step of pos = origin + step * idx (least squares), or None (one index only)."""
    if len(set(idx)) < 2:
        return None
    step, origin = np.polyfit(np.asarray(idx, float), np.asarray(pos, float), 1)
    return float(origin), float(step)


def layout(rows: list[dict]) -> Layout | None:
    """The map's layout (None: the rows are not on a grid of more than one cell)."""
    grid = _grid(rows)
    if grid is None:
        return None
    gx, gy = grid
    placed = [r for r in rows if r.get("grid_x") not in (None, "") and _num(r.get("x_m")) is not None
              and _num(r.get("y_m")) is not None]
    fx = _pitch([int(r["grid_x"]) for r in placed], [_num(r["x_m"]) / UM for r in placed])
    fy = _pitch([int(r["grid_y"]) for r in placed], [_num(r["y_m"]) / UM for r in placed])
    if fx is None and fy is None:
        return Layout(gx, gy)
    # a single row or column: its cells as wide as they are tall
    if fx is None:
        fx = (float(np.median([_num(r["x_m"]) / UM for r in placed])) - abs(fy[1]) * gx[0], abs(fy[1]))
    if fy is None:
        fy = (float(np.median([_num(r["y_m"]) / UM for r in placed])) - abs(fx[1]) * gy[0], abs(fx[1]))
    if not (fx[1] and fy[1]):
        return Layout(gx, gy)
    every_x, every_y = list(range(gx[0], gx[-1] + 1)), list(range(gy[0], gy[-1] + 1))
    return Layout(every_x, every_y, (fx[0], fy[0]), (fx[1], fy[1]))


def _num(v) -> float | None:
    if isinstance(v, bool) or v in (None, ""):
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def display(col: str) -> tuple[float, str]:
    """How a column is shown: the factor it is divided by and its label with the unit."""
    if col.endswith("_Pa"):
        return 1e3, f"{col[:-3]} (kPa)"
    if col == "rmse_over_noise":
        return 1.0, "RMSE / noise"
    if col == "quality":
        return 1.0, "quality (0-10)"
    if col == CONTACT_HEIGHT:
        return UM, "contact height (µm)"
    return 1.0, col


CONTACT_HEIGHT = "contact_height_m"


def contact_heights(rows: list[dict]) -> str | None:
    """Each curve's contact height (SI) into the rows' `contact_height_m`, above the map's lowest
    contact; what it was taken from, or None (no contact points). From `start_height_m` -
    `contact_point_m` where the table has the curves' start heights; else from the contact
    point's travel alone, which is the topography where every curve starts at one height (a
    map taken at a constant start height, as the simulated maps are)."""
    cps = [(r, _num(r.get("contact_point_m"))) for r in rows if not r.get("error")]
    cps = [(r, c) for r, c in cps if c is not None]
    if not cps:
        return None
    starts = [_num(r.get("start_height_m")) for r, _ in cps]
    absolute = all(s is not None for s in starts)
    h = [s - c for s, (_, c) in zip(starts, cps, strict=True)] if absolute else [-c for _, c in cps]
    low = min(h)
    for (r, _), v in zip(cps, h, strict=True):
        r[CONTACT_HEIGHT] = v - low
    return ("the height at contact (start height - travel to contact)" if absolute else
            "the travel to contact, less: the topography where every curve starts at one height")


def _image(rows: list[dict], col: str, gx: list[int], gy: list[int]) -> np.ndarray:
    img = np.full((len(gy), len(gx)), np.nan)
    ix, iy = {v: i for i, v in enumerate(gx)}, {v: i for i, v in enumerate(gy)}
    for r in rows:
        v = r.get(col)
        if r.get("grid_x") in (None, "") or r.get("error") or not isinstance(v, int | float):
            continue
        img[iy[int(r["grid_y"])], ix[int(r["grid_x"])]] = float(v)
    return img


def _hatch_failed(ax, rows: list[dict], lay: Layout) -> None:
    from matplotlib.patches import Rectangle

    w, h = lay.cell
    for r in rows:
        if r.get("error") and r.get("grid_x") not in (None, ""):
            cx, cy = lay.centre(int(r["grid_x"]), int(r["grid_y"]))
            ax.add_patch(Rectangle((cx - w / 2, cy - h / 2), w, h, fill=False, hatch="xxx", color="grey", lw=0))


def _axes(ax, lay: Layout) -> None:
    """Positions in µm where the file gives them; else the instrument's own grid numbers (a map
    cut from a larger one keeps them)."""
    if lay.in_um:
        ax.set_xlabel("x (µm)")
        ax.set_ylabel("y (µm)")
        ax.set_aspect("equal")
        return
    for which, g in (("x", lay.gx), ("y", lay.gy)):
        step = max(1, math.ceil(len(g) / 8))
        pos = list(range(0, len(g), step))
        getattr(ax, f"set_{which}ticks")(pos, [str(g[i]) for i in pos])
        getattr(ax, f"set_{which}label")(f"grid {which}")


def map_figure(rows: list[dict], col: str, title: str = ""):
    """One column of a map's rows on its grid (a Figure; None: off the grid or nothing to show):
    E in kPa, the contact height in µm, RMSE over the noise from 1; axes in µm where the file
    gives positions; curves that could not be analysed hatched."""
    lay = layout(rows)
    if lay is None:
        return None
    k, label = display(col)
    img = _image(rows, col, lay.gx, lay.gy) / k
    if not np.any(np.isfinite(img)):
        return None
    fig = figure(figsize=(5.4, 4.6))
    ax = fig.subplots()
    kw = {"origin": "lower", "interpolation": "nearest", "extent": lay.extent}
    if col == "rmse_over_noise":
        # 1 is the noise: what the model leaves above it is what it misses
        im = ax.imshow(img, cmap="magma", vmin=1.0, **kw)
    elif col == CONTACT_HEIGHT:
        im = ax.imshow(img, cmap="copper", **kw)
    else:
        im = ax.imshow(img, cmap="viridis", **kw)
    _hatch_failed(ax, rows, lay)
    fig.colorbar(im, ax=ax, label=label)
    _axes(ax, lay)
    ax.set_title(title or label, fontsize=9)
    return fig


def effect_figure(rows: list[dict], title: str = ""):
    """Which effect is missing where (a Figure), or None."""
    lay = layout(rows)
    effects = sorted({r.get("effect") or NO_EFFECT for r in rows if not r.get("error") and "effect" in r})
    if lay is None or not effects or effects == [NO_EFFECT]:
        return None
    code = {e: i for i, e in enumerate(effects)}
    img = np.full((len(lay.gy), len(lay.gx)), np.nan)
    ix, iy = {v: i for i, v in enumerate(lay.gx)}, {v: i for i, v in enumerate(lay.gy)}
    for r in rows:
        if not r.get("error") and r.get("grid_x") not in (None, ""):
            img[iy[int(r["grid_y"])], ix[int(r["grid_x"])]] = code[r.get("effect") or NO_EFFECT]
    from matplotlib import colormaps

    fig = figure(figsize=(5.8, 4.6))
    ax = fig.subplots()
    cmap = colormaps["tab10"].resampled(len(effects))
    im = ax.imshow(img, origin="lower", cmap=cmap, vmin=-0.5, vmax=len(effects) - 0.5, interpolation="nearest",
                   extent=lay.extent)
    _hatch_failed(ax, rows, lay)
    bar = fig.colorbar(im, ax=ax, ticks=range(len(effects)))
    bar.ax.set_yticklabels(effects, fontsize=8)
    ax.set_title(title or "the effect missing (--explain)", fontsize=9)
    _axes(ax, lay)
    return fig


def histogram_figure(rows: list[dict], col: str):
    """The column's values over the curves analysed (a Figure), in the maps' units; None under two."""
    k, label = display(col)
    vals = [v / k for v in _finite([r for r in rows if not r.get("error")], col)]
    if len(vals) < 2:
        return None
    fig = figure(figsize=(5.2, 3.4))
    ax = fig.subplots()
    ax.hist(vals, bins=min(40, max(5, int(math.sqrt(len(vals))))), color="tab:blue")
    ax.set_xlabel(label)
    ax.set_ylabel("curves")
    ax.set_title(f"{label}: {len(vals)} curves", fontsize=9)
    return fig


def write_map_report(rows: list[dict], out_dir: str | Path, params: list[str], summary: str) -> Path:
    """Figures and report.md for the rows of a batch; returns report.md's path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = [dict(r) for r in rows]  # the contact height goes into copies, not the caller's table
    height_from = contact_heights(rows)
    figures: list[tuple[str, str]] = []
    by_file: dict[str, list[dict]] = {}
    for r in rows:
        by_file.setdefault(str(r["file"]), []).append(r)
    shown = [p for p in params if not p.startswith(("x_c_m", "offset_N"))] + ["rmse_over_noise"]
    if any(r.get("quality") not in (None, "") for r in rows):
        shown.append("quality")
    if height_from:
        shown.append(CONTACT_HEIGHT)
    for k, (f, fr) in enumerate(by_file.items()):
        stem = f"map{k + 1}"
        for col in shown:
            label = display(col)[1]
            fig = map_figure(fr, col, f"{Path(f).name}: {label}")
            if fig is None:
                continue
            name = f"{stem}_{'contact_height' if col == CONTACT_HEIGHT else col}.png"
            save(fig, out / name)
            figures.append((f"{Path(f).name}: {label}", name))
        fig = effect_figure(fr, f"{Path(f).name}: the effect missing (--explain)")
        if fig is not None:
            name = f"{stem}_effect.png"
            save(fig, out / name)
            figures.append((f"{Path(f).name}: the effect missing", name))
    for col in shown:
        fig = histogram_figure(rows, col)
        if fig is None:
            continue
        name = f"hist_{'contact_height' if col == CONTACT_HEIGHT else col}.png"
        save(fig, out / name)
        figures.append((f"histogram of {display(col)[1]}", name))
    ok = [r for r in rows if not r.get("error")]
    lines = ["# Batch report", "", "```", summary, "```", ""]
    if height_from:
        lines += [f"Contact height: each curve's fitted contact point, above the lowest; from {height_from}.",
                  ""]
    caveats = Counter(c for r in ok for c in str(r.get("caveats") or "").split("; ") if c)
    if caveats:
        # what the files' readers recorded that qualifies every number here
        # (rig.analysis.workflow.inputs.caveats)
        lines += ["| caveat | curves |", "|---|---|"]
        lines += [f"| {c} | {n} |" for c, n in caveats.most_common()]
        lines.append("")
    with_sys = [r for r in ok if _num(r.get("E_Pa_sys"))]
    if any("E_Pa_sys" in r for r in ok):
        lines += ["Errors: E_Pa_stat is statistical (the noise's, given the model); E_Pa_sys systematic (how "
                  f"far the fit's range and baseline move E beyond its noise), non-zero on {len(with_sys)} of "
                  f"{len(ok)} curves.", ""]
    named = Counter(r.get("effect") for r in ok if r.get("effect"))
    if named:
        lines += ["| effect missing | curves |", "|---|---|"]
        lines += [f"| {e} | {n} |" for e, n in named.most_common()]
        lines.append("")
    lines += [f"## {title}\n\n![{title}]({name})\n" for title, name in figures]
    report = out / "report.md"
    report.write_text("\n".join(lines))
    return report
