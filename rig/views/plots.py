"""What every figure shares: a headless pyplot, and the background shaded by segment."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def shade_spans(ax, t: np.ndarray, labels: Sequence, colours: Mapping[str, str], alpha: float = 1.0) -> None:
    """Shade `ax` behind each run of equal labels (steps, phases) in its colour."""
    if not len(t):
        return
    start = 0
    for i in range(1, len(labels) + 1):
        if i == len(labels) or labels[i] != labels[start]:
            colour = colours.get(labels[start])
            if colour:
                ax.axvspan(t[start], t[min(i, len(t) - 1)], color=colour, alpha=alpha, lw=0)
            start = i


def figure(**kw):
    """A matplotlib Figure of its own (not pyplot's: no global state, so a web server's threads
    can each draw one); `kw` as for Figure, constrained layout by default. Save it with `save`."""
    from matplotlib.figure import Figure

    kw.setdefault("layout", "constrained")
    return Figure(**kw)


def save(fig, out, dpi: int = 110):
    """Write `fig` (PNG, or the format `out`'s suffix names) and return `out`."""
    fig.savefig(out, dpi=dpi)
    return out


_STAMP = re.compile(r"^(\d{8}-\d{6})_(.+?)(\.mcap)?$")


def trial_labels(names: Sequence[str], width: int = 42) -> list[str]:
    """Labels for trials that keep what tells them apart: a log's name less its start time
    (`20261127-030017_pig-07_paper-ramp-hold-0-75-mm-s-to-30-mm.mcap` reads `pig-07
    paper-ramp-hold-0-75-mm-s-to-30-mm`: specimen, protocol and speed), the time kept where two
    would read alike; wrapped at `width` characters rather than cut."""
    import textwrap

    stems = []
    for n in names:
        m = _STAMP.match(Path(str(n)).name)
        stems.append((m.group(2).replace("_", " "), m.group(1)) if m else (Path(str(n)).name, ""))
    seen = [s for s, _ in stems]
    out = []
    for s, stamp in stems:
        label = f"{s} ({stamp[9:11]}:{stamp[11:13]}:{stamp[13:15]})" if stamp and seen.count(s) > 1 else s
        out.append("\n".join(textwrap.wrap(label, width, break_on_hyphens=True)) or label)
    return out
