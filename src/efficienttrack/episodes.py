"""The one episode loop: a system, references, and a driver that picks the reference sent at every step.

Data collection (Algorithm 1, :mod:`efficienttrack.collect`: the desired position plus noise) and deployment
(Algorithm 2, :mod:`efficienttrack.runtime`: the desired position plus the policy's adjustment) are two drivers
of :func:`rollout`. References of different lengths are padded with their last desired position and run
together when the system is batched; each episode keeps only its own steps.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, Protocol

import numpy as np

from efficienttrack.errors import EfficientTrackError
from efficienttrack.progress import ProgressDisplay
from efficienttrack.records import EpisodeRecord
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.windows import pad_time_major


class Sent(NamedTuple):
    """What the runtime actually sent for one step of N machines.

    Attributes:
        q_ref: (N, 4) rad, reference sent to the position controller (target of step t+1).
        adjustment: (N, 4) rad, ``q_ref − q*_{t+1}`` as sent (0 where the guard fell back).
        fallback: (N,) bool, True where the policy output was non-finite or beyond its bound and
            the raw desired position was sent instead.
    """

    q_ref: np.ndarray
    adjustment: np.ndarray
    fallback: np.ndarray


class Driver(Protocol):
    """What :func:`rollout` asks for the reference of each step (the policy runtime, or collection noise)."""

    def start(self, obs0: np.ndarray) -> None:
        """Begin N episodes.

        Args:
            obs0: (N, 8) [rad, rad/s], the start observations.
        """
        ...

    def step(self, obs: np.ndarray, q_des_future: np.ndarray) -> Sent:
        """The reference for step t+1.

        Args:
            obs: (N, 8) [rad, rad/s], ``o_t``.
            q_des_future: (N, h, 4) rad, ``q*_{t+1} … q*_{t+h}``.

        Returns:
            What was sent.
        """
        ...


def rollout(
    system: BatchedSystem,
    references: Sequence[np.ndarray],
    driver: Driver,
    horizon: int = 1,
    progress: ProgressDisplay | None = None,
    description: str = "rollout",
) -> list[EpisodeRecord]:
    """Run N references together on a batched system (or N = 1 on any system); the only time loop.

    Every machine is reset to its ``q*_0``; at step t the driver turns ``o_t`` and the desired
    ``q*_{t+1} … q*_{t+h}`` into the reference sent. Episode i has ``T_i = L_i − 1`` steps; shorter
    references hold their last desired position while the longer ones finish, and their records
    are cut to their own length.

    Args:
        system: the closed-loop system, already checked (``load_system``); must accept N machines.
        references: N arrays (L_i, 4) rad with L_i ≥ 3.
        driver: :class:`Runtime`-like object making each step's reference.
        horizon: future desired positions h handed to the driver each step.
        progress: a progress display to report steps on, or None.
        description: label of the progress task.

    Returns:
        N records (q, qd, q_ref, q_des, u, t; meta["fallbacks"] = guarded steps within T_i).
    """
    lengths = np.array([len(q) for q in references])
    if np.any(lengths < 3):
        raise EfficientTrackError("rollout: every reference needs at least 3 positions")
    steps = int(lengths.max()) - 1
    q_des = pad_time_major(references, horizon + 1)  # (L_max + h + 1, N, 4)
    n = len(references)
    q, qd, q_ref = np.empty((steps, n, 4)), np.empty((steps, n, 4)), np.empty((steps, n, 4))
    u = np.empty((steps, n, 4))
    fallback = np.zeros((steps, n), dtype=bool)
    has_u = True
    task = progress.add_task(description, total=steps) if progress is not None else None
    obs = system.reset(q_des[0])
    driver.start(obs)
    for t in range(steps):
        sent = driver.step(obs, q_des[t + 1 : t + 1 + horizon].transpose(1, 0, 2))
        q[t], qd[t], q_ref[t], fallback[t] = obs[:, :4], obs[:, 4:], sent.q_ref, sent.fallback
        obs = system.step(sent.q_ref)
        command = system.last_command
        has_u = has_u and command is not None
        if has_u:
            u[t] = command
        if task is not None:
            progress.advance(task)
    if task is not None:
        progress.remove_task(task)
    t_axis = np.arange(steps) * system.dt
    records = []
    for i, length in enumerate(lengths - 1):
        records.append(
            EpisodeRecord(
                q=q[:length, i].copy(),
                qd=qd[:length, i].copy(),
                q_ref=q_ref[:length, i].copy(),
                q_des=q_des[1 : length + 1, i].copy(),
                u=u[:length, i].copy() if has_u else None,
                t=t_axis[:length].copy(),
                meta={"fallbacks": int(fallback[:length, i].sum())},
            )
        )
    return records


def batches(system: BatchedSystem, count: int) -> list[slice]:
    """Groups of episodes run together: all at once on a batched system, else one by one.

    Args:
        system: the system (its ``max_batch``: None = any N, else the largest N).
        count: number of episodes.

    Returns:
        Slices covering ``range(count)`` in order.
    """
    size = max(count, 1) if system.max_batch is None else system.max_batch
    return [slice(start, min(start + size, count)) for start in range(0, count, size)]
