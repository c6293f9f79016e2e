"""Algorithm 2: the adjustment policy in front of any closed-loop system, with a safety guard.

Two levels:

- :class:`Runtime`, step by step, for a real machine: ``start(obs0)``, then per control period
  ``step(obs, q_des_future) -> Sent``, then ``stop()`` (or use it as a context manager). It keeps the
  histories exactly as training builds them (``efficienttrack.dataset``), guards every output
  and counts every intervention::

      with Runtime(load_policy("policy.pt"), limits=GuardLimits.load("xe75_limits.yaml")) as rt:
          rt.start(read_obs())                       # (1, 8)
          for t in range(T):
              sent = rt.step(read_obs(), q_des[None, t + 1 : t + 1 + rt.future_length])  # q_des padded at the end
              send_reference(sent.q_ref[0])          # to the machine's position controller
      print(rt.fallbacks, rt.counts)
- :func:`track`, whole episodes: runs :class:`Runtime` over references on a (batched) system
  and returns :class:`~efficienttrack.records.EpisodeRecord` s. ``policy=None`` is the PD
  controller alone (a = 0) through the same loop.

Both run on the one episode loop of :mod:`efficienttrack.episodes`, as data collection does.

The guard owns its limits (:class:`~efficienttrack.systems.limits.GuardLimits`, from the system or a limits
file, never from the checkpoint, whose ``max_adjust`` can only tighten the bound). Every step, per machine:

1. a non-finite observation, one that jumped farther than ``max_speed · dt``, one repeated bit for bit for
   ``stale_steps`` steps, or a desired position the policy sees outside the joint limits: fall back;
2. a policy that raises, returns a shape other than (N, 4), a non-finite value or |a| beyond the bound: fall back;
3. the adjustment's change from the last step is limited to ``max_adjust_rate``;
4. the reference sent is clamped into the joint limits.

Falling back sends the raw desired position (a = 0). Each intervention sets a :class:`~efficienttrack.episodes.Guard`
bit in :attr:`Sent.guard`, and records keep them per step (``meta["guard"]``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from efficienttrack import dataset
from efficienttrack.angles import wrap
from efficienttrack.episodes import FALLBACK, STEP_TIMEOUT, Guard, Sent, batches, rollout
from efficienttrack.errors import EfficientTrackError
from efficienttrack.joints import DT, SWING
from efficienttrack.nets import resolve_device
from efficienttrack.policy import seen_lengths
from efficienttrack.progress import ProgressDisplay
from efficienttrack.records import EpisodeRecord
from efficienttrack.references import Reference
from efficienttrack.systems.limits import DEFAULT_LIMITS, GuardLimits
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

    Guard: see the module docstring; a step that falls back sends the raw desired position ``q*_{t+1}``
    (clamped into the joint limits) for that machine and is counted in :attr:`fallbacks`.

    Args:
        policy: an ``AdjustmentPolicy`` (``efficienttrack.policy``), or None for the PD controller
            alone (a = 0; history and future length 1).
        device: torch device the policy runs on (its own device when None).
        limits: the machine's limits (a system's ``limits``, or :meth:`GuardLimits.load`); :data:`DEFAULT_LIMITS`
            when None. The policy's ``cfg.max_adjust`` only tightens ``limits.max_adjust``.
        dt: control period, s (for the observation jump check).
    """

    def __init__(
        self,
        policy: torch.nn.Module | None,
        device: torch.device | str | None = None,
        limits: GuardLimits | None = None,
        dt: float = DT,
    ) -> None:
        self.policy = policy
        self.history_length, self.future_length = seen_lengths(policy.cfg if policy is not None else None)
        """h, F: lengths of the histories kept and of the desired positions ``step`` needs (policy's, or 1 without)."""
        self.limits = DEFAULT_LIMITS if limits is None else limits
        """The limits the guard enforces."""
        self.max_adjust = np.zeros(4) if policy is None else self.limits.adjust_bound(policy.cfg.max_adjust)
        """(4,) rad, the bound of |a| enforced: the machine's, tightened (never widened) by the checkpoint's."""
        if policy is None:
            self.device = torch.device("cpu")
        else:
            self.device = resolve_device(device) if device is not None else next(policy.parameters()).device
            policy.to(self.device)
        self._rate = np.asarray(self.limits.max_adjust_rate, dtype=np.float64)
        self._max_move = np.asarray(self.limits.max_speed, dtype=np.float64) * dt
        self.fallbacks = np.zeros(0, dtype=np.int64)
        """(N,) number of steps per machine since ``start`` that fell back to the raw desired position."""
        self.counts: dict[str, np.ndarray] = {}
        """Reason (``Guard`` name, lower case) → (N,) number of steps per machine with that intervention."""
        self.steps = 0
        """Steps taken since ``start``."""
        self._history: dataset.History | None = None
        self._a_prev = np.zeros((0, 4))
        self._repeats = np.zeros(0, dtype=np.int64)

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
            obs0: (N, 8) [rad, rad/s], the measured start observations (finite: there is nothing to fall back on yet).
        """
        obs0 = np.asarray(obs0, dtype=np.float64)
        if obs0.ndim != 2 or obs0.shape[1] != 8:
            raise EfficientTrackError(f"runtime: start expects obs0 of shape (N, 8), got {obs0.shape}")
        if not np.all(np.isfinite(obs0)):
            raise EfficientTrackError("runtime: non-finite start observation; nothing was sent")
        n = len(obs0)
        self._history = dataset.initial_history(obs0, self.history_length)
        self.fallbacks = np.zeros(n, dtype=np.int64)
        self.counts = {str(flag.name).lower(): np.zeros(n, dtype=np.int64) for flag in Guard}
        self.steps = 0
        self._a_prev = np.zeros((n, 4))
        self._repeats = np.zeros(n, dtype=np.int64)

    def step(self, obs: np.ndarray, q_des_future: np.ndarray) -> Sent:
        """One control period: the reference to send for step t+1.

        Args:
            obs: (N, 8) [rad, rad/s], the observation ``o_t`` just measured (a non-finite one falls back).
            q_des_future: (N, F', 4) rad, desired positions ``q*_{t+1} … q*_{t+F'}``, F' ≥ ``future_length``
                (padded with the last desired position past the end of the reference). Only ``[:, 0]`` is
                used when there is no policy; it must be finite (there is nothing else to send).

        Returns:
            The reference sent (N, 4) rad, the adjustment as sent, the per-machine fallback flags and
            :class:`~efficienttrack.episodes.Guard` bits.
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
        F = self.future_length
        if self.policy is not None and q_des_future.shape[1] < F:
            raise EfficientTrackError(f"runtime: the policy needs {F} future desired positions, got {q_des_future.shape[1]}")
        q_next = q_des_future[:, 0]
        if not np.all(np.isfinite(q_next)):
            machines = np.flatnonzero(~np.all(np.isfinite(q_next), axis=1)).tolist()
            raise EfficientTrackError(
                f"runtime: non-finite desired position q*_(t+1) for machine(s) {machines}; nothing was sent"
            )
        guard = self._check_inputs(obs, q_des_future[:, : max(F, 1)])
        obs = np.where(guard[:, None] & Guard.OBS_NONFINITE, self._history.obs[:, -1], obs)  # keep the last good one
        history = dataset.push_observation(self._history, obs)
        a = np.zeros((n, 4))
        if self.policy is not None:
            a, policy_guard = self._act(history, np.where(np.isfinite(q_des_future[:, :F]), q_des_future[:, :F], 0.0))
            guard |= policy_guard
        fallback = (guard & FALLBACK) != 0
        a = np.where(fallback[:, None], 0.0, a)
        # rate limit (from the adjustment sent last step; a fallback's a = 0 is not limited)
        limited = np.clip(a, self._a_prev - self._rate, self._a_prev + self._rate)
        guard |= _bits(~fallback & np.any(limited != a, axis=1), Guard.RATE_LIMITED)
        a = np.where(fallback[:, None], 0.0, limited)
        # joint limits
        q_ref = self.limits.clamp(q_next + a)
        clamped = np.any(q_ref != q_next + a, axis=1)
        guard |= _bits(clamped, Guard.CLAMPED)
        a = np.where(clamped[:, None], q_ref - q_next, a)
        a[:, SWING] = np.where(clamped, wrap(a[:, SWING]), a[:, SWING])  # a swing clamped after wrapping
        self._history = dataset.push_reference(history, q_ref)
        self._a_prev = a
        self.fallbacks += fallback
        for flag in Guard:
            self.counts[str(flag.name).lower()] += (guard & flag.value) != 0
        self.steps += 1
        return Sent(q_ref=q_ref, adjustment=a, fallback=fallback, guard=guard)

    def sent_instead(self, q_ref: np.ndarray) -> None:
        """The machine took ``q_ref`` instead of the reference the last ``step`` returned: the history holds it.

        A loop that sends the raw reference (shadow mode, a hold, a stale sensor) or a machine that clamps calls this,
        so that the policy's next step sees the references really sent, as in training. The guard's rate limit stays
        on the adjustments ``step`` returned.

        Args:
            q_ref: (N, 4) rad, the references really sent in the last step.
        """
        if self._history is None or self.steps == 0:
            raise EfficientTrackError("runtime: sent_instead called before a step (or after stop)")
        q_ref = np.asarray(q_ref, dtype=np.float64)
        if q_ref.shape != self._history.q_ref[:, -1].shape or not np.all(np.isfinite(q_ref)):
            raise EfficientTrackError(f"runtime: sent_instead expects finite q_ref of shape (N, 4), got {q_ref.shape}")
        q_hist = self._history.q_ref.copy()
        q_hist[:, -1] = q_ref
        self._history = dataset.History(obs=self._history.obs, q_ref=q_hist)

    def stop(self) -> None:
        """End the episode (the counters stay readable)."""
        self._history = None

    def _check_inputs(self, obs: np.ndarray, q_des_seen: np.ndarray) -> np.ndarray:
        """(N,) uint16 Guard bits of the inputs: non-finite, jumping or stale observations, desired positions outside."""
        last = self._history.obs[:, -1]
        finite = np.all(np.isfinite(obs), axis=1)
        with np.errstate(invalid="ignore"):
            move = np.abs(obs[:, :4] - last[:, :4])
            move[:, SWING] = np.abs(wrap(move[:, SWING]))
            jump = finite & np.any(move > self._max_move, axis=1)
        self._repeats = np.where(np.all(obs == last, axis=1), self._repeats + 1, 0)
        stale = np.zeros(len(obs), dtype=bool) if self.limits.stale_steps is None else self._repeats >= self.limits.stale_steps
        outside = np.any(self.limits.outside(q_des_seen), axis=(1, 2))
        return (
            _bits(~finite, Guard.OBS_NONFINITE)
            | _bits(jump, Guard.OBS_JUMP)
            | _bits(stale, Guard.OBS_STALE)
            | _bits(outside, Guard.DESIRED_OUTSIDE)
        )

    def _act(self, history: dataset.History, q_des_future: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The policy's adjustment (N, 4) rad (0 where it fell back) and its (N,) uint16 Guard bits."""
        n = len(q_des_future)
        everyone = np.ones(n, dtype=bool)
        try:
            with torch.no_grad():
                out = self.policy(
                    torch.as_tensor(history.obs, dtype=torch.float32, device=self.device),
                    torch.as_tensor(history.q_ref, dtype=torch.float32, device=self.device),
                    torch.as_tensor(q_des_future, dtype=torch.float32, device=self.device),
                )
            a = np.asarray(out.detach().cpu().double().numpy() if isinstance(out, torch.Tensor) else out, dtype=np.float64)
        except Exception:  # any failure of the policy falls back to the raw reference, counted
            return np.zeros((n, 4)), _bits(everyone, Guard.POLICY_ERROR)
        if a.shape != (n, 4):
            return np.zeros((n, 4)), _bits(everyone, Guard.POLICY_SHAPE)
        nonfinite = ~np.all(np.isfinite(a), axis=1)
        with np.errstate(invalid="ignore"):
            beyond = ~nonfinite & np.any(np.abs(a) > self.max_adjust + GUARD_TOLERANCE, axis=1)
        guard = _bits(nonfinite, Guard.POLICY_NONFINITE) | _bits(beyond, Guard.ADJUST_BOUND)
        return np.where((nonfinite | beyond)[:, None], 0.0, a), guard


def _bits(hit: np.ndarray, flag: Guard) -> np.ndarray:
    """(N,) uint16: ``flag`` where ``hit`` (N,) bool, else 0."""
    return np.where(hit, np.uint16(flag.value), np.uint16(0))


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
        :func:`~efficienttrack.episodes.guard_steps`)}.

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
