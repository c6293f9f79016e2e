"""The paper's tracking metrics, each defined once (data README, section "Metrics").

Per episode of T steps, with the tracking error e_t = wrap(q[t+1] − q_des[t]), t = 0 … T−2:

- MAE: mean of |e| over steps and joints.
- RMSE: mean over joints of sqrt(mean over steps of e²).
- FMAE: mean over joints of |e| at the last step (t = T−2).
- 1st-order smoothness: mean over joints of sqrt(mean of wrap(q[t] − q[t−1])²) over q[1 … T−1].
- 2nd-order smoothness: the same on the second difference q[t] − 2q[t−1] + q[t−2] over q[1 … T−1].
- ETD-MAE / ETD-FMAE: distance between the arm tips at q[t+1] and q_des[t], mean / last step.

Each figure is computed per episode, then averaged over the episodes of a set. Radians and
metres inside; the report (:func:`compute_metrics`) is in degrees and centimetres.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from rich.table import Table

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_csv
from efficienttrack.core.joints import CONTROL_RATE_HZ, JOINT_NAMES
from efficienttrack.data.kinematics import tip_position
from efficienttrack.data.records import EpisodeRecord, load_record, record_files

if TYPE_CHECKING:
    import torch

TABLE_METRICS = ("mae_deg", "rmse_deg", "fmae_deg", "smt1_deg", "smt2_deg", "etd_mae_cm", "etd_fmae_cm")
"""Table I's metrics: MAE, RMSE, FMAE, 1st/2nd-order smoothness (°), ETD-MAE, ETD-FMAE (cm)."""
METRIC_KEYS = ("episodes", "steps", *TABLE_METRICS, "per_joint_mae_deg")
"""Keys of the dict returned by :func:`compute_metrics`: the episodes and steps measured, :data:`TABLE_METRICS`, and
the MAE per joint."""
MIN_STEPS = 4
"""Shortest episode with every metric defined (the 2nd-order smoothness needs q[1], q[2], q[3])."""
MPE_STEPS = 20
"""Prediction horizon of the model's multi-step error (the paper's Tr./Te.MPE: 20 steps, 1 s)."""
ArrayT = TypeVar("ArrayT", np.ndarray, "torch.Tensor")


def tracking_error(q: np.ndarray, q_des: np.ndarray) -> np.ndarray:
    """Tracking error of every step: e_t = wrap(q[t+1] − q_des[t]).

    Args:
        q: (T, 4) rad, measured positions.
        q_des: (T, 4) rad, desired position for the next step.

    Returns:
        (T−1, 4) rad.
    """
    return wrap(q[1:] - q_des[:-1])


def position_error(q_hat: ArrayT, q: ArrayT) -> ArrayT:
    """Absolute position error |wrap(q̂ − q)| of predicted or simulated positions, numpy or torch.

    The multi-step errors (the learned model's MPE, the simulator's open-loop error and window error)
    are means of this over windows and steps.

    Args:
        q_hat: (..., 4) rad, predicted or simulated positions.
        q: (..., 4) rad, the recorded positions they are compared with (same kind and shape).

    Returns:
        (..., 4) rad, the same kind of array.
    """
    return abs(wrap(q_hat - q))


def adjustment(q_ref: np.ndarray, q_des: np.ndarray) -> np.ndarray:
    """Adjustment of every step: a_t = wrap(q_ref[t] − q_des[t]), the reference sent minus the desired one.

    Args:
        q_ref: (T, 4) rad, reference sent at step t (target of step t+1).
        q_des: (T, 4) rad, desired position for step t+1.

    Returns:
        (T, 4) rad; zero for the PD controller alone.
    """
    return wrap(q_ref - q_des)


def mae(e: np.ndarray) -> float:
    """Mean absolute error over steps and joints of ``e`` (S, 4) rad → rad."""
    return float(np.mean(np.abs(e)))


def per_joint_mae(e: np.ndarray) -> np.ndarray:
    """Mean absolute error per joint of ``e`` (S, 4) rad → (4,) rad."""
    return np.mean(np.abs(e), axis=0)


def rmse(e: np.ndarray) -> float:
    """Root mean square error per joint over steps, then the mean over joints; ``e`` (S, 4) rad → rad."""
    return float(np.mean(np.sqrt(np.mean(e**2, axis=0))))


def fmae(e: np.ndarray) -> float:
    """Final mean absolute error: mean over joints of |e| at the last step; ``e`` (S, 4) rad → rad."""
    return float(np.mean(np.abs(e[-1])))


def smoothness(q: np.ndarray, order: int) -> float:
    """Order-``order`` smoothness of the controlled positions q[1 … T−1].

    The RMS over steps of the ``order``-th (angle-wrapped) difference, averaged over joints.

    Args:
        q: (T, 4) rad, measured positions; q[0] (before any command) is left out.
        order: 1 (step size) or 2 (change of step size).

    Returns:
        rad.
    """
    if order not in (1, 2):
        raise ValueError(f"smoothness order {order}: expected 1 or 2")
    if len(q) < order + 2:
        raise EfficientTrackError(f"smoothness of order {order} needs at least {order + 2} steps, got {len(q)}")
    diff = wrap(np.diff(q[1:], axis=0))
    if order == 2:
        diff = np.diff(diff, axis=0)
    return float(np.mean(np.sqrt(np.mean(diff**2, axis=0))))


def tip_distance(q: np.ndarray, q_des: np.ndarray) -> np.ndarray:
    """End-effector tracking distance of every step: |fk(q[t+1]) − fk(q_des[t])|.

    Args:
        q: (T, 4) rad, measured positions.
        q_des: (T, 4) rad, desired position for the next step.

    Returns:
        (T−1,) m.
    """
    return np.linalg.norm(tip_position(q[1:]) - tip_position(q_des[:-1]), axis=-1)


def episode_metrics(record: EpisodeRecord) -> dict[str, Any]:
    """The metrics of one episode, in degrees / centimetres (keys of :data:`METRIC_KEYS`, episodes = 1).

    Args:
        record: the episode (only ``q`` and ``q_des`` are used).

    Returns:
        A dict like :func:`compute_metrics`' for a single episode.
    """
    e = tracking_error(record.q, record.q_des)
    etd = tip_distance(record.q, record.q_des)
    return {
        "episodes": 1,
        "steps": len(record),
        "mae_deg": np.degrees(mae(e)),
        "rmse_deg": np.degrees(rmse(e)),
        "fmae_deg": np.degrees(fmae(e)),
        "smt1_deg": np.degrees(smoothness(record.q, 1)),
        "smt2_deg": np.degrees(smoothness(record.q, 2)),
        "etd_mae_cm": 100 * float(np.mean(etd)),
        "etd_fmae_cm": 100 * float(etd[-1]),
        "per_joint_mae_deg": np.degrees(per_joint_mae(e)),
    }


def compute_metrics(records: Sequence[EpisodeRecord]) -> dict[str, Any]:
    """The paper's metrics of a set of episodes: each computed per episode, then averaged.

    Args:
        records: the episodes (at least one, each with T ≥ 4 steps for the 2nd-order smoothness).

    Returns:
        ``{"episodes": int, "steps": int (Σ T, the steps of these episodes), "mae_deg", "rmse_deg",
        "fmae_deg", "smt1_deg", "smt2_deg": float °, "etd_mae_cm", "etd_fmae_cm": float cm,
        "per_joint_mae_deg": [4] ° (boom, arm, bucket, swing)}``.
    """
    if not records:
        raise EfficientTrackError("metrics: no episodes given")
    short = [str(r.meta.get("name", i)) for i, r in enumerate(records) if len(r) < MIN_STEPS]
    if short:
        raise EfficientTrackError(f"metrics: episode(s) {', '.join(short[:5])} have fewer than {MIN_STEPS} steps")
    per_episode = [episode_metrics(record) for record in records]
    result: dict[str, Any] = {"episodes": len(records), "steps": int(sum(len(r) for r in records))}
    for key in TABLE_METRICS:
        result[key] = float(np.mean([m[key] for m in per_episode]))
    result["per_joint_mae_deg"] = np.mean([m["per_joint_mae_deg"] for m in per_episode], axis=0).tolist()
    return result


HELD_SPEED_DEG_S = 2.0
"""Below this desired speed (°/s) a joint's reference counts as held in :func:`moving_held_split`."""


def moving_held_split(records: Sequence[EpisodeRecord], held_speed_deg_s: float = HELD_SPEED_DEG_S) -> dict[str, Any]:
    """Tracking error per joint, split by whether that joint's reference moves or holds still, pooled over steps.

    Step t of a joint counts as held when its desired speed |wrap(q_des[t] − q_des[t−1])| / dt (for t = 0:
    from q[0]) is below ``held_speed_deg_s``. Ripple and offsets show in the held steps, lag in the moving ones;
    the signed mean on held steps tells an offset (a joint resting below or above its reference) from ripple.

    Args:
        records: the episodes (``q``, ``q_des`` (T, 4) rad).
        held_speed_deg_s: the speed threshold, °/s.

    Returns:
        ``{"held_speed_deg_s", "held_share": [4], "moving_mae_deg": [4], "held_mae_deg": [4], "held_bias_deg": [4]}``,
        per joint (boom, arm, bucket, swing); a joint without held (or moving) steps gets None there.
    """
    if not records:
        raise EfficientTrackError("metrics: no episodes given")
    errors, held = [], []
    for record in records:
        errors.append(tracking_error(record.q, record.q_des))
        previous = np.concatenate([record.q[:1], record.q_des[:-2]])
        held.append(np.abs(wrap(record.q_des[:-1] - previous)) * CONTROL_RATE_HZ < np.radians(held_speed_deg_s))
    e, still = np.concatenate(errors), np.concatenate(held)

    def per_joint(values: np.ndarray, mask: np.ndarray) -> list[float | None]:
        counts = mask.sum(axis=0)
        sums = np.where(mask, values, 0.0).sum(axis=0)
        return [None if n == 0 else float(np.degrees(total / n)) for total, n in zip(sums, counts, strict=True)]

    return {
        "held_speed_deg_s": held_speed_deg_s,
        "held_share": still.mean(axis=0).tolist(),
        "moving_mae_deg": per_joint(np.abs(e), ~still),
        "held_mae_deg": per_joint(np.abs(e), still),
        "held_bias_deg": per_joint(e, still),
    }


def metrics_by_path(
    paths: Iterable[str | Path], recursive: bool = False, pool: bool = False, per_episode: bool = False
) -> dict[str, dict[str, Any]]:
    """The metrics of episode files and folders: one entry per path, per episode, or all pooled.

    Args:
        paths: episode files or folders (a folder means the episodes directly in it unless ``recursive``).
        recursive: read the subfolders of folders too.
        pool: one entry for all the episodes of all ``paths``, keyed by the paths joined with `` + ``.
        per_episode: one entry per episode file, keyed by its path (overrides ``pool``).

    Returns:
        Name → the dict of :func:`compute_metrics`, in the order of ``paths`` (folders sorted).

    Raises:
        EfficientTrackError: a missing or empty path, an invalid episode, or one path given twice.
    """
    paths = [Path(path) for path in paths]
    if not paths:
        raise EfficientTrackError("metrics: no episode files given")
    if len(set(paths)) < len(paths):
        raise EfficientTrackError(f"metrics: a path is given twice ({', '.join(map(str, paths))})")
    files = {path: record_files(path, recursive) for path in paths}
    if per_episode:
        return {str(file): compute_metrics([load_record(file)]) for group in files.values() for file in group}
    records = {path: [load_record(file) for file in group] for path, group in files.items()}
    if pool:
        return {" + ".join(map(str, paths)): compute_metrics([r for group in records.values() for r in group])}
    return {str(path): compute_metrics(group) for path, group in records.items()}


def write_metrics_csv(rows: Mapping[str, Mapping[str, Any]], path: str | Path) -> Path:
    """Write metric rows as CSV atomically: a ``path`` column, then :data:`METRIC_KEYS` (per-joint MAE in 4 columns).

    Args:
        rows: name → the dict of :func:`compute_metrics` (e.g. from :func:`metrics_by_path`).
        path: the CSV file to write.

    Returns:
        The path written.
    """
    header = ["path", *METRIC_KEYS[:-1], *(f"mae_deg_{joint}" for joint in JOINT_NAMES)]
    lines = ([name, *(m[key] for key in METRIC_KEYS[:-1]), *m["per_joint_mae_deg"]] for name, m in rows.items())
    return write_csv(path, header, lines)


def rounded(metrics: Mapping[str, Any], decimals: int = 4) -> dict[str, Any]:
    """``metrics`` with every float rounded to ``decimals`` (for JSON output)."""
    return {
        key: [round(v, decimals) for v in value] if isinstance(value, list) else round(value, decimals)
        for key, value in metrics.items()
    }


def interaction_hours(steps: int) -> float:
    """Interaction time I.T. in hours of ``steps`` control steps at 20 Hz."""
    return steps / CONTROL_RATE_HZ / 3600


def metrics_table(
    rows: Mapping[str, Mapping[str, Any]],
    title: str,
    training_steps: Mapping[str, int | None] | None = None,
    label: str = "method",
) -> Table:
    """A rich table with one row per method, interactions counted as in the paper.

    I.S. and I.T. are the interactions with the system used for *training* (collection), as in the
    paper's tables; the evaluated test episodes and their steps have their own columns.

    Args:
        rows: method name → the dict of :func:`compute_metrics` (of the test episodes).
        title: table title.
        training_steps: method name → interaction steps used to train it (None or absent: not known or
            not trained, shown as "–"); None for no method.
        label: heading of the first column, what the rows are (``method``, ``path``).

    Returns:
        The table: MAE, RMSE, FMAE, 1st/2nd-order smoothness (oSMT) in °, ETD-MAE/FMAE in cm,
        per-joint MAE in ° (boom, arm, bucket, swing), test episodes and steps, training interaction
        steps I.S. and time I.T. in h.
    """
    table = Table(
        title=title,
        caption="angles in °, ETD in cm; per joint: MAE °; eps/steps: the episodes measured; "
        "I.S./I.T.: training interactions (steps, h at 20 Hz)",
    )
    table.add_column(label, overflow="fold", min_width=8)
    headers = (
        "MAE",
        "RMSE",
        "FMAE",
        "oSMT1",
        "oSMT2",
        "ETD-MAE",
        "ETD-FMAE",
        "boom",
        "arm",
        "bucket",
        "swing",
        "eps",
        "steps",
        "I.S.",
        "I.T.",
    )
    for header in headers:
        table.add_column(header, justify="right", no_wrap=True)
    for name, m in rows.items():
        steps = (training_steps or {}).get(name)
        table.add_row(
            name,
            *(f"{m[key]:.2f}" for key in TABLE_METRICS),
            *(f"{v:.2f}" for v in m["per_joint_mae_deg"]),
            str(m["episodes"]),
            str(m["steps"]),
            "–" if steps is None else str(steps),
            "–" if steps is None else f"{interaction_hours(steps):.2f}",
        )
    return table
