"""``curves.png``: one figure of learning curves, panels declared by each runner (:class:`Panel`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["Panel", "plot_panels"]


@dataclass(frozen=True, kw_only=True)
class Panel:
    title: str
    y: tuple[str, ...]
    """Metric keys drawn in this panel (one line each; a key never logged is left out)."""
    x: str = "step"
    """The metric on the x axis (``step`` is the iteration)."""
    x_label: str = "iteration"
    y_range: tuple[float, float] | None = None
    target: float | None = None
    """A dashed horizontal line (e.g. the success rate a demo aims at)."""
    legend: tuple[str, ...] = ()
    """The lines' names in the legend, in the order of ``y`` (default: the keys)."""


def plot_panels(rows: Sequence[dict], panels: Sequence[Panel], path: str, title: str) -> str | None:
    """Draw the panels that have data into ``path``; None (and no file) if none has."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drawn = [(panel, _series(rows, panel)) for panel in panels]
    drawn = [(panel, series) for panel, series in drawn if series]
    if not drawn:
        return None
    fig, axes = plt.subplots(1, len(drawn), figsize=(5 * len(drawn), 3.6), squeeze=False)
    for ax, (panel, series) in zip(axes[0], drawn):
        names = dict(zip(panel.y, panel.legend))
        for key, (xs, ys) in series.items():
            ax.plot(xs, ys, marker="o", markersize=3, label=names.get(key, key))
        if len(series) > 1:
            ax.legend(fontsize=8)
        if panel.y_range is not None:
            ax.set_ylim(*panel.y_range)
        if panel.target is not None:
            ax.axhline(panel.target, color="grey", linestyle="--", linewidth=0.8)
        ax.set_title(panel.title)
        ax.set_xlabel(panel.x_label)
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _series(rows: Sequence[dict], panel: Panel) -> dict[str, tuple[list, list]]:
    out = {}
    for key in panel.y:
        points = [(r[panel.x], r[key]) for r in rows if panel.x in r and _finite(r.get(key))]
        if points:
            out[key] = ([p[0] for p in points], [p[1] for p in points])
    return out


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)
