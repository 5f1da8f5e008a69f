"""What every figure shares: a headless pyplot, and the background shaded by segment."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

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
