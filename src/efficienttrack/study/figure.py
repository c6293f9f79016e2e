"""A study's figure: each method's mean test MAE against interaction time, stars at the points validation chose."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib import ticker

from efficienttrack.core.fileio import atomic_write
from efficienttrack.study.paper_table import paper_row
from efficienttrack.study.summary import entry_key, entry_order, method_label

LOG_MAE_SPAN = 10.0
"""The figure's MAE axis is logarithmic when the largest MAE drawn is more than this many times the smallest."""


def log_mae_axis(entries: Sequence[dict[str, Any]]) -> bool:
    """Whether the figure draws MAE on a log axis.

    A curve far above the others (an open-loop start, say) would flatten them on a linear one.

    Args:
        entries: :func:`~efficienttrack.study.summary.summarize`'s entries (their ``curve``).

    Returns:
        True when the largest positive MAE of the curves is more than :data:`LOG_MAE_SPAN` times the smallest.
    """
    maes = [p["mae_deg"] for e in entries for p in e["curve"] if p["mae_deg"] > 0]
    return bool(maes) and max(maes) > LOG_MAE_SPAN * min(maes)


LINE_STYLES = ("-", "--", ":", "-.", (0, (5, 1, 1, 1, 1, 1)))
"""The line of each curve of one method and loop: solid for the first (the preset's, when it ran), then dashed, dotted …
for its ``--method-set`` variants, in the report's order."""


def plot_study(entries: Sequence[dict[str, Any]], path: str | Path, paper: bool = False) -> Path:
    """MAE against interaction time, as the paper's figure: one line per method and loop (the mean over seeds).

    Closed loop in the dark, open loop in the light shade of the method's hue; a method evaluated only without
    training (PD) is a horizontal line. A star marks each seed's point chosen on the validation references (its test
    MAE), where the study held some out; no point is marked by its test MAE. With ``paper``, a hollow diamond in the
    method's colour marks the paper's Table I point of each trained method and loop drawn. The x axis is logarithmic,
    and so is the y axis when the MAEs span more than :data:`LOG_MAE_SPAN` times.

    Args:
        entries: :func:`~efficienttrack.study.summary.summarize`'s entries (their ``curve``).
        path: PNG to write.
        paper: mark the paper's Table I points (a study on the paper's simulator).

    Returns:
        The path written.
    """
    palette = plt.get_cmap("tab20")  # pairs of a dark and a light shade of each hue
    fig, ax = plt.subplots(figsize=(8, 4.8), layout="constrained")
    drawn = starred = marked = False
    variants: dict[tuple[str, str], int] = {}  # per method and loop: its curves so far, the preset's first
    for e in entries:
        trained = [p for p in e["curve"] if p["interaction_steps"] > 0]
        label = method_label(e)
        if not trained:
            mae = e["curve"][0]["mae_deg"]
            ax.axhline(mae, color="k", ls="--", lw=1, label=f"{label} ({mae:.2f}°)")
            continue
        hue = 2 * entry_order(entry_key(e))[0] % 20
        color = palette(hue if e["loop"] == "closed" else hue + 1)
        x = np.array([p["interaction_hours"] for p in trained])
        y = np.array([p["mae_deg"] for p in trained])
        variant = variants[e["method"], e["loop"]] = variants.get((e["method"], e["loop"]), -1) + 1
        style = LINE_STYLES[variant % len(LINE_STYLES)]
        ax.plot(x, y, marker="o", ls=style, color=color, ms=3, label=f"{label} ({e['loop']} loop)")
        published = paper_row(e["method"], e["loop"]) if paper else None
        if published is not None and published["interaction_hours"] is not None:
            ax.plot(published["interaction_hours"], published["mae_deg"], "D", mfc="none", color=color, ms=9, mew=2)
            marked = True
        for chosen in e.get("selected") or ():
            ax.plot(chosen["interaction_hours"], chosen["mae_deg"], "*", color=color, ms=14, markeredgecolor="k", zorder=3)
            starred = True
        drawn = True
    if drawn:
        ax.set_xscale("log")
    log_mae = log_mae_axis(entries)
    if log_mae:
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.yaxis.set_minor_formatter(ticker.FuncFormatter(_minor_label))
    else:
        ax.set_ylim(bottom=0)
    ax.set_xlabel("interaction time (h, at 20 Hz)")
    ax.set_ylabel("test MAE (°, log)" if log_mae else "test MAE (°)")
    if starred:
        ax.plot([], [], "*", color="0.6", ms=12, markeredgecolor="k", ls="none", label="chosen on validation (per seed)")
    if marked:
        ax.plot([], [], "D", mfc="none", color="0.4", ms=8, mew=2, ls="none", label="the paper's Table I")
    ax.set_title("MAE against interaction time")
    ax.grid(alpha=0.3, which="both")
    if entries:
        ax.legend(fontsize=8)
    try:
        return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)


def _minor_label(value: float, _: int) -> str:
    """A log axis's minor tick label: 2, 3 and 5 times a power of ten, plainly written (the others unlabelled)."""
    mantissa = value / 10 ** np.floor(np.log10(value))
    return f"{value:g}" if round(mantissa) in (2, 3, 5) else ""
