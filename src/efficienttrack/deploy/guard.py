"""The guarded step of Algorithm 2, without torch: histories, the guard and its counters, shared by both runtimes.

:class:`GuardedRuntime` is the one implementation of the guard. The torch runtime
(:class:`efficienttrack.deploy.runtime.Runtime`) and the torch-free ONNX runtime
(:class:`efficienttrack.deploy.onnx_runtime.OnnxRuntime`) differ only in how they evaluate the policy: each hands
:class:`GuardedRuntime` a function from the float64 histories to the adjustment.

The guard owns its limits (:class:`~efficienttrack.systems.limits.GuardLimits`, from the system or a limits
file, never from the policy file, whose ``max_adjust`` can only tighten the bound). Every step, per machine:

1. a non-finite observation, one that jumped farther than ``max_speed · dt`` or farther than its velocities allow
   (:func:`~efficienttrack.deploy.sensor.motion_excess` beyond :data:`~efficienttrack.deploy.sensor.SENSOR_TOLERANCE`:
   dropped samples the caller did not stamp, or a faulty sensor; that machine's histories start afresh), one repeated
   bit for bit for
   ``stale_steps`` steps, one that comes more than ``max_gap`` periods after the last (dropped samples, see below), or a
   desired position the policy sees outside the joint limits: fall back;
2. a policy that raises, returns a shape other than (N, 4), a non-finite value or |a| beyond the bound: fall back;
3. the adjustment's change from the last step is limited to ``max_adjust_rate``;
4. the reference sent is clamped into the joint limits.

Falling back sends the raw desired position (a = 0). Each intervention sets a :class:`~efficienttrack.deploy.episodes.Guard`
bit in :attr:`Sent.guard`, and records keep them per step (``meta["guard"]``).

Time: without time stamps every ``step`` is one control period ``dt`` after the one before, as
:func:`~efficienttrack.deploy.runtime.track` and the fixed-rate loop of :mod:`efficienttrack.deploy.loop` call it (the
loop watches the time itself: a dropped sample is a step with a non-finite observation, and missed periods are overruns
it counts, holds on and stops at). A caller that may skip periods passes ``t``, the observation's
time in seconds on a monotonic clock, to ``start`` and ``step``: the jump check then allows ``max_speed`` times the
real time since the last observation, and an observation more than ``max_gap`` periods (:data:`MAX_GAP`) after the last
falls back (:attr:`~efficienttrack.deploy.episodes.Guard.OBS_STALE`: the samples between were dropped) and starts the
histories afresh from it, as ``start`` does: the histories hold one entry per period, and the policy must not see the
jump over the gap as one period's motion. The adjustment comes back from 0 at ``max_adjust_rate``. A period between two
calls without both stamps counts as one.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, Self

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT, SWING
from efficienttrack.data.windows import History, initial_history, push_observation, push_reference
from efficienttrack.deploy.episodes import FALLBACK, Guard, Sent
from efficienttrack.deploy.sensor import SENSOR_TOLERANCE, motion_excess
from efficienttrack.systems.limits import DEFAULT_LIMITS, GuardLimits

GUARD_TOLERANCE = 1e-6
"""Slack (rad) on the adjustment bound before the guard intervenes (float32 round-off)."""
MAX_GAP = 2.0
"""Control periods between two time-stamped observations beyond which samples were dropped: the step falls back and
the histories start afresh (the fixed-rate loop's ``stale_ticks``: one call late by less than a period is not a gap)."""

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
        dt: control period, s (for the observation jump check, and the period a call without ``t`` stands for).
        max_gap: periods between two time-stamped observations beyond which the step falls back and the histories
            start afresh (> 1; see the module docstring).
    """

    def __init__(
        self,
        act: PolicyCall | None,
        lengths: Sequence[int],
        policy_max_adjust: Sequence[float] | None,
        limits: GuardLimits | None,
        dt: float = DT,
        max_gap: float = MAX_GAP,
    ) -> None:
        if not (isinstance(max_gap, int | float) and math.isfinite(max_gap) and max_gap > 1):
            raise EfficientTrackError(f"runtime: max_gap must be a number of control periods > 1, got {max_gap!r}")
        self._policy_call = act
        self.dt, self.max_gap = float(dt), float(max_gap)
        """The control period, s, and the gap in periods beyond which samples count as dropped."""
        self.history_length, self.future_length = (int(n) for n in lengths)
        """h, F: lengths of the histories kept and of the desired positions ``step`` needs (policy's, or 1 without)."""
        self.limits = DEFAULT_LIMITS if limits is None else limits
        """The limits the guard enforces."""
        self.max_adjust = np.zeros(4) if act is None else self.limits.adjust_bound(policy_max_adjust)
        """(4,) rad, the bound of |a| enforced: the machine's, tightened (never widened) by the policy file's."""
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
        self._t_last: float | None = None  # the last observation's time stamp, s, when it had one

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

    def start(self, obs0: np.ndarray, t: float | None = None) -> None:
        """Begin an episode for N machines: histories filled with ``o_0`` and ``q^r_0 = q_0``, counters zeroed.

        Args:
            obs0: (N, 8) [rad, rad/s], the measured start observations (finite: there is nothing to fall back on yet).
            t: s on a monotonic clock, when ``obs0`` was measured, or None (see ``step``).
        """
        obs0 = np.asarray(obs0, dtype=np.float64)
        if obs0.ndim != 2 or obs0.shape[1] != 8:
            raise EfficientTrackError(f"runtime: start expects obs0 of shape (N, 8), got {obs0.shape}")
        if not np.all(np.isfinite(obs0)):
            raise EfficientTrackError("runtime: non-finite start observation; nothing was sent")
        self._t_last = None if t is None else _checked_time(t, "start")
        n = len(obs0)
        self._history = initial_history(obs0, self.history_length)
        self.fallbacks = np.zeros(n, dtype=np.int64)
        self.counts = {str(flag.name).lower(): np.zeros(n, dtype=np.int64) for flag in Guard}
        self.steps = 0
        self._a_prev = np.zeros((n, 4))
        self._repeats = np.zeros(n, dtype=np.int64)

    def step(self, obs: np.ndarray, q_des_future: np.ndarray, t: float | None = None) -> Sent:
        """One control period: the reference to send for step t+1.

        Without ``t`` the call stands for one control period after the last (``start`` or ``step``). With ``t`` (and a
        stamp on the last call) the guard uses the real time since the last observation: the jump check allows
        ``max_speed`` times it, and more than ``max_gap`` periods (dropped samples) fall back
        (``Guard.OBS_STALE``) and start the histories afresh from ``obs``, as ``start`` does.

        Args:
            obs: (N, 8) [rad, rad/s], the observation ``o_t`` just measured (a non-finite one falls back).
            q_des_future: (N, F', 4) rad, desired positions ``q*_{t+1} … q*_{t+F'}``, F' ≥ ``future_length``
                (padded with the last desired position past the end of the reference). Only ``[:, 0]`` is
                used when there is no policy; it must be finite (there is nothing else to send).
            t: s on a monotonic clock (``time.monotonic()``), when ``obs`` was measured, later than the last call's;
                None: one period after the last call.

        Returns:
            The reference sent (N, 4) rad, the adjustment as sent, the per-machine fallback flags and
            :class:`~efficienttrack.deploy.episodes.Guard` bits.

        Raises:
            EfficientTrackError: called before ``start``, inputs of the wrong shape, a non-finite ``q*_{t+1}``, or a
                ``t`` not finite or not after the last call's; nothing was sent.
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
        periods = self._periods(t)
        guard = self._check_inputs(obs, q_des_future[:, : max(F, 1)], periods)
        gap = periods > self.max_gap  # samples were dropped: a = 0, and the histories start afresh
        guard |= _bits(np.full(n, gap), Guard.OBS_STALE)
        obs = np.where(guard[:, None] & Guard.OBS_NONFINITE, self._history.obs[:, -1], obs)  # keep the last good one
        afresh = (gap | (guard & Guard.OBS_JUMP) != 0)[:, None, None]  # a jump is not one period's motion either
        fresh = initial_history(obs, self.history_length)
        history = History(np.where(afresh, fresh.obs, self._history.obs), np.where(afresh, fresh.q_ref, self._history.q_ref))
        history = push_observation(history, obs)
        a = np.zeros((n, 4))
        if self._policy_call is not None:
            a, policy_guard = self._act(history, np.where(np.isfinite(q_des_future[:, :F]), q_des_future[:, :F], 0.0))
            guard |= policy_guard
        fallback = (guard & FALLBACK) != 0
        a = np.where(fallback[:, None], 0.0, a)
        # rate limit (from the adjustment sent last step; a fallback's a = 0 is not limited)
        limited = self.limits.rate_limit(a, self._a_prev)
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
        self._t_last = t
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

    def _periods(self, t: float | None) -> float:
        """Control periods since the last observation: by the stamps of both, else 1 (checked, not kept)."""
        if t is None:
            return 1.0
        t = _checked_time(t, "step")
        if self._t_last is None:
            return 1.0
        if t <= self._t_last:
            raise EfficientTrackError(
                f"runtime: step at t = {t} s, not after the last call's {self._t_last} s; t must come from a monotonic "
                "clock; nothing was sent"
            )
        return (t - self._t_last) / self.dt

    def _check_inputs(self, obs: np.ndarray, q_des_seen: np.ndarray, periods: float = 1.0) -> np.ndarray:
        """(N,) uint16 Guard bits of the inputs: non-finite, jumping or stale observations, desired positions outside.

        ``periods``: control periods since the last observation (the jump check allows ``max_speed`` for that long).
        """
        assert self._history is not None  # step checks that the runtime was started
        last = self._history.obs[:, -1]
        finite = np.all(np.isfinite(obs), axis=1)
        with np.errstate(invalid="ignore"):
            move = np.abs(obs[:, :4] - last[:, :4])
            move[:, SWING] = np.abs(wrap(move[:, SWING]))
            inexplicable = periods <= self.max_gap and np.any(  # a stamped gap is judged as one (OBS_STALE)
                motion_excess(last, obs, periods * self.dt) > SENSOR_TOLERANCE, axis=1
            )
            jump = finite & (np.any(move > self._max_move * periods, axis=1) | inexplicable)
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


def _checked_time(t: Any, where: str) -> float:
    """``t`` as a finite float, else EfficientTrackError naming the call."""
    if isinstance(t, bool) or not isinstance(t, int | float | np.integer | np.floating) or not math.isfinite(t):
        raise EfficientTrackError(f"runtime: {where} needs t as a finite number of seconds or None, got {t!r}")
    return float(t)


def _bits(hit: np.ndarray, flag: Guard) -> np.ndarray:
    """(N,) uint16: ``flag`` where ``hit`` (N,) bool, else 0."""
    return np.where(hit, np.uint16(flag.value), np.uint16(0))
