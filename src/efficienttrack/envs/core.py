"""What the environments share, without gymnasium: the paper's observation, the action, the reward, N episodes at once.

One episode tracks one reference q*_0 … q*_{L−1} (L − 1 steps, as :func:`efficienttrack.deploy.episodes.rollout` runs it).
At step t the agent sees (N machines at once, float32):

========= =========== ============================ ==============================================================
part      shape       unit                         meaning
========= =========== ============================ ==============================================================
o_H       (h, 8)      [rad, rad/s]                 ``o_{t−h+1} … o_t``, the measured (q, q̇), oldest first
q^r_H     (h, 4)      rad (closed) / 1 (open)      closed: the references sent ``q^r_{t−h+1} … q^r_t``;
                                                   open: the last actions ``a_{t−h} … a_{t−1}``
q*_F      (F, 4)      rad                          the desired positions ``q*_{t+1} … q*_{t+F}``
========= =========== ============================ ==============================================================

flattened in that order (h = 21, F = 20: 168 + 84 + 80 = 332 values). At an episode start the histories are padded
as training pads them (:func:`efficienttrack.data.windows.initial_history`: ``[o_0]·h``, ``[q_0]·h``; the open loop's
action history with zeros) and ``q*_F`` past the reference's end with its last desired position
(:func:`efficienttrack.data.windows.pad_time_major`).

The action a_t ∈ [−1, 1]⁴ (joints boom, arm, bucket, swing; clipped into it):

- closed loop: the reference sent is ``q^r_{t+1} = clamp(q*_{t+1} + a_t · max_adjust)``, ``max_adjust`` the
  system's per-joint adjustment bound (``limits.max_adjust``, rad) and ``clamp`` its joint limits, exactly as the
  runtime guard clamps (:meth:`~efficienttrack.systems.limits.GuardLimits.clamp`);
- open loop: the PWM sent to the plant is ``u_t = 1000 · a_t``.

The reward (rad): ``r_t = 5 (0.1 − RMS_j wrap(q_{t+1} − q*_{t+1})) + 5 (0.1 − RMS_j(Δa_t))`` with ``Δa_t`` the change of
the adjustment in rad (closed loop: ``(a_t − a_{t−1}) · max_adjust``) or of the action (open loop: ``a_t − a_{t−1}``),
``a_{−1} = 0``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import ENV_FUTURE, MAX_HORIZON, N_JOINTS, OBS_DIM, PWM_SCALE
from efficienttrack.data.cycles import generate_references
from efficienttrack.data.references import Reference, load_references
from efficienttrack.data.windows import History, initial_history, pad_time_major, push_observation, push_reference
from efficienttrack.systems.limits import GuardLimits
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import SystemSpec

LOOPS = ("closed", "open")
"""The two loops: ``closed`` (the policy adjusts the PD controller's reference) and ``open`` (the policy sends PWM)."""
HISTORY = 21
"""h of the baselines' observation, the past observations and references (or actions) the agent sees: 21, as in the
research code's comparison (its 332-value observation). EfficientTrack's own networks see ``PolicyConfig.horizon`` (the
paper's h = 20) and ``ModelConfig.history_length``."""
FUTURE = ENV_FUTURE
"""F, the desired positions ahead the agent sees, as in the paper."""
REWARD_WEIGHT = 5.0
"""Weight of each reward term."""
REWARD_OFFSET = 0.1
"""Offset of each reward term, rad: a term is positive while its RMS stays below it."""
DEFAULT_REFERENCES = 8
"""How many cycles :func:`resolve_references` generates (seed 0) when no references are given."""

RefsArg = str | Path | Sequence[Reference] | None
"""References as the environments take them: a folder (or file) of references, a list of them, or None."""


def observation_size(history: int = HISTORY, future: int = FUTURE) -> int:
    """Length of the flat observation: h·8 + h·4 + F·4 (332 for the paper's h = 21, F = 20).

    Args:
        history: h.
        future: F.
    """
    return history * (OBS_DIM + N_JOINTS) + future * N_JOINTS


def check_loop(loop: object) -> str:
    """``loop`` if it is ``"closed"`` or ``"open"``; an error naming it otherwise.

    Args:
        loop: the loop asked for.
    """
    if loop not in LOOPS:
        raise EfficientTrackError(f"loop: unknown loop {loop!r} (use 'closed' or 'open')")
    return str(loop)


def make_spec(
    system: str | SystemSpec | None = None,
    plant: str | None = None,
    pd: str | None = None,
    system_opts: Mapping[str, Any] | None = None,
    limits: str | None = None,
) -> SystemSpec:
    """The :class:`SystemSpec` the keyword arguments of the environments name.

    Args:
        system: a :class:`SystemSpec`, or a reference-level system's built-in name or ``module:callable``; None: the
            default (``xe75``) unless ``plant`` is given.
        plant: a PWM-level plant's built-in name or ``module:callable`` (closed with ``pd`` for the closed loop).
        pd: PD gains for ``plant``: a preset name or a JSON file.
        system_opts: keyword options of the system's or plant's callable.
        limits: YAML/JSON file of the guard's limits, amending the system's own.

    Returns:
        The spec.
    """
    if isinstance(system, SystemSpec):
        if plant is not None or system_opts or limits is not None:
            raise EfficientTrackError("system: give a SystemSpec or plant=/system_opts=/limits=, not both")
        return system
    if system is not None and not isinstance(system, str):
        raise EfficientTrackError(f"system: expected a name, 'module:callable' or a SystemSpec, got {type(system).__name__}")
    options = tuple(sorted(dict(system_opts or {}).items()))
    return SystemSpec(system=system, plant=plant, pd=pd, options=options, limits=limits)


def open_system(loop: str, spec: SystemSpec) -> BatchedSystem:
    """The system an environment steps: the closed loop (``spec.open()``) or the PWM-level plant (``spec.open_plant()``).

    Args:
        loop: ``"closed"`` or ``"open"``.
        spec: the system spec.

    Returns:
        The checked, batched view.
    """
    if check_loop(loop) == "closed":
        return spec.open()
    plant = spec.open_plant()
    if plant is None:
        raise EfficientTrackError(
            f"open loop: system '{spec.system_name}' has no PWM-level plant; "
            "give plant= (a built-in name or 'module:callable')"
        )
    if spec.limits is not None:
        plant.limits = GuardLimits.load(spec.limits, base=plant.limits)
    return plant


def check_lengths(history: int, future: int) -> None:
    """Refuse an h or F outside 1 … :data:`~efficienttrack.core.joints.MAX_HORIZON`, before anything is allocated.

    Args:
        history: h.
        future: F.
    """
    if not (1 <= history <= MAX_HORIZON and 1 <= future <= MAX_HORIZON):
        raise EfficientTrackError(f"history and future must be 1 to {MAX_HORIZON} steps, got {history} and {future}")


def resolve_references(refs: RefsArg) -> list[Reference]:
    """The references of an environment.

    Args:
        refs: a folder or file of references (:func:`~efficienttrack.data.references.load_references`), a list of
            :class:`~efficienttrack.data.references.Reference`, or None for :data:`DEFAULT_REFERENCES` generated
            loading cycles (:func:`~efficienttrack.data.cycles.generate_references`, seed 0).

    Returns:
        At least one reference.
    """
    if refs is None:
        return generate_references(DEFAULT_REFERENCES, seed=0)
    if isinstance(refs, str | Path):
        return load_references(refs)
    if not isinstance(refs, Iterable):
        raise EfficientTrackError(f"refs: expected a folder or a list of Reference, got {type(refs).__name__}")
    refs = list(refs)
    if not refs:
        raise EfficientTrackError("refs: no references given")
    bad = [type(r).__name__ for r in refs if not isinstance(r, Reference)]
    if bad:
        raise EfficientTrackError(f"refs: expected a folder or a list of Reference, got a list holding {bad[0]}")
    return refs


def observe(history: History, q_des_future: np.ndarray) -> np.ndarray:
    """The flat observation of N machines.

    Args:
        history: ``obs`` (N, h, 8) [rad, rad/s] and ``q_ref`` (N, h, 4) (references sent, rad, or the last actions).
        q_des_future: (N, F, 4) rad, ``q*_{t+1} … q*_{t+F}``.

    Returns:
        (N, h·8 + h·4 + F·4) float32.
    """
    n = len(q_des_future)
    return np.concatenate(
        [history.obs.reshape(n, -1), history.q_ref.reshape(n, -1), np.reshape(q_des_future, (n, -1))], axis=1
    ).astype(np.float32)


def reward(error: np.ndarray, change: np.ndarray) -> np.ndarray:
    """The reward of N machines, ``5 (0.1 − RMS_j(error)) + 5 (0.1 − RMS_j(change))``.

    Args:
        error: (N, 4) rad, the wrapped tracking error ``q_{t+1} − q*_{t+1}``.
        change: (N, 4), the change of the adjustment (closed loop, rad) or of the action (open loop).

    Returns:
        (N,) float64.
    """
    rms_e = np.sqrt(np.mean(np.square(error), axis=-1))
    rms_a = np.sqrt(np.mean(np.square(change), axis=-1))
    return REWARD_WEIGHT * (REWARD_OFFSET - rms_e) + REWARD_WEIGHT * (REWARD_OFFSET - rms_a)


def check_actions(actions: object, n: int) -> np.ndarray:
    """Actions of N machines as float64, clipped into [−1, 1]; an error for a wrong shape or a non-finite value.

    Args:
        actions: (N, 4) actions (anything ``np.asarray`` takes).
        n: N.

    Returns:
        (N, 4) float64 in [−1, 1].
    """
    try:
        a = np.asarray(actions, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise EfficientTrackError(f"action: expected ({n}, 4) numbers, got {type(actions).__name__}") from exc
    if a.shape != (n, N_JOINTS):
        raise EfficientTrackError(f"action: expected shape ({n}, 4) [boom, arm, bucket, swing], got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise EfficientTrackError("action: NaN or inf")
    return np.clip(a, -1.0, 1.0)


class Command(NamedTuple):
    """What an action makes of one step for N machines.

    Attributes:
        sent: (N, 4), what the system is stepped with: the reference ``q^r_{t+1}`` rad (closed) or PWM (open).
        remembered: (N, 4), what the q^r history keeps: the reference sent (closed) or the action (open).
        adjustment: (N, 4), the action in the reward's units: ``a · max_adjust`` rad (closed) or ``a`` (open).
    """

    sent: np.ndarray
    remembered: np.ndarray
    adjustment: np.ndarray


class ActionMap:
    """How an action becomes what the system is stepped with, for one loop and one system.

    Args:
        loop: ``"closed"`` or ``"open"``.
        system: the system stepped (its ``limits``: ``max_adjust`` and the joint limits).
    """

    def __init__(self, loop: str, system: BatchedSystem) -> None:
        self.loop = check_loop(loop)
        self.limits = system.limits
        self.max_adjust = np.asarray(self.limits.max_adjust, dtype=np.float64)
        """(4,) rad, the closed loop's adjustment for a = ±1."""

    def command(self, a: np.ndarray, q_next: np.ndarray) -> Command:
        """The step's command.

        Args:
            a: (N, 4) actions in [−1, 1].
            q_next: (N, 4) rad, the desired positions ``q*_{t+1}``.

        Returns:
            The command.
        """
        if self.loop == "open":
            return Command(sent=PWM_SCALE * a, remembered=a, adjustment=a)
        adjustment = a * self.max_adjust
        q_ref = self.limits.clamp(q_next + adjustment)
        return Command(sent=q_ref, remembered=q_ref, adjustment=adjustment)

    def start_history(self, obs0: np.ndarray, history: int) -> History:
        """The histories at an episode start, padded as training pads them (the open loop's actions with zeros).

        Args:
            obs0: (N, 8) [rad, rad/s], the start observations.
            history: h.

        Returns:
            obs (N, h, 8), q_ref (N, h, 4).
        """
        start = initial_history(obs0, history)
        return start if self.loop == "closed" else History(obs=start.obs, q_ref=np.zeros_like(start.q_ref))

    def change(self, adjustment: np.ndarray, previous: np.ndarray) -> np.ndarray:
        """(N, 4), the change of the adjustment the reward sees (closed loop: an angle difference, wrapped).

        Args:
            adjustment: (N, 4), this step's (:attr:`Command.adjustment`).
            previous: (N, 4), the last step's (zeros at an episode start).
        """
        change = adjustment - previous
        return wrap(change) if self.loop == "closed" else change


class StepResult(NamedTuple):
    """One step of N episodes.

    Attributes:
        obs: (N, D) float32, the observations after the step (those of the episodes that ended: their final ones).
        reward: (N,) float64.
        truncated: (N,) bool, the episode reached the end of its reference.
        error: (N, 4) rad, ``wrap(q_{t+1} − q*_{t+1})``.
    """

    obs: np.ndarray
    reward: np.ndarray
    truncated: np.ndarray
    error: np.ndarray


class Episodes:
    """N episodes at once on one batched system: the state machine under the single and the vector environment.

    Args:
        system: the system stepped (the closed loop, or the plant for the open loop), N machines at once.
        loop: ``"closed"`` or ``"open"``.
        refs: the references (at least one); episode i tracks ``refs[k_i]``.
        history: h.
        future: F.
    """

    def __init__(self, system: BatchedSystem, loop: str, refs: Sequence[Reference], history: int, future: int) -> None:
        check_lengths(history, future)
        self.system = system
        self.actions = ActionMap(loop, system)
        self.refs = list(refs)
        if self.actions.loop == "closed":
            for ref in self.refs:
                system.limits.check_reference(ref.q, ref.name)
        self.history_length, self.future_length = history, future
        self.table = pad_time_major([ref.q for ref in self.refs], future + 1)
        """(L_max + F + 1, R, 4) rad, every reference time-major, padded with its last desired position."""
        self.steps = np.array([ref.steps for ref in self.refs], dtype=np.int64)
        """(R,) steps of each reference's episode, L − 1."""
        self.k = np.zeros(0, dtype=np.int64)
        """(N,) the reference of each episode."""
        self.t = np.zeros(0, dtype=np.int64)
        """(N,) the step each episode is at."""
        self.history: History | None = None
        self._previous = np.zeros((0, N_JOINTS))

    @property
    def size(self) -> int:
        """D, the length of one observation."""
        return observation_size(self.history_length, self.future_length)

    def future(self) -> np.ndarray:
        """(N, F, 4) rad, each episode's ``q*_{t+1} … q*_{t+F}``."""
        rows = self.t[:, None] + 1 + np.arange(self.future_length)[None, :]
        return self.table[rows, self.k[:, None]]

    def error(self) -> np.ndarray:
        """(N, 4) rad, each episode's tracking error now, ``wrap(q_t − q*_t)``."""
        assert self.history is not None, "error called before start"
        return wrap(self.history.obs[:, -1, :N_JOINTS] - self.table[self.t, self.k])

    def observation(self) -> np.ndarray:
        """(N, D) float32, the current observations."""
        assert self.history is not None, "observation called before start"
        return observe(self.history, self.future())

    def start(self, k: np.ndarray) -> np.ndarray:
        """Start N episodes (a reset of the whole batch).

        Args:
            k: (N,) int, the reference of each.

        Returns:
            (N, D) float32, the first observations.
        """
        self.k = self._check_k(k)
        self.t = np.zeros(len(self.k), dtype=np.int64)
        obs0 = self.system.reset(self.table[0, self.k])
        self.history = self.actions.start_history(obs0, self.history_length)
        self._previous = np.zeros((len(self.k), N_JOINTS))
        return self.observation()

    def restart(self, index: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Start new episodes on some machines while the others run on.

        Args:
            index: (K,) int, the machines.
            k: (K,) int, their references.

        Returns:
            (N, D) float32, the observations of all N (the restarted ones their first).
        """
        k = self._check_k(k)
        obs0 = self.system.reset_machines(index, self.table[0, k])
        self.k, self.t = self.k.copy(), self.t.copy()
        self.k[index], self.t[index] = k, 0
        fresh = self.actions.start_history(obs0, self.history_length)
        assert self.history is not None, "restart called before start"
        obs_hist, q_hist = self.history.obs.copy(), self.history.q_ref.copy()
        obs_hist[index], q_hist[index] = fresh.obs, fresh.q_ref
        self.history = History(obs=obs_hist, q_ref=q_hist)
        self._previous = self._previous.copy()
        self._previous[index] = 0.0
        return self.observation()

    def step(self, actions: np.ndarray) -> StepResult:
        """Step every episode (one call of the system for all N).

        Args:
            actions: (N, 4) in [−1, 1] (:func:`check_actions`).

        Returns:
            The observations, rewards, truncations and tracking errors.
        """
        if self.history is None:
            raise EfficientTrackError("step called before reset")
        if np.any(self.t >= self.steps[self.k]):
            raise EfficientTrackError("step called after an episode ended (truncated); call reset first")
        q_next = self.table[self.t + 1, self.k]
        command = self.actions.command(actions, q_next)
        obs = self.system.step(command.sent)
        self.history = push_observation(push_reference(self.history, command.remembered), obs)
        self.t = self.t + 1
        error = wrap(obs[:, :N_JOINTS] - q_next)
        r = reward(error, self.actions.change(command.adjustment, self._previous))
        self._previous = command.adjustment
        return StepResult(obs=self.observation(), reward=r, truncated=self.t >= self.steps[self.k], error=error)

    def _check_k(self, k: object) -> np.ndarray:
        k = np.asarray(k)
        if k.dtype.kind not in "iu" or np.any((k < 0) | (k >= len(self.refs))):
            raise EfficientTrackError(f"reference: expected indices 0 … {len(self.refs) - 1}, got {k.tolist()}")
        return k.astype(np.int64)
