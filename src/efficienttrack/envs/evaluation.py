"""A deterministic agent on every reference once, all at once on the batched system, as episode records to score.

:func:`evaluate` is how a baseline trained on the environments is measured exactly like EfficientTrack: the agent
sees the environments' observations (:func:`efficienttrack.envs.core.observe`), and the episodes run in the one
episode loop (:func:`efficienttrack.deploy.episodes.rollout`), so that :func:`efficienttrack.data.metrics.compute_metrics`
scores the records. In the closed loop the agent is called by the guard that deploys EfficientTrack
(:class:`~efficienttrack.deploy.guard.GuardedRuntime`: its fallbacks, rate limit and clamp, on the guard's histories of
the references really sent), its action a ∈ [−1, 1] the adjustment ``a · max_adjust``: one scoring path for every
method. In the open loop (PWM, no reference to guard) the actions are applied as the environments apply them
(:class:`efficienttrack.envs.core.ActionMap`).
With ``act`` returning zeros the closed loop is the PD controller alone, record for record.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.windows import History, push_observation, push_reference
from efficienttrack.deploy.episodes import STEP_TIMEOUT, Sent, batches, rollout
from efficienttrack.deploy.guard import GuardedRuntime
from efficienttrack.envs.core import (
    FUTURE,
    HISTORY,
    ActionMap,
    RefsArg,
    check_actions,
    check_lengths,
    observe,
    open_system,
    resolve_references,
)
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import SystemSpec

Act = Callable[[np.ndarray], np.ndarray]
"""A deterministic agent: observations (N, D) float32 → actions (N, 4) in [−1, 1] (anything ``np.asarray`` takes)."""


class _AgentDriver:
    """The driver of :func:`rollout` that asks the agent for each step's action, keeping the environments' histories."""

    def __init__(self, act: Act, actions: ActionMap, history: int, future: int) -> None:
        self._act = act
        self._actions = actions
        self._h, self._f = history, future
        self._history: History | None = None

    def start(self, obs0: np.ndarray) -> None:
        self._history = self._actions.start_history(obs0, self._h)

    def step(self, obs: np.ndarray, q_des_future: np.ndarray) -> Sent:
        assert self._history is not None  # rollout calls start first
        history = push_observation(self._history, obs)
        n = len(obs)
        a = check_actions(self._act(observe(history, q_des_future[:, : self._f])), n)
        command = self._actions.command(a, q_des_future[:, 0])
        self._history = push_reference(history, command.remembered)
        return Sent(q_ref=command.sent, adjustment=command.adjustment, fallback=np.zeros(n, dtype=bool))


class _GuardedAgent:
    """The agent as the guard calls a policy (:data:`~efficienttrack.deploy.guard.PolicyCall`).

    The environments' observation of the guard's histories goes in, the adjustment ``a · max_adjust`` (rad) comes out.
    The guard falls back when a policy fails, as it must on a machine; in an evaluation that would score a broken
    agent as PD, so the first failure is kept (:attr:`error`) for :func:`evaluate` to raise.
    """

    def __init__(self, act: Act, max_adjust: np.ndarray) -> None:
        self._act, self._max_adjust = act, max_adjust
        self.error: Exception | None = None

    def __call__(self, obs_hist: np.ndarray, qref_hist: np.ndarray, q_des_future: np.ndarray) -> np.ndarray:
        try:
            a = self._act(observe(History(obs=obs_hist, q_ref=qref_hist), q_des_future))
            return check_actions(a, len(obs_hist)) * self._max_adjust
        except Exception as exc:
            self.error = self.error or exc
            raise


def evaluate(
    act: Act,
    refs: RefsArg,
    loop: str = "closed",
    system: SystemSpec | BatchedSystem | None = None,
    history: int = HISTORY,
    future: int = FUTURE,
    step_timeout: float | None = STEP_TIMEOUT,
) -> list[EpisodeRecord]:
    """Run a deterministic agent on every reference once, all together on the batched system.

    Args:
        act: observations (N, D) float32 → actions (N, 4) in [−1, 1] (clipped into it); N = the references run
            together.
        refs: a folder of references, a list of :class:`~efficienttrack.data.references.Reference`, or None for the
            environments' default (8 generated loading cycles, seed 0).
        loop: ``"closed"`` (the action adjusts the PD controller's reference) or ``"open"`` (the action is PWM / 1000).
        system: the spec of the system (default ``SystemSpec()``, the built-in ``xe75``), or the already-opened system
            to step (the closed loop, or the plant for the open loop).
        history: h, as the agent was trained with.
        future: F, as the agent was trained with.
        step_timeout: seconds a system step may take (:func:`~efficienttrack.deploy.episodes.rollout`); None: no limit.

    Returns:
        One record per reference, in order: q, qd (T, 4) measured; q_ref (T, 4) rad, the reference sent (closed loop)
        or the desired position q*_{t+1} (open loop); q_des (T, 4) rad; u (T, 4) PWM (the PD controller's, or the
        agent's), None when the system does not expose it; t (T,) s; meta ``name``, ``loop``, ``fallbacks`` (the
        guard's, closed loop; 0 open) and ``guard`` (closed loop: {reason: steps}).
    """
    refs = resolve_references(refs)
    system = open_system(loop, SystemSpec() if system is None else system) if not isinstance(system, BatchedSystem) else system
    check_lengths(history, future)
    actions = ActionMap(loop, system)
    if actions.loop == "closed":
        for ref in refs:
            system.limits.check_reference(ref.q, ref.name)
    records: list[EpisodeRecord] = []
    for part in batches(system, len(refs)):
        arrays = [ref.q for ref in refs[part]]
        if actions.loop == "closed":
            agent = _GuardedAgent(act, actions.max_adjust)
            with GuardedRuntime(agent, (history, future), None, system.limits, system.dt) as guarded:
                part_records = rollout(system, arrays, guarded, future, step_timeout=step_timeout)
            if agent.error is not None:
                error = agent.error
                raise EfficientTrackError(f"evaluate: the agent failed: {type(error).__name__}: {error}") from error
        else:
            driver = _AgentDriver(act, actions, history, future)
            part_records = rollout(system, arrays, driver, future, step_timeout=step_timeout)
        for record, ref in zip(part_records, refs[part], strict=True):
            if actions.loop == "open":  # what was sent is the PWM; the reference is the desired position
                record.u, record.q_ref = record.q_ref, record.q_des.copy()
            record.meta.update(name=ref.name, loop=actions.loop)
        records += part_records
    return records
