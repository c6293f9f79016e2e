"""Figures people would rather look at than read: references, tracking, training curves, fidelity.

Every function writes a PNG atomically and returns its path; matplotlib runs headless (Agg).
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

from pathlib import Path
from typing import Any, NamedTuple

import matplotlib.pyplot as plt
import numpy as np

from efficienttrack.core.fileio import atomic_write
from efficienttrack.core.joints import DT, JOINT_NAMES
from efficienttrack.data.metrics import adjustment, mae, tracking_error
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.references import Reference


def plot_references(refs: list[Reference], path: str | Path) -> Path:
    """Draw every reference per joint, in degrees against time, one subplot per joint.

    Args:
        refs: references, each q (T, 4) rad at 20 Hz.
        path: PNG to write (parents created).

    Returns:
        The path written.
    """
    fig, axes = _figure(4, 1, (10, 9), STACKED, sharex=True)
    for ref in refs:
        for joint, ax in enumerate(axes):
            ax.plot(ref.t, np.degrees(ref.q[:, joint]), lw=0.8, alpha=0.7)
    for name, ax in zip(JOINT_NAMES, axes, strict=True):
        ax.set_ylabel(f"{name} (°)")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time (s)")
    axes[0].set_title(f"{len(refs)} reference{'s' if len(refs) != 1 else ''}")
    try:
        return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)


def _figure(
    rows: int,
    columns: int,
    size: tuple[float, float],
    margins: tuple[float, float, float, float],
    gap: float = 0.0,
    **kwargs: Any,
):
    """``plt.subplots`` with fixed margins (left, right, top, bottom) and ``gap`` between columns, in inches.

    These figures' labels are known, so fixed margins hold them; a constrained layout measures every text again at
    each save, about half of a figure's drawing time.
    """
    fig, axes = plt.subplots(rows, columns, figsize=size, **kwargs)
    left, right, top, bottom = margins
    width = (size[0] - left - right - gap * (columns - 1)) / columns
    fig.subplots_adjust(left=left / size[0], right=1 - right / size[0], top=1 - top / size[1], bottom=bottom / size[1],
                        hspace=0.12 if kwargs.get("sharex") else 0.3, wspace=gap / width)  # fmt: skip
    return fig, axes


STACKED = (0.9, 0.2, 0.45, 0.55)
"""Margins of a figure of joints stacked over a shared time axis: y labels, a title, the time axis."""


def _save(fig: plt.Figure, path: str | Path) -> Path:
    try:
        return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)


def plot_tracking(runs: dict[str, EpisodeRecord], path: str | Path, title: str = "") -> Path:
    """Desired and achieved joint positions of one reference under several methods, and the adjustments.

    One subplot per joint (desired dashed, then each method), and a last one with each adjusting method's
    adjustment ``wrap(q_ref − q*)`` per joint (PD alone sends q_ref = q*: nothing to draw). The title
    gives each method's MAE on this reference. Desired positions and adjustments are drawn at the step
    they are the target of (``q_des[t]`` and ``q_ref[t]`` at t+1).

    Args:
        runs: method name → its record of the same reference (``q``, ``q_ref``, ``q_des`` (T, 4) rad);
            the desired curve is taken from the first.
        path: PNG to write.
        title: figure title (e.g. the reference name).

    Returns:
        The path written.
    """
    first = next(iter(runs.values()))
    t_next = first.t + (first.t[1] - first.t[0])  # q_des[t] is the target of step t+1
    errors = ", ".join(f"{name} {np.degrees(mae(tracking_error(r.q, r.q_des))):.2f}°" for name, r in runs.items())
    fig, axes = _figure(5, 1, (10, 11), STACKED, sharex=True)
    _draw_joint_traces(axes[:4], t_next, first.q_des, {name: (record.t, record.q) for name, record in runs.items()})
    adjusted = {name: adjustment(r.q_ref, r.q_des) for name, r in runs.items()}
    adjusted = {name: a for name, a in adjusted.items() if np.any(a)}
    for (name, a), style in zip(adjusted.items(), ("-", "--", ":", "-."), strict=False):
        for joint, joint_name in enumerate(JOINT_NAMES):
            axes[4].plot(t_next, np.degrees(a[:, joint]), style, color=f"C{joint}", lw=1.0, label=f"{name} {joint_name}")
    if adjusted:
        axes[4].legend(loc="upper right", fontsize=7, ncol=len(JOINT_NAMES))
    else:
        axes[4].text(0.5, 0.5, "no adjustment (q_ref = q*)", transform=axes[4].transAxes, ha="center", va="center")
    axes[4].set_ylabel("q_ref − q* (°)")
    axes[4].grid(alpha=0.3)
    axes[0].set_title(f"{title} — MAE {errors}" if title else f"MAE {errors}")
    axes[-1].set_xlabel("time (s)")
    return _save(fig, path)


def _draw_joint_traces(axes, t_des: np.ndarray, q_des: np.ndarray, traces: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    """On one axis per joint, in degrees: desired positions dashed, then each named trace.

    Args:
        axes: 4 matplotlib axes (boom, arm, bucket, swing).
        t_des: (T,) s, times of the desired positions.
        q_des: (T, 4) rad, desired positions.
        traces: label → (t (T,) s, q (T, 4) rad).
    """
    for joint, (name, ax) in enumerate(zip(JOINT_NAMES, axes, strict=True)):
        ax.plot(t_des, np.degrees(q_des[:, joint]), "k--", lw=1.0, label="desired")
        for label, (t, q) in traces.items():
            ax.plot(t, np.degrees(q[:, joint]), lw=1.1, label=label)
        ax.set_ylabel(f"{name} (°)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)


def padded_errors(records: list[EpisodeRecord]) -> np.ndarray:
    """Absolute tracking errors of episodes of different lengths, side by side, NaN after each episode's end.

    Args:
        records: E episodes, episode i with T_i steps.

    Returns:
        (E, S, 4) rad, ``|wrap(q[t+1] − q_des[t])|`` of episode i at step t, NaN for t ≥ T_i − 1; S = max T_i − 1.
    """
    errors = [np.abs(tracking_error(record.q, record.q_des)) for record in records]
    lengths = np.array([len(e) for e in errors])
    padded = np.full((len(errors), lengths.max(), 4), np.nan)
    padded[np.arange(lengths.max()) < lengths[:, None]] = np.concatenate(errors)
    return padded


def plot_tracking_error(runs: dict[str, list[EpisodeRecord]], path: str | Path) -> Path:
    """Absolute tracking error over time per joint, across episodes, for several methods.

    The error of step t is ``|wrap(q[t+1] − q_des[t])|`` (°). The line at each time is the mean over the
    episodes still running then, the band their 25–75 % range, and a last subplot counts those episodes.
    ``metrics.json`` averages differently (each episode over its own steps first, then over episodes):
    the legend gives that figure per joint.

    Args:
        runs: method name → its records (one per test reference).
        path: PNG to write.

    Returns:
        The path written.
    """
    fig, axes = _figure(5, 1, (10, 11), (0.9, 0.2, 0.65, 0.55), sharex=True)  # a two-line title
    for color, (name, records) in enumerate(runs.items()):
        e = np.degrees(padded_errors(records))  # (E, S, 4)
        running = np.sum(~np.isnan(e[:, :, 0]), axis=0)
        mean = np.nanmean(e, axis=0)
        low, high = np.nanpercentile(e, [25, 75], axis=0)
        per_episode = np.mean(np.nanmean(e, axis=1), axis=0)  # as metrics.json's per_joint_mae_deg
        t = np.arange(1, e.shape[1] + 1) * (records[0].t[1] - records[0].t[0])
        for joint, ax in enumerate(axes[:4]):
            ax.plot(t, mean[:, joint], lw=1.0, color=f"C{color}", label=f"{name} (per-episode MAE {per_episode[joint]:.2f}°)")
            ax.fill_between(t, low[:, joint], high[:, joint], color=f"C{color}", alpha=0.2, lw=0)
        axes[4].step(t, running, where="post", color=f"C{color}", ls=("-", "--", ":", "-.")[color % 4], lw=1.0, label=name)
    for joint, ax in enumerate(axes[:4]):
        ax.set_ylabel(f"|e| {JOINT_NAMES[joint]} (°)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[4].set_ylabel("episodes running")
    axes[4].set_ylim(bottom=0)
    axes[4].grid(alpha=0.3)
    axes[4].legend(loc="upper right", fontsize=8)
    axes[0].set_title(
        "tracking error over time: mean over the episodes still running (band: 25–75 % of them)\n"
        "legend: each episode averaged over its steps, then over episodes (as metrics.json)",
        fontsize=10,
    )
    axes[-1].set_xlabel("time (s)")
    return _save(fig, path)


CURVE_POINTS = 1000
"""Most points drawn of a training-loss curve (means of consecutive steps)."""


class TrainingCurves(NamedTuple):
    """What :func:`plot_training_curves` draws of one training run.

    Attributes:
        scalars: the run's scalar log, tag → ((K,) optimizer steps, (K,) values) (``training.read_scalars``).
        loss_label: what the loss (tag ``train/loss``) is, with its unit: the y-axis label.
        held_out_tag: the tag of the held-out figure drawn on the right axis (absent from ``scalars``: none drawn).
        held_out_label: what the held-out figure is, with its unit.
        measured: figures measured on the system, in the held-out figure's unit, drawn as lines beside it (label →
            value): what the policy's model-predicted figure stands for, e.g. PD's and the policy's test MAE.
    """

    scalars: dict[str, tuple[np.ndarray, np.ndarray]]
    loss_label: str
    held_out_tag: str
    held_out_label: str
    measured: dict[str, float] = {}


def _thinned(steps: np.ndarray, values: np.ndarray, points: int = CURVE_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """(K,) steps and values → at most ``points`` means of consecutive entries of each."""
    parts = max(1, min(len(steps), points))
    return (
        np.array([x.mean() for x in np.array_split(np.asarray(steps, dtype=np.float64), parts)]),
        np.array([x.mean() for x in np.array_split(np.asarray(values, dtype=np.float64), parts)]),
    )


def plot_training_curves(curves: dict[str, TrainingCurves], path: str | Path) -> Path:
    """Training loss (left axis, log scale) and held-out figure (right axis) over optimizer steps, one panel per run.

    Args:
        curves: component name (``model``, ``policy``) → its scalars and axis labels.
        path: PNG to write.

    Returns:
        The path written.
    """
    fig, axes = _figure(1, len(curves), (6 * len(curves), 3.8), (0.8, 0.85, 0.4, 0.6), 2.0, squeeze=False)
    for ax, (name, curve) in zip(axes[0], curves.items(), strict=True):
        steps, loss = _thinned(*curve.scalars["train/loss"])
        ax.plot(steps, loss, lw=1.2, color="C0", label="training loss")
        ax.set_yscale("log")
        ax.set_title(f"{name} training")
        ax.set_xlabel("optimizer step")
        ax.set_ylabel(curve.loss_label, color="C0")
        ax.grid(alpha=0.3)
        if curve.held_out_tag in curve.scalars:
            right = ax.twinx()
            right.plot(*curve.scalars[curve.held_out_tag], "o-", lw=1.2, ms=3, color="C1", label="held out (model-predicted)")
            for (label, value), style in zip(curve.measured.items(), ("--", ":", "-."), strict=False):
                right.axhline(value, color="k", ls=style, lw=1, label=f"{label} ({value:.2f})")
            right.set_ylabel(curve.held_out_label, color="C1")
            right.set_ylim(bottom=0)
            right.margins(y=0.08)
            if curve.measured:
                right.legend(fontsize=7, loc="upper right")
    return _save(fig, path)


def plot_rounds(rows: list[dict[str, Any]], path: str | Path) -> Path:
    """Test MAE per continual-learning round, against the PD controller alone, and the model's errors.

    Args:
        rows: the rounds table (:func:`efficienttrack.workflow.rounds.rounds_rows`): the PD row first, then one per round,
            with ``mae_deg``, ``interaction_hours``, ``tr_mpe_deg`` and ``te_mpe_deg``.
        path: PNG to write.

    Returns:
        The path written.
    """
    pd, rounds = rows[0], rows[1:]
    k = np.arange(1, len(rounds) + 1)
    mae = np.array([row["mae_deg"] for row in rounds])
    fig, (left, right) = _figure(1, 2, (11, 3.8), (0.8, 0.2, 0.4, 0.6), 0.9)
    left.plot(k, mae, "o-", label="EfficientTrack")
    left.axhline(pd["mae_deg"], color="k", ls="--", lw=1, label=f"PD alone ({pd['mae_deg']:.2f}°)")
    for x, y, row in zip(k, mae, rounds, strict=True):
        left.annotate(f"{y:.2f}° ({y / pd['mae_deg']:.2f}× PD)\n{row['interaction_hours']:.2f} h", (x, y), fontsize=8,
                      textcoords="offset points", xytext=(4, 6))  # fmt: skip
    left.set_ylim(bottom=0)
    left.set_ylabel("test MAE (°)")
    left.set_title("tracking error per round")
    right.plot(k, [row["tr_mpe_deg"] for row in rounds], "o-", label="Tr.MPE (training data)")
    right.plot(k, [row["te_mpe_deg"] for row in rounds], "o-", label="Te.MPE (the round's test runs)")
    right.set_ylim(bottom=0)
    right.set_ylabel("20-step model error (°)")
    right.set_title("closed-loop model per round")
    for ax in (left, right):
        ax.set_xticks(k)
        ax.set_xlim(0.7, len(rounds) + 0.7)  # room for the last round's note
        ax.set_xlabel("round")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return _save(fig, path)


def plot_sim_vs_real(
    q_real: np.ndarray, q_sim: np.ndarray, q_des: np.ndarray, path: str | Path, title: str = "", dt: float = DT
) -> Path:
    """Joint traces of one episode on the real machine and in simulation, degrees against time, one subplot per joint.

    Args:
        q_real: (T, 4) rad, logged positions.
        q_sim: (T, 4) rad, simulated positions (same start, driven with the logged q_ref).
        q_des: (T, 4) rad, desired position of the next step (drawn shifted by one step).
        path: PNG to write.
        title: figure title (e.g. the episode name).
        dt: control period, s.

    Returns:
        The path written.
    """
    t = np.arange(len(q_real)) * dt
    fig, axes = _figure(4, 1, (10, 9), STACKED, sharex=True)
    _draw_joint_traces(axes, t[1:], q_des[:-1], {"real": (t, q_real), "simulated": (t, q_sim)})
    axes[0].set_title(title)
    axes[-1].set_xlabel("time (s)")
    return _save(fig, path)
