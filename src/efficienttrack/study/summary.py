"""A study's numbers: each method and loop over seeds at its final, selected and best points, and its mean curve.

The rendering is :mod:`~efficienttrack.study.tables` (Markdown) and :mod:`~efficienttrack.study.figure` (the figure);
reading and writing the study's files is :mod:`~efficienttrack.study.report`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from efficienttrack.data.metrics import TABLE_METRICS, interaction_hours
from efficienttrack.envs.core import LOOPS
from efficienttrack.study.methods import METHODS

FIELDS = ("interaction_steps", "interaction_hours", "wall_seconds", "samples_per_step", *TABLE_METRICS)
"""What the report gives as mean ± std over seeds, at each seed's final point."""
BEST_FIELDS = ("interaction_steps", "mae_deg")
"""What it gives at each seed's selected and best points too (``selected_<field>``, ``best_<field>`` and their ``_std``)."""


def method_label(entry: dict[str, Any]) -> str:
    """An entry's name in the table and the figure: its method's, with its ``--method-set`` changes in brackets."""
    method, changes = entry["method"], entry.get("settings_changes") or ()
    label = METHODS[method].label if method in METHODS else method
    return f"{label} ({', '.join(text.removeprefix(method + '.') for text in changes)})" if changes else label


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


BOOTSTRAP_RESAMPLES = 10_000
"""Resamples of the seeds behind a 95 % interval (:func:`interval`)."""


def interval(values: Sequence[float]) -> list[float] | None:
    """A 95 % percentile bootstrap interval of the mean over seeds: resample the seeds with replacement.

    With 3 seeds it is coarse (its ends are near the smallest and largest values); it is there so that two methods are
    called different only where their intervals do not overlap. Seeded: the same values give the same interval.

    Args:
        values: one value per seed.

    Returns:
        [low, high], or None with fewer than 2 values.
    """
    if len(values) < 2:
        return None
    x = np.asarray(values, dtype=np.float64)
    draws = np.random.default_rng(0).integers(0, len(x), (BOOTSTRAP_RESAMPLES, len(x)))  # (R, n) seed indices
    low, high = np.percentile(x[draws].mean(axis=1), [2.5, 97.5])
    return [float(low), float(high)]


def entry_order(key: tuple[str, str, tuple[str, ...]]) -> tuple[int, str, int, tuple[str, ...]]:
    """Sort key of (method, loop, changes): the registry's order (others after, by name), closed first, presets first."""
    method, loop, changes = key
    rank = list(METHODS).index(method) if method in METHODS else len(METHODS)
    return rank, method, LOOPS.index(loop) if loop in LOOPS else len(LOOPS), changes


def entry_key(result: dict[str, Any]) -> tuple[str, str, tuple[str, ...]]:
    """What one entry of the report gathers the seeds of: method, loop and ``--method-set`` changes.

    Args:
        result: a job's ``result.json`` contents.
    """
    return result["method"], result["loop"], tuple(result.get("settings_changes") or ())


def _flat(p: dict[str, Any]) -> dict[str, Any]:
    """A curve point as the report shows it: interaction steps and hours, wall time, compute, the test and validation MAE.

    ``samples_per_step`` is the point's gradient samples (the batch rows its optimizer steps took) per interaction
    step: None before the first interaction step, and for a point that did not count them (made before they were
    kept). ``validation_mae_deg`` is None for a point not measured on validation references.
    """
    samples, steps = p.get("gradient_samples"), p["interaction_steps"]
    return {
        "interaction_steps": steps,
        "interaction_hours": interaction_hours(steps),
        "wall_seconds": p.get("wall_seconds"),
        "gradient_samples": samples,
        "samples_per_step": samples / steps if samples is not None and steps > 0 else None,
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
        "interaction_steps", "interaction_hours", "wall_seconds", "samples_per_step", "mae_deg", "rmse_deg", "fmae_deg",
        "smt1_deg", "smt2_deg", "etd_mae_cm", "etd_fmae_cm" (means at the final points) and each with ``_std``,
        "selected_interaction_steps", "selected_mae_deg" and their ``_std`` (the test MAE at the points selected on
        validation; None unless every seed has one), "best_interaction_steps", "best_mae_deg" and their ``_std`` (at
        the best points on test), "mae_deg_ci95", "selected_mae_deg_ci95": [low, high] (:func:`interval`; None with
        one seed), "selection_steps": for a method whose points are separate runs (``Method.separate_runs``), the
        interaction steps of all the runs its validation choice looked at, mean over seeds (else None),
        "per_joint_mae_deg": [4], "episodes", "steps": the test set, "final", "best": [per seed: the point],
        "selected": [per seed: the point] or None, "curve": [the mean over seeds at each interaction count:
        {"interaction_steps", "interaction_hours", "mae_deg", "mae_deg_std", "seeds"}], "curves": [{"seed", "points":
        [each point: interaction steps and hours, wall seconds, "gradient_samples", "samples_per_step", test metrics,
        "validation_mae_deg"]}]}``;
        a point of "final", "selected", "best" is ``{"seed", **that point}``.
    """
    groups: dict[tuple[str, str, tuple[str, ...]], list[dict[str, Any]]] = {}
    for result in results:
        groups.setdefault(entry_key(result), []).append(result)
    entries = []
    for (method, loop, changes), group in sorted(groups.items(), key=lambda item: entry_order(item[0])):
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
        entry["mae_deg_ci95"] = interval([p["mae_deg"] for p in final])
        entry["selected_mae_deg_ci95"] = interval([p["mae_deg"] for p in selected]) if selected else None
        separate = method in METHODS and loop in METHODS[method].separate_runs
        entry["selection_steps"] = (
            stats([sum(p["interaction_steps"] for p in c["points"]) for c in curves])[0] if separate and selected else None
        )
        entry["per_joint_mae_deg"] = np.mean([f["per_joint_mae_deg"] for f in final], axis=0).tolist()
        entry["episodes"], entry["steps"] = final[0].get("episodes"), final[0].get("steps")
        entry["final"], entry["selected"], entry["best"] = final, selected, best
        entry["curve"] = mean_curve([c["points"] for c in curves])
        entry["curves"] = curves
        entries.append(entry)
    return entries
