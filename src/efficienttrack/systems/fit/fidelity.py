"""How closely a simulator reproduces a machine's logs (:func:`fidelity`).

- **closed loop**: the system (PD law included) is reset at each log's first position and driven
  with the logged ``q_ref`` (:func:`closed_loop_rollout`); per joint, the paper's MAE
  ``mean_t |wrap(q[t+1] − q_des[t])|`` per episode, averaged over episodes, for the simulation and the log,
  and their ratio sim / real. All episodes run in one batch (shorter ones are padded with their last
  reference and masked).
- **open loop** ``mpe20``: from every ``stride``-th step t0 with a full horizon, the plant is reset
  at the logged state of t0 and replays ``u[t0 … t0+19]`` (:func:`open_loop_replay`); the error is the mean of
  ``|wrap(q_sim[t0+k] − q[t0+k])|`` over k = 1 … 20, then over windows, per joint
  (:func:`~efficienttrack.systems.fit.logs.window_error`). Plants whose ``reset`` accepts ``qd0`` and ``u_past``
  (the built-in one) start with the logged velocity and the logged commands in the delay line; other plants
  start at rest at ``q[t0]``.
- **open loop** ``travel_ratio20``: on the same windows, the real joint's travel over the 20 steps against the
  simulated one's, ``Σ D_real·D_sim / Σ D_sim²`` with ``D = wrap(q[t0+20] − q[t0])`` (the least-squares slope
  of real over simulated travel), per joint (:func:`travel_ratio`). Above 1 the real joint goes further than the
  simulated one under the same PWM: a simulator that is too slow overall, under that set's commands.
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import N_JOINTS
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.systems.fit.logs import Padded, Windows, make_windows, pad, tracking_mae, window_error
from efficienttrack.systems.protocol import BatchedSystem


def closed_loop_rollout(system: BatchedSystem, data: Padded) -> np.ndarray:
    """Drive a reference-level system with the logged ``q_ref``, all episodes in one batch.

    Args:
        system: the system (PD law included), reset at each episode's first logged position.
        data: padded logs (N episodes).

    Returns:
        q (T, N, 4) rad: ``q[0]`` the logged start, ``q[t+1]`` the position after ``q_ref[t]``.
    """
    q = np.empty_like(data.q)
    q[0] = data.q[0]
    system.reset(data.q[0])
    for t in range(len(q) - 1):
        q[t + 1] = system.step(data.q_ref[t])[:, :N_JOINTS]
    return q


class Fidelity(NamedTuple):
    """How closely a simulator reproduces a machine's logs (see :mod:`efficienttrack.systems.fit.fidelity`).

    Attributes:
        real_mae_deg: (4,) deg, PD tracking MAE per joint of the logs.
        sim_mae_deg: (4,) deg, the same for the simulator driven with the logged q_ref.
        ratio: (4,) sim / real.
        mpe20_deg: (4,) deg, open-loop 20-step position error per joint, or None without a plant.
        travel_ratio20: (4,) real / simulated joint travel over the open-loop windows, or None without a plant
            (NaN for a joint the simulator never moves).
        q_sim: (T, N, 4) rad, the simulated closed-loop positions (padded like ``data``).
        data: the padded logs.
    """

    real_mae_deg: np.ndarray
    sim_mae_deg: np.ndarray
    ratio: np.ndarray
    mpe20_deg: np.ndarray | None
    travel_ratio20: np.ndarray | None
    q_sim: np.ndarray
    data: Padded

    def to_json(self, decimals: int = 4) -> dict[str, Any]:
        """The one-line JSON report: ``{"closed_loop": {...}, "open_loop": {"mpe20_deg": [4], "travel_ratio20": [4]}}``.

        The open-loop lists are null without a plant; a NaN value (a joint the simulator never moves) is null.

        Args:
            decimals: digits after the decimal point each value (deg, or the unitless ratio) is rounded to.
        """

        def r(x: np.ndarray | None) -> list[float | None] | None:
            return None if x is None else [round(float(v), decimals) if np.isfinite(v) else None for v in x]

        return {
            "closed_loop": {"real_mae_deg": r(self.real_mae_deg), "sim_mae_deg": r(self.sim_mae_deg), "ratio": r(self.ratio)},
            "open_loop": {"mpe20_deg": r(self.mpe20_deg), "travel_ratio20": r(self.travel_ratio20)},
        }


def _accepts_history(plant: Any) -> bool:
    try:
        names = inspect.signature(plant.reset).parameters
    except (TypeError, ValueError):
        return False
    return "qd0" in names and "u_past" in names and bool(getattr(plant, "batched", False))


def open_loop_replay(plant: BatchedSystem, data: Padded, horizon: int = 20, stride: int = 10) -> tuple[np.ndarray, Windows]:
    """Replay the logged PWM from every ``stride``-th step (definition in the module docstring).

    Args:
        plant: the PWM-level plant (checked view; the raw plant is used for history-aware resets).
        data: padded logs with the PWM ``u``.
        horizon: steps replayed from each start.
        stride: distance between window starts, steps.

    Returns:
        The simulated positions q (H, W, 4) rad, and the windows they replay (logged positions ``windows.q``).
    """
    w = make_windows(data, horizon, stride=stride)
    raw = plant.system
    if _accepts_history(raw):
        raw.reset(w.q0, qd0=w.qd0, u_past=w.u_past)
        return np.stack([np.asarray(raw.step(u), dtype=np.float64)[:, :N_JOINTS] for u in w.u]), w
    chunk = plant.max_batch or len(w.q0)
    parts = []
    for i in range(0, len(w.q0), chunk):
        part = slice(i, i + chunk)
        plant.reset(w.q0[part])
        parts.append(np.stack([plant.step(u[part])[:, :N_JOINTS] for u in w.u]))
    return np.concatenate(parts, axis=1), w


def travel_ratio(q_sim: np.ndarray, windows: Windows) -> np.ndarray:
    """Real over simulated joint travel at the windows' end, (4,), NaN for a joint the simulation never moves.

    Args:
        q_sim: (H, W, 4) rad, simulated positions from :func:`open_loop_replay`.
        windows: the windows replayed (W of them).
    """
    real = wrap(windows.q[-1] - windows.q0)
    sim = wrap(q_sim[-1] - windows.q0)
    power = (sim * sim).sum(axis=0)
    return np.divide((real * sim).sum(axis=0), power, out=np.full(N_JOINTS, np.nan), where=power > 0)


def fidelity(
    records: Sequence[EpisodeRecord], system: BatchedSystem, plant: BatchedSystem | None = None, stride: int = 10
) -> Fidelity:
    """Closed-loop PD tracking MAE of a system vs the logs, and the plant's open-loop 20-step error and travel.

    Args:
        records: logs of the real machine under its PD law (``u`` needed for the open loop).
        system: the reference-level system (PD law included).
        plant: its PWM-level plant, for the open-loop figures (skipped when None).
        stride: distance between the open-loop window starts, steps.

    Returns:
        The comparison; angles in degrees.
    """
    if not isinstance(stride, int) or isinstance(stride, bool) or stride < 1:
        raise EfficientTrackError(f"fidelity: the open-loop window stride must be an integer ≥ 1 step, got {stride!r}")
    data = pad(records)
    if system.max_batch is None:
        q_sim = closed_loop_rollout(system, data)
    else:  # an unbatched system runs one episode at a time
        q_sim = np.empty_like(data.q)
        for i, record in enumerate(records):
            q_i = closed_loop_rollout(system, pad([record]))[:, 0]
            q_sim[: len(q_i), i], q_sim[len(q_i) :, i] = q_i, q_i[-1]
    real = np.degrees(tracking_mae(data.q, data).mean(axis=0))
    sim = np.degrees(tracking_mae(q_sim, data).mean(axis=0))
    mpe = travel = None
    if plant is not None:
        if any(r.u is None for r in records):
            raise EfficientTrackError("open-loop fidelity needs logs with the PWM command 'u'")
        q_open, windows = open_loop_replay(plant, data, stride=stride)
        mpe = np.degrees(window_error(q_open, windows))
        travel = travel_ratio(q_open, windows)
    return Fidelity(real, sim, sim / np.maximum(real, 1e-12), mpe, travel, q_sim, data)
