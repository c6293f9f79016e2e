"""The simulated episode loop: a system, references, and a driver that picks the reference sent at every step.

Of the two time loops, this one runs N episodes at once on a simulator, as fast as it computes; a real machine's,
one episode on 20 Hz deadlines with watchdogs, is :class:`~efficienttrack.deploy.loop.Loop`. On a simulated clock,
with the controller alone, the two give the same episode (tested in ``tests/test_loop.py``); with a policy the loop
also limits the adjustment's rate and ramps it to 0 at the end.

Data collection (Algorithm 1, :mod:`efficienttrack.workflow.collect`: the desired position plus noise) and deployment
(Algorithm 2, :mod:`efficienttrack.deploy.runtime`: the desired position plus the policy's adjustment) are two drivers
of :func:`rollout`. References of different lengths are padded with their last desired position and run
together when the system is batched; each episode keeps only its own steps.

The loop runs the system's ``reset`` and ``step`` in a watchdog thread: a step that does not return within
``step_timeout`` seconds ends the episode with an error naming the system and the step, instead of hanging
forever (a thread, not a signal: signal-based timeouts work only in the main thread).
"""

from __future__ import annotations

import enum
import queue
import threading
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple, Protocol

import numpy as np

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.windows import pad_time_major
from efficienttrack.systems.protocol import BatchedSystem

STEP_TIMEOUT = 60.0
"""Seconds a system's ``reset`` or ``step`` may take before the episode is ended with an error."""


class Guard(enum.IntFlag):
    """Why the runtime guard intervened in a step, one bit each (a step may have several).

    The first eight are fallbacks (the raw desired position was sent, a = 0); ``RATE_LIMITED`` and ``CLAMPED``
    change the reference sent without falling back.
    """

    POLICY_ERROR = 1
    """The policy raised an exception."""
    POLICY_SHAPE = 2
    """The policy's output was not (N, 4) for N machines (a (1, 4) output is not broadcast)."""
    POLICY_NONFINITE = 4
    """The policy's output was NaN or infinite."""
    ADJUST_BOUND = 8
    """|a| exceeded the machine's adjustment bound (tightened by the checkpoint's)."""
    OBS_NONFINITE = 16
    """The observation was NaN or infinite (the last good one is kept in the history)."""
    OBS_JUMP = 32
    """The position moved more than ``max_speed · dt`` since the last observation (a sensor fault, dropped samples)."""
    OBS_STALE = 64
    """The observation repeated bit for bit for ``stale_steps`` steps, or (``Runtime.step`` given times) arrived after a
    gap of dropped samples longer than ``max_gap`` periods."""
    DESIRED_OUTSIDE = 128
    """A desired position the policy sees was outside the joint limits or not finite."""
    RATE_LIMITED = 256
    """The adjustment changed faster than ``max_adjust_rate`` and was limited."""
    CLAMPED = 512
    """The reference sent was clamped into the joint limits."""


FALLBACK = (
    Guard.POLICY_ERROR
    | Guard.POLICY_SHAPE
    | Guard.POLICY_NONFINITE
    | Guard.ADJUST_BOUND
    | Guard.OBS_NONFINITE
    | Guard.OBS_JUMP
    | Guard.OBS_STALE
    | Guard.DESIRED_OUTSIDE
)
"""The :class:`Guard` bits that send the raw desired position."""


class Sent(NamedTuple):
    """What the runtime actually sent for one step of N machines.

    Attributes:
        q_ref: (N, 4) rad, reference sent to the position controller (target of step t+1).
        adjustment: (N, 4) rad, ``q_ref − q*_{t+1}`` as sent (0 where the guard fell back).
        fallback: (N,) bool, True where the guard fell back to the raw desired position (any :data:`FALLBACK` bit).
        guard: (N,) uint16, the :class:`Guard` bits of each machine's step, or None from a driver without a guard.
    """

    q_ref: np.ndarray
    adjustment: np.ndarray
    fallback: np.ndarray
    guard: np.ndarray | None = None


def guard_steps(guard: np.ndarray) -> dict[str, list[int]]:
    """The steps at which each kind of intervention happened, for a record's ``meta["guard"]``.

    Args:
        guard: (T,) uint16, one machine's :class:`Guard` bits per step.

    Returns:
        Reason name (``policy_error``, ``obs_jump``, …, lower case) → the steps it happened at; reasons that never
        happened are left out.
    """
    steps = {}
    for flag in Guard:
        hits = np.flatnonzero(guard & flag.value)
        if len(hits):
            steps[str(flag.name).lower()] = hits.tolist()
    return steps


class _StepTimeout(Exception):
    """The watchdog stopped waiting for a call."""


class _Watchdog:
    """Runs calls in one daemon worker thread and stops waiting for one after ``timeout`` seconds.

    A call that never returns leaves its (daemon) worker behind; it cannot be killed from Python, but it does
    not keep the process alive.
    """

    def __init__(self, timeout: float) -> None:
        self.timeout = timeout
        self._calls: queue.SimpleQueue[tuple[Callable[[Any], Any], Any] | None] = queue.SimpleQueue()
        self._results: queue.SimpleQueue[tuple[bool, Any]] = queue.SimpleQueue()
        self._worker = threading.Thread(target=self._work, name="efficienttrack-step-watchdog", daemon=True)
        self._worker.start()

    def _work(self) -> None:
        while (call := self._calls.get()) is not None:
            fn, arg = call
            try:
                self._results.put((True, fn(arg)))
            except BaseException as exc:  # handed to the caller's thread, re-raised there
                self._results.put((False, exc))

    def call(self, fn: Callable[[Any], Any], arg: Any) -> Any:
        """``fn(arg)`` in the worker; its exception is re-raised here; :class:`_StepTimeout` after ``timeout`` s."""
        self._calls.put((fn, arg))
        try:
            ok, value = self._results.get(timeout=self.timeout)
        except queue.Empty:
            raise _StepTimeout from None
        if not ok:
            raise value
        return value

    def close(self) -> None:
        """Let the worker end (once its current call, if any, returns)."""
        self._calls.put(None)


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
    step_timeout: float | None = STEP_TIMEOUT,
) -> list[EpisodeRecord]:
    """Run N references together on a batched system (or N = 1 on any system), as fast as it computes.

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
        step_timeout: seconds the system's ``reset`` or ``step`` may take before the episodes are ended with an
            EfficientTrackError; None waits forever (and calls the system in this thread).

    Returns:
        N records (q, qd, q_ref, q_des, u, t; meta["fallbacks"] = guarded steps within T_i, and for a driver with a
        guard meta["guard"] = {reason: steps}, :func:`guard_steps`).
    """
    lengths = np.array([len(q) for q in references])
    if np.any(lengths < 3):
        raise EfficientTrackError("rollout: every reference needs at least 3 positions")
    if step_timeout is not None and not step_timeout > 0:
        raise EfficientTrackError(f"rollout: step_timeout must be a positive number of seconds or None, got {step_timeout}")
    steps = int(lengths.max()) - 1
    q_des = pad_time_major(references, horizon + 1)  # (L_max + h + 1, N, 4)
    n = len(references)
    q, qd, q_ref = np.empty((steps, n, 4)), np.empty((steps, n, 4)), np.empty((steps, n, 4))
    u = np.empty((steps, n, 4))
    fallback = np.zeros((steps, n), dtype=bool)
    guard = np.zeros((steps, n), dtype=np.uint16)
    has_u, has_guard = True, True
    task = progress.add_task(description, total=steps) if progress is not None else None
    watchdog = _Watchdog(step_timeout) if step_timeout is not None else None
    try:
        obs = _call(watchdog, system.reset, q_des[0], system, "reset")
        driver.start(obs)
        for t in range(steps):
            sent = driver.step(obs, q_des[t + 1 : t + 1 + horizon].transpose(1, 0, 2))
            q[t], qd[t], q_ref[t], fallback[t] = obs[:, :4], obs[:, 4:], sent.q_ref, sent.fallback
            if sent.guard is None:
                has_guard = False
            elif has_guard:
                guard[t] = sent.guard
            obs = _call(watchdog, system.step, sent.q_ref, system, f"step {t}")
            command = system.last_command
            has_u = has_u and command is not None
            if has_u:
                u[t] = command
            if progress is not None and task is not None:
                progress.advance(task)
    finally:
        if watchdog is not None:
            watchdog.close()
    if progress is not None and task is not None:
        progress.remove_task(task)
    t_axis = np.arange(steps) * system.dt
    records = []
    for i, length in enumerate(lengths - 1):
        meta: dict[str, Any] = {"fallbacks": int(fallback[:length, i].sum())}
        if has_guard:
            meta["guard"] = guard_steps(guard[:length, i])
        records.append(
            EpisodeRecord(
                q=q[:length, i].copy(),
                qd=qd[:length, i].copy(),
                q_ref=q_ref[:length, i].copy(),
                q_des=q_des[1 : length + 1, i].copy(),
                u=u[:length, i].copy() if has_u else None,
                t=t_axis[:length].copy(),
                meta=meta,
            )
        )
    return records


def _call(watchdog: _Watchdog | None, fn: Callable[[Any], Any], arg: Any, system: BatchedSystem, what: str) -> Any:
    """``fn(arg)``, under the watchdog when there is one; a timeout becomes an error naming the system and the call."""
    if watchdog is None:
        return fn(arg)
    try:
        return watchdog.call(fn, arg)
    except _StepTimeout:
        raise EfficientTrackError(
            f"{system.name}: {what} did not return within {watchdog.timeout:g} s; the episode was ended "
            "(a slower system needs a longer step_timeout)"
        ) from None


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
