"""The single Gymnasium environment: one machine tracking one reference per episode (see :mod:`efficienttrack.envs.core`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import N_JOINTS
from efficienttrack.data.references import Reference
from efficienttrack.envs.core import (
    FUTURE,
    HISTORY,
    Episodes,
    RefsArg,
    check_actions,
    check_loop,
    make_spec,
    open_system,
    resolve_references,
)
from efficienttrack.systems.spec import SystemSpec

RESET_OPTIONS = ("reference",)
"""The keys ``reset(options=...)`` takes."""


def spaces_for(size: int) -> tuple[spaces.Box, spaces.Box]:
    """The observation and action space of one environment.

    Args:
        size: D, the observation's length (332 for the paper's h and F).

    Returns:
        Box(−inf, inf, (D,), float32) and Box(−1, 1, (4,), float32).
    """
    return (
        spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float32),
        spaces.Box(-1.0, 1.0, shape=(N_JOINTS,), dtype=np.float32),
    )


def chosen_reference(options: Mapping[str, Any] | None, refs: list[Reference], rng: np.random.Generator) -> int:
    """The reference an episode tracks: ``options["reference"]`` (index or name) or one drawn with ``rng``.

    Args:
        options: the reset options, or None.
        refs: the environment's references.
        rng: the environment's ``np_random``.

    Returns:
        The index into ``refs``.
    """
    options = dict(options or {})
    unknown = sorted(set(options) - set(RESET_OPTIONS))
    if unknown:
        raise EfficientTrackError(f"reset options: unknown key(s) {unknown} (known: {list(RESET_OPTIONS)})")
    if "reference" not in options:
        return int(rng.integers(len(refs)))
    choice = options["reference"]
    if isinstance(choice, str):
        names = [ref.name for ref in refs]
        if choice not in names:
            raise EfficientTrackError(f"reset options: no reference named '{choice}'")
        return names.index(choice)
    if isinstance(choice, int | np.integer) and not isinstance(choice, bool) and 0 <= choice < len(refs):
        return int(choice)
    raise EfficientTrackError(f"reset options: 'reference' must be a name or an index 0 … {len(refs) - 1}, got {choice!r}")


def step_info(refs: list[Reference], k: np.ndarray, t: np.ndarray, error: np.ndarray, i: int) -> dict[str, Any]:
    """The info of machine i: reference name and index, step, tracking error (4,) rad.

    Args:
        refs: the references.
        k: (N,) the reference of each episode.
        t: (N,) the step each episode is at.
        error: (N, 4) rad, ``wrap(q_t − q*_t)``.
        i: the machine.
    """
    return {"reference": refs[k[i]].name, "reference_index": int(k[i]), "step": int(t[i]), "tracking_error": error[i].copy()}


class TrackingEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """Track a reference with a machine: closed loop (adjust the PD controller's reference) or open loop (send PWM).

    Observation (332,) float32, action (4,) in [−1, 1], reward: see :mod:`efficienttrack.envs.core` and
    ``docs/envs.md``. One episode is one reference, chosen with ``np_random`` at ``reset`` or by
    ``options={"reference": index_or_name}``; it ends truncated at the reference's end (L − 1 steps), never terminated.
    ``info``: ``reference`` (name), ``reference_index``, ``step`` (t after the step), ``tracking_error`` (4,) rad,
    ``wrap(q_t − q*_t)``.

    Args:
        loop: ``"closed"`` or ``"open"``.
        system: a :class:`~efficienttrack.systems.spec.SystemSpec`, or a system's name or ``module:callable``
            (default ``xe75``); the open loop uses its PWM-level plant.
        refs: a folder of references, a list of :class:`~efficienttrack.data.references.Reference`, or None for 8
            generated loading cycles (:func:`~efficienttrack.data.cycles.generate_references`, seed 0).
        plant: a PWM-level plant instead of ``system`` (closed with ``pd`` for the closed loop).
        pd: PD gains for ``plant``: a preset name or a JSON file.
        system_opts: keyword options of the system's or plant's callable.
        limits: YAML/JSON file amending the system's limits (joint limits, ``max_adjust``).
        history: h, observations and references (actions) seen.
        future: F, desired positions ahead seen.
        render_mode: must be None (nothing is rendered).
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        loop: str = "closed",
        system: str | SystemSpec | None = None,
        refs: RefsArg = None,
        *,
        plant: str | None = None,
        pd: str | None = None,
        system_opts: Mapping[str, Any] | None = None,
        limits: str | None = None,
        history: int = HISTORY,
        future: int = FUTURE,
        render_mode: str | None = None,
    ) -> None:
        if render_mode is not None:
            raise EfficientTrackError(f"render_mode: the tracking environments render nothing, got {render_mode!r}")
        self.loop = check_loop(loop)
        self.system_spec = make_spec(system, plant, pd, system_opts, limits)
        """The system stepped (``spec`` is Gymnasium's registration record)."""
        self.references = resolve_references(refs)
        self.episodes = Episodes(open_system(self.loop, self.system_spec), self.loop, self.references, history, future)
        self.observation_space, self.action_space = spaces_for(self.episodes.size)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode.

        Args:
            seed: seeds ``np_random`` (the reference drawn); None keeps its stream.
            options: ``{"reference": index or name}`` to choose the reference.

        Returns:
            The first observation (D,) float32 and the info.
        """
        super().reset(seed=seed)
        k = chosen_reference(options, self.references, self.np_random)
        obs = self.episodes.start(np.array([k]))
        return obs[0], step_info(self.references, self.episodes.k, self.episodes.t, self.episodes.error(), 0)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """One control period (50 ms).

        Args:
            action: (4,) in [−1, 1] (clipped into it).

        Returns:
            Observation (D,) float32, reward, terminated (always False), truncated (the reference ended), info.
        """
        if np.shape(action) != (N_JOINTS,):
            raise EfficientTrackError(f"action: expected shape (4,) [boom, arm, bucket, swing], got {np.shape(action)}")
        result = self.episodes.step(check_actions(np.reshape(action, (1, N_JOINTS)), 1))
        info = step_info(self.references, self.episodes.k, self.episodes.t, result.error, 0)
        return result.obs[0], float(result.reward[0]), False, bool(result.truncated[0]), info


class ClosedLoopEnv(TrackingEnv):
    """``EfficientTrack/ClosedLoop-v0``: :class:`TrackingEnv` with ``loop="closed"``.

    Args:
        system: a SystemSpec or a reference-level system's name (default ``xe75``).
        refs: a folder or list of references; None: 8 generated cycles.
        **kwargs: the other keyword arguments of :class:`TrackingEnv`.
    """

    def __init__(self, system: str | SystemSpec | None = None, refs: RefsArg = None, **kwargs: Any) -> None:
        super().__init__("closed", system, refs, **kwargs)


class OpenLoopEnv(TrackingEnv):
    """``EfficientTrack/OpenLoop-v0``: :class:`TrackingEnv` with ``loop="open"``.

    Args:
        system: a SystemSpec or a system's name with a built-in plant (default ``xe75``); or give ``plant=``.
        refs: a folder or list of references; None: 8 generated cycles.
        **kwargs: the other keyword arguments of :class:`TrackingEnv`.
    """

    def __init__(self, system: str | SystemSpec | None = None, refs: RefsArg = None, **kwargs: Any) -> None:
        super().__init__("open", system, refs, **kwargs)
