"""Figures people would rather look at than read: references, tracking, training curves, fidelity.

Every function writes a PNG atomically and returns its path; matplotlib runs headless (Agg).
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

from pathlib import Path
from typing import NamedTuple

import matplotlib.pyplot as plt
import numpy as np

from efficienttrack.fileio import atomic_write
from efficienttrack.joints import DT, JOINT_NAMES
from efficienttrack.metrics import tracking_error
from efficienttrack.records import EpisodeRecord
from efficienttrack.references import Reference


def plot_references(refs: list[Reference], path: str | Path) -> Path:
    """Draw every reference per joint, in degrees against time, one subplot per joint.

    Args:
        refs: references, each q (T, 4) rad at 20 Hz.
        path: PNG to write (parents created).

    Returns:
        The path written.
    """
    fig, axes = plt.subplots(4, 1, figsize=(10, 9), sharex=True, layout="constrained")
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


def _save(fig: plt.Figure, path: str | Path) -> Path:
    try:
        return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)


def plot_tracking(runs: dict[str, EpisodeRecord], path: str | Path, title: str = "") -> Path:
    """Desired and achieved joint positions of one reference under several methods, one subplot per joint.

    Args:
        runs: method name → its record of the same reference (``q`` (T, 4) rad, ``q_des`` (T, 4) rad);
            the desired curve is taken from the first.
        path: PNG to write.
        title: figure title (e.g. the reference name).

    Returns:
        The path written.
    """
    first = next(iter(runs.values()))
    t_next = first.t + (first.t[1] - first.t[0])  # q_des[t] is the target of step t+1
    traces = {name: (record.t, record.q) for name, record in runs.items()}
    return _plot_joint_traces(t_next, first.q_des, traces, path, title)


def _plot_joint_traces(
    t_des: np.ndarray, q_des: np.ndarray, traces: dict[str, tuple[np.ndarray, np.ndarray]], path: str | Path, title: str
) -> Path:
    """One subplot per joint, in degrees: desired positions dashed, then each named trace.

    Args:
        t_des: (T,) s, times of the desired positions.
        q_des: (T, 4) rad, desired positions.
        traces: label → (t (T,) s, q (T, 4) rad).
        path: PNG to write.
        title: figure title.
    """
    fig, axes = plt.subplots(4, 1, figsize=(10, 9), sharex=True, layout="constrained")
    for joint, (name, ax) in enumerate(zip(JOINT_NAMES, axes, strict=True)):
        ax.plot(t_des, np.degrees(q_des[:, joint]), "k--", lw=1.0, label="desired")
        for label, (t, q) in traces.items():
            ax.plot(t, np.degrees(q[:, joint]), lw=1.1, label=label)
        ax.set_ylabel(f"{name} (°)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(title)
    axes[-1].set_xlabel("time (s)")
    return _save(fig, path)


def plot_tracking_error(runs: dict[str, list[EpisodeRecord]], path: str | Path) -> Path:
    """Absolute tracking error over time per joint, averaged over episodes, for several methods.

    The error of step t is ``|wrap(q[t+1] − q_des[t])|`` (°); episodes of different lengths are
    averaged over the episodes still running.

    Args:
        runs: method name → its records (one per test reference).
        path: PNG to write.

    Returns:
        The path written.
    """
    fig, axes = plt.subplots(4, 1, figsize=(10, 9), sharex=True, layout="constrained")
    for name, records in runs.items():
        steps = max(len(r) for r in records) - 1
        total, count = np.zeros((steps, 4)), np.zeros((steps, 1))
        for record in records:  # one accumulation per episode
            e = np.degrees(np.abs(tracking_error(record.q, record.q_des)))
            total[: len(e)] += e
            count[: len(e)] += 1
        mean = total / np.maximum(count, 1)
        t = np.arange(1, steps + 1) * (records[0].t[1] - records[0].t[0])
        for joint, ax in enumerate(axes):
            ax.plot(t, mean[:, joint], lw=1.0, label=f"{name} (time mean {mean[:, joint].mean():.2f}°)")
    for joint, ax in enumerate(axes):
        ax.set_ylabel(f"|e| {JOINT_NAMES[joint]} (°)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[0].set_title("tracking error over time (mean over test references)")
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
    """

    scalars: dict[str, tuple[np.ndarray, np.ndarray]]
    loss_label: str
    held_out_tag: str
    held_out_label: str


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
    fig, axes = plt.subplots(1, len(curves), figsize=(6 * len(curves), 3.8), layout="constrained", squeeze=False)
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
            right.plot(*curve.scalars[curve.held_out_tag], "o-", lw=1.2, ms=3, color="C1", label="held out")
            right.set_ylabel(curve.held_out_label, color="C1")
            right.set_ylim(bottom=0)
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
    return _plot_joint_traces(t[1:], q_des[:-1], {"real": (t, q_real), "simulated": (t, q_sim)}, path, title)
