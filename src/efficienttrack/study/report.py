"""A study's report, rebuilt from its jobs' folders every time: table (Markdown, CSV), ``study.json`` and the figure.

Each method and loop is reported at its final point: for each seed the last point of its curve, at the end of its
budget, so that nothing is chosen by looking at the test references; then the mean and the standard deviation over
the seeds (sample standard deviation; null with one seed) of that point's interaction steps (I.S.), interaction
time (I.T. = I.S. / 20 Hz, hours), wall time and every metric of :func:`~efficienttrack.data.metrics.compute_metrics`.
Beside it, two chosen points. The selected point, in a study with validation references
(:attr:`~efficienttrack.study.jobs.Study.validation`): for each seed the point of its curve with the lowest validation
MAE, and its test metrics; a choice made without the test references, so an honest figure for "trained until it
stopped improving". The best point: the point with the lowest test MAE, as the paper's Table I reports ("when the
model converges to the optimal value"); a choice made on the test set, so an optimistic figure, labelled so.

A study with validation references gets a second table under the first: each method and loop at each seed's selected
point, with every metric, as the first gives the final point. A study on the paper's simulator (``--system paper``)
prints the paper's Table I row under each of its rows, in both tables (:mod:`efficienttrack.study.paper_table`).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib import ticker

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, write_csv, write_json
from efficienttrack.data.metrics import METRIC_KEYS, interaction_hours
from efficienttrack.envs.core import LOOPS
from efficienttrack.study.jobs import ERROR, JOBS, RESULT, STUDY_CONFIG
from efficienttrack.study.methods import METHODS
from efficienttrack.study.paper_table import is_paper_system, paper_row

METRICS = METRIC_KEYS[2:-1]
"""Table I's metrics: MAE, RMSE, FMAE, 1st/2nd-order smoothness (°), ETD-MAE, ETD-FMAE (cm)."""
FIELDS = ("interaction_steps", "interaction_hours", "wall_seconds", *METRICS)
"""What the report gives as mean ± std over seeds, at each seed's final point."""
BEST_FIELDS = ("interaction_steps", "mae_deg")
"""What it gives at each seed's selected and best points too (``selected_<field>``, ``best_<field>`` and their ``_std``)."""
COLUMNS = {
    "interaction_steps": ("I.S.", ",.0f"),
    "interaction_hours": ("I.T. (h)", ".3f"),
    "wall_seconds": ("wall (s)", ".0f"),
    "mae_deg": ("MAE (°)", ".2f"),
    "rmse_deg": ("RMSE (°)", ".2f"),
    "fmae_deg": ("FMAE (°)", ".2f"),
    "smt1_deg": ("1st oSMT (°)", ".3f"),
    "smt2_deg": ("2nd oSMT (°)", ".3f"),
    "etd_mae_cm": ("ETD-MAE (cm)", ".2f"),
    "etd_fmae_cm": ("ETD-FMAE (cm)", ".2f"),
}
"""Column heading and number format of each field in ``study.md``."""
BUNDLE = "results.json"
"""The study's results as data (:func:`report`): what ``study-plot`` redraws the table and figure from."""
BUNDLE_FORMAT = "efficienttrack-study-results/1"
"""The ``format`` field of a :data:`BUNDLE`."""
OUTPUTS = (BUNDLE, "study.json", "study.md", "study.csv", "study.png")
"""The report's files in the study folder."""
LOG_MAE_SPAN = 10.0
"""The figure's MAE axis is logarithmic when the largest MAE drawn is more than this many times the smallest."""


@dataclass(frozen=True)
class Report:
    """A study's report.

    Attributes:
        entries: the content of ``study.json``, one entry per method and loop.
        failed: job name → error, of the jobs with an ``error.json`` and no result.
        markdown: the content of ``study.md``.
        paths: the files written.
    """

    entries: list[dict[str, Any]]
    failed: dict[str, str]
    markdown: str
    paths: tuple[Path, ...]


def read_result(path: Path) -> dict[str, Any] | None:
    """A job's ``result.json``, or None when it is missing or not a finished job's result (unreadable, truncated).

    Args:
        path: the file.

    Returns:
        The result (with ``method``, ``loop``, ``seed`` and a non-empty ``curve``), or None.
    """
    try:
        result = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return result if _is_result(result) else None


def _is_result(result: Any) -> bool:
    """Whether ``result`` is a finished job's result: a mapping with ``method``, ``loop``, ``seed`` and a curve."""
    keys = ("method", "loop", "seed", "curve")
    return isinstance(result, dict) and all(key in result for key in keys) and bool(result["curve"])


def read_bundle(path: Path) -> dict[str, Any]:
    """A study's results as data (``results.json``, :func:`report` writes it): what every table and figure is drawn from.

    Args:
        path: the file.

    Returns:
        ``{"format", "system", "jobs": [result.json of each finished job], "failed": {job: error}}``.

    Raises:
        EfficientTrackError: not such a file (unreadable, or another format).
    """
    try:
        bundle = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise EfficientTrackError(f"{path}: not a readable study results file ({exc})") from exc
    if not isinstance(bundle, dict) or bundle.get("format") != BUNDLE_FORMAT or not isinstance(bundle.get("jobs"), list):
        raise EfficientTrackError(f"{path}: not a study's {BUNDLE} (format '{BUNDLE_FORMAT}')")
    jobs = [job for job in bundle["jobs"] if _is_result(job)]
    if len(jobs) != len(bundle["jobs"]):
        raise EfficientTrackError(f"{path}: {len(bundle['jobs']) - len(jobs)} job(s) lack a method, loop, seed or curve")
    return bundle


def read_jobs(out: Path) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """The finished jobs' results and the failed jobs' errors in a study folder, or in its results file.

    Args:
        out: the study folder (``out/jobs/<name>/result.json`` or ``error.json``), or its :data:`BUNDLE` file (a
            committed one, say, its folder long gone).

    Returns:
        The results (:func:`read_result`), in the order of the folders' names, and job name → error of the jobs with an
        ``error.json`` or an unreadable ``result.json``.

    Raises:
        EfficientTrackError: ``out`` holds no study (no ``jobs`` folder, not a results file).
    """
    if out.is_file():
        bundle = read_bundle(out)
        return bundle["jobs"], {str(k): str(v) for k, v in dict(bundle.get("failed") or {}).items()}
    if not (out / JOBS).is_dir():
        raise EfficientTrackError(f"{out}: no study here (no {JOBS}/ folder)")
    results, failed = [], {}
    for folder in sorted(path for path in (out / JOBS).iterdir() if path.is_dir()):
        result = read_result(folder / RESULT)
        if result is not None:
            results.append(result)
        elif (folder / RESULT).exists():  # named, never dropped: a report without it would look complete
            failed[folder.name] = f"unreadable {RESULT} (damaged or truncated): a rerun of the study runs the job again"
        elif (folder / ERROR).exists():
            try:
                failed[folder.name] = str(json.loads((folder / ERROR).read_text())["error"])
            except (OSError, ValueError, KeyError, TypeError):
                failed[folder.name] = f"unreadable {ERROR}"
    return results, failed


def stats(values: Sequence[float]) -> tuple[float | None, float | None]:
    """Mean and sample standard deviation (None for a single value; both None without values).

    Args:
        values: the values (one per seed).

    Returns:
        (mean, std).
    """
    if not values:
        return None, None
    return float(np.mean(values)), (float(np.std(values, ddof=1)) if len(values) > 1 else None)


def _label(entry: dict[str, Any]) -> str:
    """An entry's name in the table and the figure: its method's, with its ``--method-set`` changes in brackets."""
    method, changes = entry["method"], entry.get("settings_changes") or ()
    label = METHODS[method].label if method in METHODS else method
    return f"{label} ({', '.join(text.removeprefix(method + '.') for text in changes)})" if changes else label


def _order(key: tuple[str, str, tuple[str, ...]]) -> tuple[int, str, int, tuple[str, ...]]:
    """Sort key of (method, loop, changes): the registry's order (others after, by name), closed first, presets first."""
    method, loop, changes = key
    rank = list(METHODS).index(method) if method in METHODS else len(METHODS)
    return rank, method, LOOPS.index(loop) if loop in LOOPS else len(LOOPS), changes


def _key(result: dict[str, Any]) -> tuple[str, str, tuple[str, ...]]:
    """What one entry of the report gathers the seeds of: method, loop and ``--method-set`` changes."""
    return result["method"], result["loop"], tuple(result.get("settings_changes") or ())


def _flat(p: dict[str, Any]) -> dict[str, Any]:
    """A curve point as the report shows it: interaction steps and hours, wall time, the test metrics, the validation MAE.

    ``validation_mae_deg`` is None for a point not measured on validation references.
    """
    return {
        "interaction_steps": p["interaction_steps"],
        "interaction_hours": interaction_hours(p["interaction_steps"]),
        "wall_seconds": p.get("wall_seconds"),
        **p["metrics"],
        "validation_mae_deg": p["validation"]["mae_deg"] if "validation" in p else None,
    }


def selected_point(curve: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """The point of one seed's curve chosen on the validation references: the lowest validation MAE (the earlier on a tie).

    Args:
        curve: the points of a job's ``result.json``, by interaction steps.

    Returns:
        The point, or None when one of the points has no ``"validation"`` metrics (a study without validation
        references, the ILC oracle): no choice is made on part of a curve.
    """
    if not curve or any("validation" not in p for p in curve):
        return None
    return min(curve, key=lambda p: p["validation"]["mae_deg"])


def point_stats(points: Sequence[dict[str, Any]], field: str) -> tuple[float | None, float | None]:
    """Mean and sample standard deviation over seeds of one field at each seed's point (:func:`stats`).

    Args:
        points: one point per seed (:func:`_flat`'s keys).
        field: the field, e.g. ``mae_deg``; a point where it is None (no wall time recorded) is left out.

    Returns:
        (mean, std).
    """
    return stats([p[field] for p in points if p[field] is not None])


def _mean_point(steps: int, maes: list[float]) -> dict[str, Any]:
    """A point of the mean curve: the seeds' MAE at ``steps`` interaction steps, mean and std."""
    mae, std = stats(maes)
    return {"interaction_steps": steps, "interaction_hours": interaction_hours(steps), "mae_deg": mae, "mae_deg_std": std,
            "seeds": len(maes)}  # fmt: skip


def mean_curve(curves: Sequence[Sequence[dict[str, Any]]]) -> list[dict[str, Any]]:
    """The mean over seeds of their curves, point by point.

    Seeds with as many points each are averaged evaluation by evaluation, at their mean interaction count: a method
    that stops at whole episodes reaches an evaluation point a few steps past it, differently on each seed. Otherwise
    the points of equal interaction counts are averaged.

    Args:
        curves: each seed's points ("interaction_steps", "mae_deg"), in order.

    Returns:
        The mean points (:func:`_mean_point`), by interaction steps.
    """
    if len({len(points) for points in curves}) == 1:
        return [
            _mean_point(round(float(np.mean([p["interaction_steps"] for p in row]))), [p["mae_deg"] for p in row])
            for row in zip(*curves, strict=True)
        ]
    by_steps: dict[int, list[float]] = {}
    for points in curves:
        for p in points:
            by_steps.setdefault(p["interaction_steps"], []).append(p["mae_deg"])
    return [_mean_point(steps, maes) for steps, maes in sorted(by_steps.items())]


def summarize(results: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One entry per method, loop and settings: mean ± std over seeds of each seed's final, selected and best points; curves.

    Args:
        results: the jobs' ``result.json`` contents.

    Returns:
        Entries ordered as :data:`~efficienttrack.study.methods.METHODS`, closed loop first, a method's preset before its
        ``--method-set`` changes: ``{"method", "loop", "settings_changes": [change] (only with changes), "seeds": [int],
        "interaction_steps", "interaction_hours", "wall_seconds", "mae_deg", "rmse_deg", "fmae_deg", "smt1_deg",
        "smt2_deg", "etd_mae_cm", "etd_fmae_cm" (means at the final points) and each with ``_std``,
        "selected_interaction_steps", "selected_mae_deg" and their ``_std`` (the test MAE at the points selected on
        validation; None unless every seed has one), "best_interaction_steps", "best_mae_deg" and their ``_std`` (at
        the best points on test), "per_joint_mae_deg": [4], "episodes", "steps": the test set, "final", "best": [per
        seed: the point], "selected": [per seed: the point] or None, "curve": [the mean over seeds at each interaction
        count: {"interaction_steps", "interaction_hours", "mae_deg", "mae_deg_std", "seeds"}], "curves": [{"seed",
        "points": [each point: interaction steps and hours, wall seconds, test metrics, "validation_mae_deg"]}]}``;
        a point of "final", "selected", "best" is ``{"seed", **that point}``.
    """
    groups: dict[tuple[str, str, tuple[str, ...]], list[dict[str, Any]]] = {}
    for result in results:
        groups.setdefault(_key(result), []).append(result)
    entries = []
    for (method, loop, changes), group in sorted(groups.items(), key=lambda item: _order(item[0])):
        group = sorted(group, key=lambda r: r["seed"])
        curves = [{"seed": r["seed"], "points": [_flat(p) for p in r["curve"]]} for r in group]
        final = [{"seed": c["seed"], **max(c["points"], key=lambda p: p["interaction_steps"])} for c in curves]
        best = [{"seed": c["seed"], **min(c["points"], key=lambda p: p["mae_deg"])} for c in curves]
        chosen = [{"seed": r["seed"], **_flat(s)} for r in group if (s := selected_point(r["curve"])) is not None]
        selected = chosen if len(chosen) == len(group) else None  # no choice made on part of the seeds
        entry: dict[str, Any] = {"method": method, "loop": loop, "seeds": [c["seed"] for c in curves]}
        if changes:
            entry["settings_changes"] = list(changes)
        for field in FIELDS:
            entry[field], entry[f"{field}_std"] = point_stats(final, field)
        for field in BEST_FIELDS:
            entry[f"selected_{field}"], entry[f"selected_{field}_std"] = point_stats(selected or [], field)
            entry[f"best_{field}"], entry[f"best_{field}_std"] = point_stats(best, field)
        entry["per_joint_mae_deg"] = np.mean([f["per_joint_mae_deg"] for f in final], axis=0).tolist()
        entry["episodes"], entry["steps"] = final[0].get("episodes"), final[0].get("steps")
        entry["final"], entry["selected"], entry["best"] = final, selected, best
        entry["curve"] = mean_curve([c["points"] for c in curves])
        entry["curves"] = curves
        entries.append(entry)
    return entries


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
        entries: :func:`summarize`'s entries.
        points: an entry's points that the row reports, one per seed (its "final", say).
        paper: put the paper's Table I row, in italics, under each row that has one.
        more: an entry's cells after the :data:`FIELDS` (empty ones in the paper's row).

    Returns:
        The rows' lines: method, loop, seeds, then the mean ± std over seeds of each of :data:`FIELDS` at the points.
    """
    lines = []
    for e in entries:
        chosen = points(e)
        extra = more(e)
        values = [cell(*point_stats(chosen, field), COLUMNS[field][1]) for field in FIELDS]
        lines.append(_row([_label(e), e["loop"], str(len(e["seeds"])), *values, *extra]))
        published = paper_row(e["method"], e["loop"]) if paper else None
        if published is not None:
            theirs = ["–" if published.get(field) is None else f"{published[field]:{COLUMNS[field][1]}}" for field in FIELDS]
            lines.append(_row(["*paper, Table I*", e["loop"], "", *(f"*{v}*" for v in theirs), *([""] * len(extra))]))
    return lines


def _chosen_cells(e: dict[str, Any]) -> list[str]:
    """The first table's cells after the metrics: the test MAE and I.S. at the selected points, then at the best."""
    return [
        cell(e[f"{which}_{field}"], e[f"{which}_{field}_std"], COLUMNS[field][1])
        for which in ("selected", "best")
        for field in ("mae_deg", "interaction_steps")
    ]


def markdown_table(entries: Sequence[dict[str, Any]], failed: dict[str, str], paper: bool = False) -> str:
    """The report as Markdown: one row per method and loop (mean ± std over seeds), and the failed jobs.

    The first table gives each method and loop at its final points; in a study with validation references (an entry
    with "selected" points) a second one gives it at the points selected on them, every metric; a method without a
    selection there (the ILC oracle) at its final points, as in the first.

    Args:
        entries: :func:`summarize`'s entries.
        failed: job name → error.
        paper: put the paper's Table I row under each row that has one (a study on the paper's simulator).

    Returns:
        The text of ``study.md``.
    """
    chosen = ["selected MAE (°)", "I.S. selected", "best MAE (°)", "I.S. at best"]
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
    lines += ["", "I.S.: training interaction steps; I.T.: I.S. at 20 Hz in hours; wall: time to the final point; "
              "metrics on the held-out test references. Selected MAE: each seed's test MAE at the point of its curve "
              "with the lowest MAE on the validation references (training references held out of every method's "
              "training), and where it was; – without validation references (and for the ILC oracle). Best MAE: each "
              "seed's lowest test MAE along its curve and where it was reached, the paper's selection: chosen on the "
              "test set, an optimistic figure."]  # fmt: skip
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
        entries: :func:`summarize`'s entries (their "curves").
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
        cells = [_label(e), e["loop"], str(len(e["seeds"]))]
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


def log_mae_axis(entries: Sequence[dict[str, Any]]) -> bool:
    """Whether the figure draws MAE on a log axis.

    A curve far above the others (an open-loop start, say) would flatten them on a linear one.

    Args:
        entries: :func:`summarize`'s entries (their ``curve``).

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
        entries: :func:`summarize`'s entries (their ``curve``).
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
        label = _label(e)
        if not trained:
            mae = e["curve"][0]["mae_deg"]
            ax.axhline(mae, color="k", ls="--", lw=1, label=f"{label} ({mae:.2f}°)")
            continue
        hue = 2 * _order(_key(e))[0] % 20
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


def _study_system(out: Path) -> dict[str, Any]:
    """The system a study folder (or results file) ran on, from its ``study_config.json`` (empty when it is missing)."""
    try:
        identity = json.loads((out if out.is_file() else out / STUDY_CONFIG).read_text())
    except (OSError, ValueError):
        return {}
    system = identity.get("system") if isinstance(identity, dict) else None
    return system if isinstance(system, dict) else {}


def report(out: str | Path) -> Report:
    """Rebuild the study's report from its jobs' folders: ``study.json``, ``study.md``, ``study.csv``, ``study.png``.

    It also writes the results as data, :data:`BUNDLE`: the study's identity and every job's curve (per seed and
    point: interaction steps, wall time, test and validation metrics; the job's settings changes and provenance, with
    the commit), from which ``study-plot`` redraws the table and the figure without the folder.

    Args:
        out: the study folder (``out/jobs/<name>/result.json`` of each finished job).

    Returns:
        The report.

    Raises:
        EfficientTrackError: ``out`` holds no study (no ``jobs`` folder).
    """
    out = Path(out)
    results, failed = read_jobs(out)
    entries = summarize(results)
    paper = is_paper_system(_study_system(out))
    markdown = markdown_table(entries, failed, paper)
    fields = (*FIELDS, *(f"{which}_{field}" for which in ("selected", "best") for field in BEST_FIELDS))
    header = ["method", "loop", "seeds", *(name for field in fields for name in (field, f"{field}_std")), "settings_changes"]
    rows = (
        [e["method"], e["loop"], " ".join(map(str, e["seeds"])), *(e[name] for name in header[3:-1]),
         " ".join(e.get("settings_changes", ()))]
        for e in entries
    )  # fmt: skip
    identity = json.loads((out / STUDY_CONFIG).read_text()) if (out / STUDY_CONFIG).is_file() else {}
    bundle = {"format": BUNDLE_FORMAT, "system": _study_system(out), "study": identity, "jobs": results, "failed": failed}
    paths = (
        write_json(out / BUNDLE, bundle),
        write_json(out / "study.json", entries),
        atomic_write(out / "study.md", lambda f: f.write(markdown), mode="w"),
        write_csv(out / "study.csv", header, rows),
        plot_study(entries, out / "study.png", paper),
    )
    return Report(entries, failed, markdown, paths)


def _same_measurement(result: dict[str, Any], held: dict[str, Any]) -> bool:
    """Whether two jobs' results are one measurement of a method that ignores the seed: the same test figures."""
    method = METHODS.get(result["method"])
    if method is None or method.seeded:
        return False
    return [p["metrics"] for p in result["curve"]] == [p["metrics"] for p in held["curve"]]


def _longer_note(job: str, kept: tuple[Path, dict[str, Any]], dropped: tuple[Path, dict[str, Any]]) -> str:
    """The table's note on a job found in two folders at two budgets: which (folder, result) is shown."""
    return f"{job}: {kept[0]}'s {kept[1]['budget']:,} steps in place of {dropped[0]}'s {dropped[1]['budget']:,}"


def combine(folders: Sequence[str | Path], path: str | Path) -> Report:
    """One table and one figure of several study folders (studies of one system run in several sittings).

    Args:
        folders: study folders (each ``jobs/<name>/result.json``); a method, loop and seed may be in one of them only,
            except for a method whose outcome does not depend on the seed (PD, the ILC oracle): a job of it found again,
            at any seed, with the same test figures is the same measurement, taken once; and a job run again with a
            larger budget (a longer run of it), which takes the shorter one's place, as the table notes.
        path: the PNG to write (:func:`plot_study`).

    Returns:
        The combined report (its ``paths``: the figure alone).

    Raises:
        EfficientTrackError: a folder holds no study, two folders ran on different systems, or one job (method, loop,
            seed) is in two folders at one budget.
    """
    results: list[dict[str, Any]] = []
    failed: dict[str, str] = {}
    longer: list[str] = []
    owner: dict[tuple[str, str, tuple[str, ...], int], tuple[Path, dict[str, Any]]] = {}
    system: tuple[Path, dict[str, Any]] | None = None
    for folder in map(Path, folders):
        found, errors = read_jobs(folder)
        here = _study_system(folder)
        if system is not None and here != system[1]:
            raise EfficientTrackError(
                f"{folder}: ran on {here or 'an unknown system'}, {system[0]} on {system[1]}: one system only"
            )
        system = system or (folder, here)
        for result in found:
            seeded = result["method"] not in METHODS or METHODS[result["method"]].seeded
            key = (*_key(result), result["seed"] if seeded else -1)
            if key in owner:
                first, held = owner[key]
                if _same_measurement(result, held):
                    continue
                job = f"{result['method']}-{result['loop']}-s{result['seed']}"
                budgets = (result.get("budget"), held.get("budget"))
                if budgets[0] == budgets[1] or None in budgets:  # not a longer run of it: the same job twice
                    raise EfficientTrackError(f"{folder} and {first} both hold {job}: give it once")
                if held["budget"] > result["budget"]:
                    longer.append(_longer_note(job, (first, held), (folder, result)))
                    continue
                longer.append(_longer_note(job, (folder, result), (first, held)))
                results = [r for r in results if r is not held]
            owner[key] = (folder, result)
            results.append(result)
        failed |= {f"{folder}/{name}": error for name, error in errors.items()}
    entries = summarize(results)
    paper = system is not None and is_paper_system(system[1])
    markdown = markdown_table(entries, failed, paper)
    if longer:
        markdown += "\nJobs run again with a larger budget, the longer run shown: " + "; ".join(longer) + ".\n"
    return Report(entries, failed, markdown, (plot_study(entries, path, paper),))
