"""Pictures of a batch (`rig analyze --each --report DIR`): each parameter on the instrument's
grid, the error over the noise, which effect is missing where, histograms, and report.md.

A map is drawn per file that carries grid positions; curves without one (single curves, a folder
of files) get the histograms and the summary only. Cells are drawn where the instrument put
them (`grid_x`, `grid_y`); a curve that could not be analysed is hatched, so a hole in a map is
never read as a value.
"""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import numpy as np

from rig.views.plots import pyplot

NO_EFFECT = "(none)"


def _finite(rows: list[dict], col: str) -> list[float]:
    return [float(r[col]) for r in rows if isinstance(r.get(col), int | float)
            and not isinstance(r.get(col), bool) and math.isfinite(float(r[col]))]


def _grid(rows: list[dict]) -> tuple[list[int], list[int]] | None:
    gx = sorted({int(r["grid_x"]) for r in rows if r.get("grid_x") not in (None, "")})
    gy = sorted({int(r["grid_y"]) for r in rows if r.get("grid_y") not in (None, "")})
    return (gx, gy) if len(gx) * len(gy) > 1 else None


def _image(rows: list[dict], col: str, gx: list[int], gy: list[int]) -> np.ndarray:
    img = np.full((len(gy), len(gx)), np.nan)
    ix, iy = {v: i for i, v in enumerate(gx)}, {v: i for i, v in enumerate(gy)}
    for r in rows:
        v = r.get(col)
        if r.get("grid_x") in (None, "") or r.get("error") or not isinstance(v, int | float):
            continue
        img[iy[int(r["grid_y"])], ix[int(r["grid_x"])]] = float(v)
    return img


def _hatch_failed(ax, rows: list[dict], gx: list[int], gy: list[int]) -> None:
    from matplotlib.patches import Rectangle

    ix, iy = {v: i for i, v in enumerate(gx)}, {v: i for i, v in enumerate(gy)}
    for r in rows:
        if r.get("error") and r.get("grid_x") not in (None, ""):
            ax.add_patch(Rectangle((ix[int(r["grid_x"])] - 0.5, iy[int(r["grid_y"])] - 0.5), 1, 1, fill=False,
                                   hatch="xxx", color="grey", lw=0))


def _axes(ax, gx: list[int], gy: list[int]) -> None:
    """The instrument's own grid numbers on the axes (a map cut from a larger one keeps them)."""
    for which, g in (("x", gx), ("y", gy)):
        step = max(1, math.ceil(len(g) / 8))
        pos = list(range(0, len(g), step))
        getattr(ax, f"set_{which}ticks")(pos, [str(g[i]) for i in pos])
        getattr(ax, f"set_{which}label")(f"grid {which}")


def write_map_report(rows: list[dict], out_dir: str | Path, params: list[str], summary: str) -> Path:
    """Figures and report.md for the rows of a batch; returns report.md's path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plt = pyplot()
    figures: list[tuple[str, str]] = []
    by_file: dict[str, list[dict]] = {}
    for r in rows:
        by_file.setdefault(str(r["file"]), []).append(r)
    shown = [p for p in params if not p.startswith(("x_c_m", "offset_N"))] + ["rmse_over_noise"]
    for k, (f, fr) in enumerate(by_file.items()):
        grid = _grid(fr)
        if grid is None:
            continue
        gx, gy = grid
        stem = f"map{k + 1}"
        for col in shown:
            img = _image(fr, col, gx, gy)
            if not np.any(np.isfinite(img)):
                continue
            fig, ax = plt.subplots(figsize=(5.2, 4.4), constrained_layout=True)
            if col == "rmse_over_noise":
                # 1 is the noise: what the model leaves above it is what it misses
                im = ax.imshow(img, origin="lower", cmap="magma", vmin=1.0, interpolation="nearest")
            else:
                im = ax.imshow(img, origin="lower", cmap="viridis", interpolation="nearest")
            _hatch_failed(ax, fr, gx, gy)
            fig.colorbar(im, ax=ax, label=col)
            _axes(ax, gx, gy)
            ax.set_title(f"{Path(f).name}: {col}", fontsize=9)
            name = f"{stem}_{col}.png"
            fig.savefig(out / name, dpi=110)
            plt.close(fig)
            figures.append((f"{Path(f).name}: {col}", name))
        effects = sorted({r.get("effect") or NO_EFFECT for r in fr if not r.get("error") and "effect" in r})
        if effects and effects != [NO_EFFECT]:
            code = {e: i for i, e in enumerate(effects)}
            img = np.full((len(gy), len(gx)), np.nan)
            ix, iy = {v: i for i, v in enumerate(gx)}, {v: i for i, v in enumerate(gy)}
            for r in fr:
                if not r.get("error") and r.get("grid_x") not in (None, ""):
                    img[iy[int(r["grid_y"])], ix[int(r["grid_x"])]] = code[r.get("effect") or NO_EFFECT]
            fig, ax = plt.subplots(figsize=(5.6, 4.4), constrained_layout=True)
            cmap = plt.get_cmap("tab10", len(effects))
            im = ax.imshow(img, origin="lower", cmap=cmap, vmin=-0.5, vmax=len(effects) - 0.5,
                           interpolation="nearest")
            _hatch_failed(ax, fr, gx, gy)
            bar = fig.colorbar(im, ax=ax, ticks=range(len(effects)))
            bar.ax.set_yticklabels(effects, fontsize=8)
            ax.set_title(f"{Path(f).name}: the effect missing (--explain)", fontsize=9)
            _axes(ax, gx, gy)
            name = f"{stem}_effect.png"
            fig.savefig(out / name, dpi=110)
            plt.close(fig)
            figures.append((f"{Path(f).name}: the effect missing", name))
    ok = [r for r in rows if not r.get("error")]
    for col in shown:
        vals = _finite(ok, col)
        if len(vals) < 2:
            continue
        fig, ax = plt.subplots(figsize=(5.2, 3.4), constrained_layout=True)
        ax.hist(vals, bins=min(40, max(5, int(math.sqrt(len(vals))))), color="tab:blue")
        ax.set_xlabel(col)
        ax.set_ylabel("curves")
        ax.set_title(f"{col}: {len(vals)} curves", fontsize=9)
        name = f"hist_{col}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        figures.append((f"histogram of {col}", name))
    lines = ["# Batch report", "", "```", summary, "```", ""]
    named = Counter(r.get("effect") for r in ok if r.get("effect"))
    if named:
        lines += ["| effect missing | curves |", "|---|---|"]
        lines += [f"| {e} | {n} |" for e, n in named.most_common()]
        lines.append("")
    lines += [f"## {title}\n\n![{title}]({name})\n" for title, name in figures]
    report = out / "report.md"
    report.write_text("\n".join(lines))
    return report
