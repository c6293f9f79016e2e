"""Algorithm 2: the adjustment policy in front of any closed-loop system, with a safety guard.

Two levels:

- :class:`Runtime`, step by step, for a real machine: ``start(obs0)``, then per control period
  ``step(obs, q_des_future) -> Sent``, then ``stop()`` (or use it as a context manager). It keeps the
  histories exactly as training builds them (``efficienttrack.data.windows``), guards every output
  and counts every intervention::

      with Runtime(load_policy("policy.pt"), limits=GuardLimits.load("xe75_limits.yaml")) as rt:
          rt.start(read_obs())                       # (1, 8)
          for t in range(T):
              sent = rt.step(read_obs(), q_des[None, t + 1 : t + 1 + rt.future_length])  # q_des padded at the end
              send_reference(sent.q_ref[0])          # to the machine's position controller
      print(rt.fallbacks, rt.counts)

  Each ``step`` without a time stamp stands for one control period after the last. A caller that may miss periods
  (dropped samples, a busy computer) passes the observation's time, ``rt.start(obs0, t=time.monotonic())`` and
  ``rt.step(obs, q_des_future, t=time.monotonic())``: the jump check then allows the real time since the last
  observation, and a gap of more than ``max_gap`` periods falls back (a = 0) and starts the histories afresh
  (:mod:`efficienttrack.deploy.guard`). Without stamps a gap still shows in the readings themselves: a position that
  moved farther than its velocities allow falls back and starts that machine's histories afresh too.
- :func:`track`, whole episodes: runs :class:`Runtime` over references on a (batched) system
  and returns :class:`~efficienttrack.data.records.EpisodeRecord` s. ``policy=None`` is the PD
  controller alone (a = 0) through the same loop.

Both run on the one episode loop of :mod:`efficienttrack.deploy.episodes`, as data collection does.

The guard (:mod:`efficienttrack.deploy.guard`, one implementation shared with the torch-free ONNX runtime of
:mod:`efficienttrack.deploy.onnx_runtime`) owns its limits, falls back to the raw desired position on any fault of the
inputs or the policy, limits the adjustment's rate and clamps the reference sent into the joint limits; each
intervention is a :class:`~efficienttrack.deploy.episodes.Guard` bit in :attr:`Sent.guard`, kept per step in records.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import cast

import numpy as np
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.references import Reference
from efficienttrack.deploy.episodes import STEP_TIMEOUT, batches, rollout
from efficienttrack.deploy.guard import MAX_GAP, GuardedRuntime
from efficienttrack.learn.nets import resolve_device
from efficienttrack.learn.policy import seen_lengths
from efficienttrack.learn.settings import PolicyConfig
from efficienttrack.systems.limits import GuardLimits
from efficienttrack.systems.protocol import BatchedSystem


class Runtime(GuardedRuntime):
    """Algorithm 2 with a torch policy: the guarded step of :class:`~efficienttrack.deploy.guard.GuardedRuntime`.

    ``start``/``step``/``stop``, the histories, the guard and its counters are :class:`GuardedRuntime`'s; this
    class evaluates an ``AdjustmentPolicy`` on float32 tensors on its device.

    Args:
        policy: an ``AdjustmentPolicy`` (``efficienttrack.learn.policy``), or None for the PD controller
            alone (a = 0; history and future length 1).
        device: torch device the policy runs on (its own device when None).
        limits: the machine's limits (a system's ``limits``, or :meth:`GuardLimits.load`), a required keyword: a
            runtime without them would send anything within ±2π. ``limits=None`` is the explicit choice of
            :data:`DEFAULT_LIMITS` (a simulator, a test). The policy's ``cfg.max_adjust`` only tightens
            ``limits.max_adjust``.
        dt: control period, s (for the observation jump check, and the period a ``step`` without ``t`` stands for).
        max_gap: periods between two time-stamped observations (``step(..., t=...)``) beyond which samples count as
            dropped: the step falls back and the histories start afresh (:data:`~efficienttrack.deploy.guard.MAX_GAP`).
    """

    def __init__(
        self,
        policy: torch.nn.Module | None,
        device: torch.device | str | None = None,
        *,
        limits: GuardLimits | None,
        dt: float = DT,
        max_gap: float = MAX_GAP,
    ) -> None:
        cfg = cast(PolicyConfig, policy.cfg) if policy is not None else None  # a policy module carries its PolicyConfig
        act = None if policy is None else self._evaluate
        super().__init__(act, seen_lengths(cfg), None if cfg is None else cfg.max_adjust, limits, dt, max_gap)
        self.policy = policy
        if policy is None:
            self.device = torch.device("cpu")
        else:
            self.device = resolve_device(device) if device is not None else next(policy.parameters()).device
            policy.to(self.device)

    def _evaluate(self, obs_hist: np.ndarray, qref_hist: np.ndarray, q_des_future: np.ndarray) -> np.ndarray:
        """The policy on the histories (:data:`~efficienttrack.deploy.guard.PolicyCall`), in float32 on its device."""
        assert self.policy is not None  # the guard's policy call only when there is a policy
        with torch.no_grad():
            out = self.policy(
                torch.as_tensor(obs_hist, dtype=torch.float32, device=self.device),
                torch.as_tensor(qref_hist, dtype=torch.float32, device=self.device),
                torch.as_tensor(q_des_future, dtype=torch.float32, device=self.device),
            )
        return out.detach().cpu().double().numpy() if isinstance(out, torch.Tensor) else out


def check_references(references: Sequence[Reference], limits: GuardLimits) -> None:
    """Refuse, before anything moves, a reference that leaves the joint limits (naming it, the joint and the step).

    Args:
        references: the references (``.name``, ``.q`` (L, 4) rad).
        limits: the machine's limits.
    """
    for ref in references:
        limits.check_reference(ref.q, ref.name)


def track(
    system: BatchedSystem,
    policy: torch.nn.Module | None,
    references: Sequence[Reference],
    device: torch.device | str | None = None,
    progress: bool = True,
    description: str = "tracking",
    limits: GuardLimits | None = None,
    step_timeout: float | None = STEP_TIMEOUT,
    on_done: Callable[[list[EpisodeRecord]], None] | None = None,
) -> list[EpisodeRecord]:
    """Algorithm 2 over a set of references: one record per reference.

    Args:
        system: the closed-loop system (``load_system``).
        policy: the adjustment policy, or None for the PD controller alone.
        references: the references (``.name``, ``.q`` (L_i, 4) rad of desired positions q*_0 … q*_{L_i − 1});
            every one must stay within the joint limits (checked before the first step).
        device: where the policy runs (its own device when None).
        progress: show progress (a bar on a terminal, plain lines otherwise).
        description: label of the progress bar and of errors.
        limits: the limits the guard enforces; the system's (``system.limits``) when None.
        step_timeout: seconds a system step may take before the episodes end with an error (None: no limit).
        on_done: called with the records of every group of episodes as soon as it has run (to flush them).

    Returns:
        Records with ``q_ref`` = the adjusted reference sent, ``q_des`` = the desired one, and
        ``meta`` = {name, method, fallbacks (steps that fell back), guard ({reason: steps}, see
        :func:`~efficienttrack.deploy.episodes.guard_steps`)}.

    Raises:
        EfficientTrackError: a reference outside the joint limits (before any step); the system or the policy
            raised, or a step timed out: the message names the episodes that were running and the error (chained).
    """
    limits = system.limits if limits is None else limits
    check_references(references, limits)
    records: list[EpisodeRecord] = []
    method = "pd" if policy is None else "efficienttrack"
    with ProgressDisplay(progress) as bar:
        for part in batches(system, len(references)):
            runtime = Runtime(policy, device=device, limits=limits, dt=system.dt)
            try:
                with runtime:
                    arrays = [ref.q for ref in references[part]]
                    part_records = rollout(system, arrays, runtime, runtime.future_length, bar, description, step_timeout)
            except Exception as exc:
                names = ", ".join(ref.name for ref in references[part])
                raise EfficientTrackError(f"{description}: failed on episode(s) {names}: {type(exc).__name__}: {exc}") from exc
            for record, ref in zip(part_records, references[part], strict=True):
                record.meta.update(name=ref.name, method=method)
            records += part_records
            if on_done is not None:
                on_done(part_records)
    return records
