"""Algorithm 2: the adjustment policy in front of any closed-loop system, with a safety guard.

Two levels:

- :class:`Runtime`, step by step, for a real machine: ``start(obs0)``, then per control period
  ``step(obs, q_des_future) -> Sent``, then ``stop()`` (or use it as a context manager). It keeps the
  histories exactly as training builds them (``efficienttrack.dataset``), guards every output
  and counts every intervention::

      with Runtime(load_policy("policy.pt")) as rt:
          rt.start(read_obs())                       # (1, 8)
          for t in range(T):
              sent = rt.step(read_obs(), q_des[None, t + 1 : t + 1 + rt.future_length])  # q_des padded at the end
              send_reference(sent.q_ref[0])          # to the machine's position controller
      print(rt.fallbacks)
- :func:`track`, whole episodes: runs :class:`Runtime` over references on a (batched) system
  and returns :class:`~efficienttrack.records.EpisodeRecord` s. ``policy=None`` is the PD
  controller alone (a = 0) through the same loop.

Both run on the one episode loop of :mod:`efficienttrack.episodes`, as data collection does.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from efficienttrack import dataset
from efficienttrack.episodes import Sent, batches, rollout
from efficienttrack.errors import EfficientTrackError
from efficienttrack.nets import resolve_device
from efficienttrack.policy import seen_lengths
from efficienttrack.progress import ProgressDisplay
from efficienttrack.records import EpisodeRecord
from efficienttrack.references import Reference
from efficienttrack.systems.protocol import BatchedSystem

GUARD_TOLERANCE = 1e-6
"""Slack (rad) on the adjustment bound before the guard intervenes (float32 round-off)."""


class Runtime:
    """Algorithm 2 for N machines at once, one control period at a time.

    Lifecycle: ``start(obs0)`` → ``step(obs, q_des_future)`` every period → ``stop()``; also a
    context manager (``with Runtime(policy) as rt: rt.start(obs0); ...``). At start the histories
    are filled with ``o_0`` and ``q^r_0 = q_0`` (the measured start position), exactly as the
    training windows are padded; each step appends ``o_t`` and ``q^r_t`` (the reference sent in
    the previous step) before asking the policy for ``a_t``.

    Guard: where the policy returns a non-finite value or ``|a| > max_adjust`` for a machine, the
    raw desired position ``q*_{t+1}`` is sent for that machine and the step is counted in
    :attr:`fallbacks`.

    Args:
        policy: an ``AdjustmentPolicy`` (``efficienttrack.policy``), or None for the PD controller
            alone (a = 0; history and future length 1).
        device: torch device the policy runs on (its own device when None).
    """

    def __init__(self, policy: torch.nn.Module | None, device: torch.device | str | None = None) -> None:
        self.policy = policy
        self.history_length, self.future_length = seen_lengths(policy.cfg if policy is not None else None)
        """h, F: lengths of the histories kept and of the desired positions ``step`` needs (policy's, or 1 without)."""
        if policy is None:
            self.max_adjust = np.zeros(4)
            self.device = torch.device("cpu")
        else:
            self.max_adjust = np.asarray(policy.cfg.max_adjust, dtype=np.float64)
            self.device = resolve_device(device) if device is not None else next(policy.parameters()).device
            policy.to(self.device)
        self.fallbacks = np.zeros(0, dtype=np.int64)
        """(N,) number of guarded steps per machine since ``start``."""
        self.steps = 0
        """Steps taken since ``start``."""
        self._history: dataset.History | None = None

    def __enter__(self) -> Runtime:
        """Enter the context (``start`` is still called with the first observation)."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Leave the context: ``stop``."""
        self.stop()

    @property
    def running(self) -> bool:
        """True between ``start`` and ``stop``."""
        return self._history is not None

    def start(self, obs0: np.ndarray) -> None:
        """Begin an episode for N machines: histories filled with ``o_0`` and ``q^r_0 = q_0``, counters zeroed.

        Args:
            obs0: (N, 8) [rad, rad/s], the measured start observations.
        """
        obs0 = np.asarray(obs0, dtype=np.float64)
        if obs0.ndim != 2 or obs0.shape[1] != 8:
            raise EfficientTrackError(f"runtime: start expects obs0 of shape (N, 8), got {obs0.shape}")
        self._history = dataset.initial_history(obs0, self.history_length)
        self.fallbacks = np.zeros(len(obs0), dtype=np.int64)
        self.steps = 0

    def step(self, obs: np.ndarray, q_des_future: np.ndarray) -> Sent:
        """One control period: the reference to send for step t+1.

        Args:
            obs: (N, 8) [rad, rad/s], the observation ``o_t`` just measured.
            q_des_future: (N, F', 4) rad, desired positions ``q*_{t+1} … q*_{t+F'}``, F' ≥ ``future_length``
                (padded with the last desired position past the end of the reference). Only ``[:, 0]`` is
                used when there is no policy.

        Returns:
            The reference sent, the adjustment and the per-machine fallback flags.
        """
        if self._history is None:
            raise EfficientTrackError("runtime: step called before start (or after stop)")
        obs = np.asarray(obs, dtype=np.float64)
        q_des_future = np.asarray(q_des_future, dtype=np.float64)
        n = len(self.fallbacks)
        if obs.shape != (n, 8) or q_des_future.ndim != 3 or q_des_future.shape[0] != n or q_des_future.shape[2] != 4:
            raise EfficientTrackError(
                f"runtime: step expects obs (N, 8) and q_des_future (N, F, 4) with N = {n}, "
                f"got {obs.shape} and {q_des_future.shape}"
            )
        if not (np.all(np.isfinite(obs)) and np.all(np.isfinite(q_des_future))):
            raise EfficientTrackError("runtime: non-finite observation or desired position; nothing was sent")
        history = dataset.push_observation(self._history, obs)
        q_next = q_des_future[:, 0]
        if self.policy is None:
            a = np.zeros((n, 4))
        else:
            a = self._act(history, q_des_future)
        bad = ~np.all(np.isfinite(a), axis=1) | np.any(np.abs(a) > self.max_adjust + GUARD_TOLERANCE, axis=1)
        a = np.where(bad[:, None], 0.0, a)
        q_ref = q_next + a
        self._history = dataset.push_reference(history, q_ref)
        self.fallbacks += bad
        self.steps += 1
        return Sent(q_ref=q_ref, adjustment=a, fallback=bad)

    def stop(self) -> None:
        """End the episode (the counters stay readable)."""
        self._history = None

    def _act(self, history: dataset.History, q_des_future: np.ndarray) -> np.ndarray:
        F = self.future_length
        if q_des_future.shape[1] < F:
            raise EfficientTrackError(f"runtime: the policy needs {F} future desired positions, got {q_des_future.shape[1]}")
        with torch.no_grad():
            a = self.policy(
                torch.as_tensor(history.obs, dtype=torch.float32, device=self.device),
                torch.as_tensor(history.q_ref, dtype=torch.float32, device=self.device),
                torch.as_tensor(q_des_future[:, :F], dtype=torch.float32, device=self.device),
            )
        return a.detach().cpu().double().numpy()


def track(
    system: BatchedSystem,
    policy: torch.nn.Module | None,
    references: Sequence[Reference],
    device: torch.device | str | None = None,
    progress: bool = True,
    description: str = "tracking",
    on_done: Callable[[list[EpisodeRecord]], None] | None = None,
) -> list[EpisodeRecord]:
    """Algorithm 2 over a set of references: one record per reference.

    Args:
        system: the closed-loop system (``load_system``).
        policy: the adjustment policy, or None for the PD controller alone.
        references: the references (``.name``, ``.q`` (L_i, 4) rad of desired positions q*_0 … q*_{L_i − 1}).
        device: where the policy runs (its own device when None).
        progress: show progress (a bar on a terminal, plain lines otherwise).
        description: label of the progress bar and of errors.
        on_done: called with the records of every group of episodes as soon as it has run (to flush them).

    Returns:
        Records with ``q_ref`` = the adjusted reference sent, ``q_des`` = the desired one, and
        ``meta`` = {name, method, fallbacks}.

    Raises:
        EfficientTrackError: the system or the policy raised; the message names the episodes that were running
            and the error (chained as the cause).
    """
    records: list[EpisodeRecord] = []
    method = "pd" if policy is None else "efficienttrack"
    with ProgressDisplay(progress) as bar:
        for part in batches(system, len(references)):
            runtime = Runtime(policy, device=device)
            try:
                with runtime:
                    arrays = [ref.q for ref in references[part]]
                    part_records = rollout(system, arrays, runtime, runtime.future_length, bar, description)
            except Exception as exc:
                names = ", ".join(ref.name for ref in references[part])
                raise EfficientTrackError(f"{description}: failed on episode(s) {names}: {type(exc).__name__}: {exc}") from exc
            for record, ref in zip(part_records, references[part], strict=True):
                record.meta.update(name=ref.name, method=method)
            records += part_records
            if on_done is not None:
                on_done(part_records)
    return records
