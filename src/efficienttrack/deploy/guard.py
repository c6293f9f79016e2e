"""The guarded step of Algorithm 2, without torch: histories, the guard and its counters, shared by both runtimes.

:class:`GuardedRuntime` is the one implementation of the guard. The torch runtime
(:class:`efficienttrack.deploy.runtime.Runtime`) and the torch-free ONNX runtime
(:class:`efficienttrack.deploy.onnx_runtime.OnnxRuntime`) differ only in how they evaluate the policy: each hands
:class:`GuardedRuntime` a function from the float64 histories to the adjustment.

The guard owns its limits (:class:`~efficienttrack.systems.limits.GuardLimits`, from the system or a limits
file, never from the policy file, whose ``max_adjust`` can only tighten the bound). Every step, per machine:

1. a non-finite observation, one that jumped farther than ``max_speed · dt``, one repeated bit for bit for
   ``stale_steps`` steps, or a desired position the policy sees outside the joint limits: fall back;
2. a policy that raises, returns a shape other than (N, 4), a non-finite value or |a| beyond the bound: fall back;
3. the adjustment's change from the last step is limited to ``max_adjust_rate``;
4. the reference sent is clamped into the joint limits.

Falling back sends the raw desired position (a = 0). Each intervention sets a :class:`~efficienttrack.deploy.episodes.Guard`
bit in :attr:`Sent.guard`, and records keep them per step (``meta["guard"]``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Self

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT, SWING
from efficienttrack.data.windows import History, initial_history, push_observation, push_reference
from efficienttrack.deploy.episodes import FALLBACK, Guard, Sent
from efficienttrack.systems.limits import DEFAULT_LIMITS, GuardLimits

GUARD_TOLERANCE = 1e-6
"""Slack (rad) on the adjustment bound before the guard intervenes (float32 round-off)."""

PolicyCall = Callable[[np.ndarray, np.ndarray, np.ndarray], Any]
"""A policy as the guard calls it: ``(obs_hist (N, h, 8), qref_hist (N, h, 4), q_des_future (N, F, 4))``, float64
[rad, rad/s] → the adjustment a_t (N, 4) rad, anything ``np.asarray`` takes."""


class GuardedRuntime:
    """Algorithm 2 for N machines at once, one control period at a time, around any policy function.

    Lifecycle: ``start(obs0)`` → ``step(obs, q_des_future)`` every period → ``stop()``; also a
    context manager. At start the histories are filled with ``o_0`` and ``q^r_0 = q_0`` (the measured start
    position), exactly as the training windows are padded; each step appends ``o_t`` and ``q^r_t`` (the
    reference sent in the previous step) before asking the policy for ``a_t``.

    Guard: see the module docstring; a step that falls back sends the raw desired position ``q*_{t+1}``
    (clamped into the joint limits) for that machine and is counted in :attr:`fallbacks`.

    Args:
        act: the policy (:data:`PolicyCall`), or None for the PD controller alone (a = 0).
        lengths: (h, F), the history length and the number of future desired positions the policy sees ((1, 1)
            without a policy).
        policy_max_adjust: (4,) rad, the bound the policy file states, or None; it only tightens ``limits.max_adjust``.
        limits: the machine's limits (a system's ``limits``, or :meth:`GuardLimits.load`), always given: None is the
            explicit choice of :data:`DEFAULT_LIMITS` (±2π, no joint limits), never a forgotten argument.
        dt: control period, s (for the observation jump check).
    """

    def __init__(
        self,
        act: PolicyCall | None,
        lengths: Sequence[int],
        policy_max_adjust: Sequence[float] | None,
        limits: GuardLimits | None,
        dt: float = DT,
    ) -> None:
        self._policy_call = act
        self.history_length, self.future_length = (int(n) for n in lengths)
        """h, F: lengths of the histories kept and of the desired positions ``step`` needs (policy's, or 1 without)."""
        self.limits = DEFAULT_LIMITS if limits is None else limits
        """The limits the guard enforces."""
        self.max_adjust = np.zeros(4) if act is None else self.limits.adjust_bound(policy_max_adjust)
        """(4,) rad, the bound of |a| enforced: the machine's, tightened (never widened) by the policy file's."""
        self._rate = np.asarray(self.limits.max_adjust_rate, dtype=np.float64)
        self._max_move = np.asarray(self.limits.max_speed, dtype=np.float64) * dt
        self.fallbacks = np.zeros(0, dtype=np.int64)
        """(N,) number of steps per machine since ``start`` that fell back to the raw desired position."""
        self.counts: dict[str, np.ndarray] = {}
        """Reason (``Guard`` name, lower case) → (N,) number of steps per machine with that intervention."""
        self.steps = 0
        """Steps taken since ``start``."""
        self._history: History | None = None
        self._a_prev = np.zeros((0, 4))
        self._repeats = np.zeros(0, dtype=np.int64)

    def __enter__(self) -> Self:
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
        self._history = initial_history(obs0, self.history_length)
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
            :class:`~efficienttrack.deploy.episodes.Guard` bits.
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
        if self._policy_call is not None and q_des_future.shape[1] < F:
            raise EfficientTrackError(f"runtime: the policy needs {F} future desired positions, got {q_des_future.shape[1]}")
        q_next = q_des_future[:, 0]
        if not np.all(np.isfinite(q_next)):
            machines = np.flatnonzero(~np.all(np.isfinite(q_next), axis=1)).tolist()
            raise EfficientTrackError(
                f"runtime: non-finite desired position q*_(t+1) for machine(s) {machines}; nothing was sent"
            )
        guard = self._check_inputs(obs, q_des_future[:, : max(F, 1)])
        obs = np.where(guard[:, None] & Guard.OBS_NONFINITE, self._history.obs[:, -1], obs)  # keep the last good one
        history = push_observation(self._history, obs)
        a = np.zeros((n, 4))
        if self._policy_call is not None:
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
        self._history = push_reference(history, q_ref)
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
        self._history = History(obs=self._history.obs, q_ref=q_hist)

    def stop(self) -> None:
        """End the episode (the counters stay readable)."""
        self._history = None

    def _check_inputs(self, obs: np.ndarray, q_des_seen: np.ndarray) -> np.ndarray:
        """(N,) uint16 Guard bits of the inputs: non-finite, jumping or stale observations, desired positions outside."""
        assert self._history is not None  # step checks that the runtime was started
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

    def _act(self, history: History, q_des_future: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The policy's adjustment (N, 4) rad (0 where it fell back) and its (N,) uint16 Guard bits."""
        assert self._policy_call is not None  # step asks for an adjustment only with a policy
        n = len(q_des_future)
        everyone = np.ones(n, dtype=bool)
        try:
            a = np.asarray(self._policy_call(history.obs, history.q_ref, q_des_future), dtype=np.float64)
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
