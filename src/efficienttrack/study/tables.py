"""A study's tables in Markdown: each method and loop at its final, selected and best points, and at equal interaction.

The numbers come from :func:`~efficienttrack.study.summary.summarize`; this module only renders them (the paper's
Table I rows under ours on its simulator, :mod:`efficienttrack.study.paper_table`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from efficienttrack.study.paper_table import paper_row
from efficienttrack.study.summary import FIELDS, method_label, point_stats

COLUMNS = {
    "interaction_steps": ("I.S.", ",.0f"),
    "interaction_hours": ("I.T. (h)", ".3f"),
    "wall_seconds": ("wall (s)", ".0f"),
    "samples_per_step": ("grad. samples / I.S.", ",.1f"),
    "mae_deg": ("MAE (°)", ".2f"),
    "rmse_deg": ("RMSE (°)", ".2f"),
    "fmae_deg": ("FMAE (°)", ".2f"),
    "smt1_deg": ("1st oSMT (°)", ".3f"),
    "smt2_deg": ("2nd oSMT (°)", ".3f"),
    "etd_mae_cm": ("ETD-MAE (cm)", ".2f"),
    "etd_fmae_cm": ("ETD-FMAE (cm)", ".2f"),
}
"""Column heading and number format of each field in ``study.md``."""


def cell(mean: float | None, std: float | None, fmt: str) -> str:
    """A table cell: ``mean ± std`` in ``fmt`` (``mean`` alone without a spread, ``–`` without a value).

    Args:
        mean: the mean.
        std: the standard deviation, or None.
        fmt: the number format, e.g. ``.2f``.

    Returns:
        The cell's text.
    """
    if mean is None:
        return "–"
    return f"{mean:{fmt}}" if std is None else f"{mean:{fmt}} ± {std:{fmt}}"


def _row(cells: Sequence[str]) -> str:
    """A Markdown table row of these cells."""
    return "| " + " | ".join(cells) + " |"


def _head(headers: Sequence[str]) -> list[str]:
    """A Markdown table's heading row and rule: the first two columns (method, loop) left-aligned, the rest right."""
    return [_row(headers), "|" + "|".join("---" if i < 2 else "---:" for i in range(len(headers))) + "|"]


def _rows(
    entries: Sequence[dict[str, Any]],
    points: Callable[[dict[str, Any]], Sequence[dict[str, Any]]],
    paper: bool,
    more: Callable[[dict[str, Any]], list[str]] = lambda e: [],
) -> list[str]:
    """A table's rows: each method and loop at one point per seed, the paper's Table I row under it on its simulator.

    Args:
        entries: :func:`~efficienttrack.study.summary.summarize`'s entries.
        points: an entry's points that the row reports, one per seed (its "final", say).
        paper: put the paper's Table I row, in italics, under the last row of each method and loop that has one
            (once under a method's variants).
        more: an entry's cells after the :data:`FIELDS` (empty ones in the paper's row).

    Returns:
        The rows' lines: method, loop, seeds, then the mean ± std over seeds of each of :data:`FIELDS` at the points.
    """
    lines = []
    last = {(e["method"], e["loop"]): i for i, e in enumerate(entries)}
    for i, e in enumerate(entries):
        chosen = points(e)
        extra = more(e)
        values = [cell(*point_stats(chosen, field), COLUMNS[field][1]) for field in FIELDS]
        lines.append(_row([method_label(e), e["loop"], str(len(e["seeds"])), *values, *extra]))
        published = paper_row(e["method"], e["loop"]) if paper and last[e["method"], e["loop"]] == i else None
        if published is not None:
            theirs = ["–" if published.get(field) is None else f"{published[field]:{COLUMNS[field][1]}}" for field in FIELDS]
            lines.append(_row(["*paper, Table I*", e["loop"], "", *(f"*{v}*" for v in theirs), *([""] * len(extra))]))
    return lines


def _interval(bounds: Sequence[float] | None) -> str:
    """A 95 % interval as a cell: ``[0.241, 0.262]``, – without one."""
    return "–" if bounds is None else f"[{bounds[0]:.3f}, {bounds[1]:.3f}]"


def _chosen_cells(e: dict[str, Any]) -> list[str]:
    """The first table's cells after the metrics.

    The final MAE's 95 % interval; the test MAE, its interval and the I.S. at the selected points; the test MAE and the
    I.S. at the best.
    """

    def at(which: str, field: str) -> str:
        return cell(e[f"{which}_{field}"], e[f"{which}_{field}_std"], COLUMNS[field][1])

    return [
        _interval(e.get("mae_deg_ci95")),
        at("selected", "mae_deg"),
        _interval(e.get("selected_mae_deg_ci95")),
        at("selected", "interaction_steps"),
        at("best", "mae_deg"),
        at("best", "interaction_steps"),
    ]


def markdown_table(entries: Sequence[dict[str, Any]], failed: dict[str, str], paper: bool = False) -> str:
    """The report as Markdown: one row per method and loop (mean ± std over seeds), and the failed jobs.

    The first table gives each method and loop at its final points; in a study with validation references (an entry
    with "selected" points) a second one gives it at the points selected on them, every metric; a method without a
    selection there (the ILC oracle) at its final points, as in the first.

    Args:
        entries: :func:`~efficienttrack.study.summary.summarize`'s entries.
        failed: job name → error.
        paper: put the paper's Table I row under each row that has one (a study on the paper's simulator).

    Returns:
        The text of ``study.md``.
    """
    chosen = ["MAE 95 % CI (°)", "selected MAE (°)", "selected 95 % CI (°)", "I.S. selected", "best MAE (°)", "I.S. at best"]
    metrics = ["method", "loop", "seeds", *(COLUMNS[field][0] for field in FIELDS)]
    lines = [
        "# Study: each method at its final point (the end of its budget), then at the point selected on validation "
        "references and at the best on test (optimistic); mean ± sample std over seeds",
        "",
        *_head([*metrics, *chosen]),
        *_rows(entries, lambda e: e["final"], paper, _chosen_cells),
    ]
    if not entries:
        lines.append("")
        lines.append("No job has finished yet.")
    lines += ["", "I.S.: training interaction steps; I.T.: I.S. at 20 Hz in hours; wall: time to the final point; grad. "
              "samples / I.S.: the batch rows the method's optimizer steps took, per interaction step (– where not "
              "counted); (reduced): a baseline run with fewer gradient samples per step than its research code "
              "(docs/baselines.md); metrics on the held-out test references. 95 % CI: a percentile bootstrap interval of the "
              "mean over the seeds (coarse with 3 seeds): two methods differ where their intervals do not overlap. "
              "Selected MAE: each seed's test MAE at the point of its curve with the lowest MAE on the validation "
              "references (training references held out of every method's training), and where it was; – without "
              "validation references (and for the ILC oracle). Best MAE: each seed's lowest test MAE along its curve "
              "and where it was reached, the paper's selection: chosen on the test set, an optimistic figure."]  # fmt: skip
    for e in entries:
        if e.get("selection_steps") is not None:
            lines += ["", f"{method_label(e)} ({e['loop']} loop): each point of its curve is a run of its own, so the point "
                      f"selected on validation was chosen among runs that took {e['selection_steps']:,.0f} interaction "
                      "steps in all (its I.S. counts its own run's alone)."]  # fmt: skip
    if paper:
        lines += ["", "*paper, Table I*: the published figures on the paper's simulator (Zou et al. 2025), each method "
                  "at its best point; I.S. of PPO summed over its 16 workers."]  # fmt: skip
    if any(e["selected"] for e in entries):
        lines += [
            "",
            "## Each method at the point its validation references chose; mean ± sample std over seeds",
            "",
            *_head(metrics),
            *_rows(entries, lambda e: e["selected"] or e["final"], paper),
            "",
            "Each seed's point with the lowest MAE on the validation references (held out of every method's "
            "training), its test metrics" + ("; the paper's rows are each method's best point." if paper else "."),
        ]
    if failed:
        lines += ["", "## Failed jobs", "", *(f"- `{name}`: {error}" for name, error in sorted(failed.items()))]
    return "\n".join(lines) + "\n"


def point_at_most(points: Sequence[dict[str, Any]], steps: int) -> dict[str, Any] | None:
    """What one seed had reached with at most ``steps`` interactions: its curve's last point at or below them.

    Args:
        points: the seed's curve points (each with "interaction_steps").
        steps: the interaction steps allowed.

    Returns:
        The point with the most interaction steps not above ``steps``, or None when every point is above them.
    """
    reached = [p for p in points if p["interaction_steps"] <= steps]
    return max(reached, key=lambda p: p["interaction_steps"]) if reached else None


def equal_interaction_table(entries: Sequence[dict[str, Any]], counts: Sequence[int]) -> str:
    """The methods at equal interaction, as Markdown: one row per method and loop, one column per interaction count N.

    A cell gives, over the seeds, the mean ± sample std of the test MAE at each seed's last curve point with at most N
    interaction steps (:func:`point_at_most`), then those points' interaction steps: one number when the seeds agree,
    else min–max. It is empty when a seed has no point so early, and when N is past every seed's final point and the
    cell would repeat the points an earlier column shows: a method's final points appear once (PD's point at 0 steps
    in the first column only).

    Args:
        entries: :func:`~efficienttrack.study.summary.summarize`'s entries (their "curves").
        counts: the interaction counts N, one column each, in increasing order (sorted, duplicates dropped).

    Returns:
        The table, its heading and the line that explains its cells.
    """
    counts = sorted(set(counts))
    headers = ["method", "loop", "seeds", *(f"≤ {n:,}" for n in counts)]
    lines = [
        "# At equal interaction: each method's test MAE with at most N interaction steps, mean ± sample std over seeds",
        "",
        *_head(headers),
    ]
    for e in entries:
        cells = [method_label(e), e["loop"], str(len(e["seeds"]))]
        finals = [max(p["interaction_steps"] for p in c["points"]) for c in e["curves"]]
        shown: list[int] | None = None  # the steps of the points of the last column filled
        for n in counts:
            reached = [point_at_most(c["points"], n) for c in e["curves"]]
            chosen = [p for p in reached if p is not None]
            steps = [p["interaction_steps"] for p in chosen]
            if len(chosen) < len(reached) or (steps == shown and n > max(finals)):
                cells.append("")
                continue
            mean, std = point_stats(chosen, "mae_deg")
            span = f"{min(steps):,}" if min(steps) == max(steps) else f"{min(steps):,}–{max(steps):,}"
            cells.append(f"{cell(mean, std, '.3f')} ({span})")
            shown = steps
        lines.append(_row(cells))
    lines += ["", "Each cell: the mean test MAE (°) over the seeds of each seed's last curve point at or below the "
              "column's interaction steps, ± sample std over seeds; in brackets the interaction steps of those points "
              "(min–max when the seeds differ). Empty: a seed has no point that early, or the final points, already "
              "shown."]  # fmt: skip
    return "\n".join(lines) + "\n"
