"""The vector environment: N machines on one batched system, one system call per step for all of them.

Equal to N :class:`~efficienttrack.envs.single.TrackingEnv` under ``gymnasium.vector.SyncVectorEnv`` with the same
seeds (``reset(seed=s)`` seeds sub-environment i with ``s + i``, as ``SyncVectorEnv`` does): each sub-environment
draws its references from its own generator. Autoreset mode ``SAME_STEP``: the step at which a sub-environment's
reference ends returns the first observation of its next episode, and the final observation and info go in
``infos["final_obs"]`` / ``infos["final_info"]`` (masks ``_final_obs`` / ``_final_info``), as SB3's ``VecEnv``
expects. The next episode starts on that machine alone (the system's ``reset_machines``) while the others run on.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from efficienttrack.core.errors import EfficientTrackError
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
from efficienttrack.envs.single import RESET_OPTIONS, chosen_reference, spaces_for
from efficienttrack.systems.spec import SystemSpec


class TrackingVectorEnv(VectorEnv):
    """N tracking environments stepping one batched system (closed or open loop; see :class:`TrackingEnv`).

    Observations (N, D) float32, actions (N, 4) in [−1, 1], rewards (N,), terminations always False, truncations
    at each reference's end. ``infos``: ``reference`` (names, object array), ``reference_index``, ``step``,
    ``tracking_error`` (N, 4) rad, each with its ``_key`` mask; for a sub-environment that just ended, those of its
    next episode, and ``final_obs`` / ``final_info`` of the one that ended.

    Args:
        num_envs: N, the sub-environments (machines).
        loop: ``"closed"`` or ``"open"``.
        system: a SystemSpec, or a system's name or ``module:callable`` (default ``xe75``).
        refs: a folder of references, a list of Reference, or None for 8 generated loading cycles (seed 0).
        plant: a PWM-level plant instead of ``system``.
        pd: PD gains for ``plant``.
        system_opts: keyword options of the system's or plant's callable.
        limits: YAML/JSON file amending the system's limits.
        history: h.
        future: F.
        render_mode: must be None.
    """

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(
        self,
        num_envs: int = 16,
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
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise EfficientTrackError(f"num_envs: expected a positive integer, got {num_envs!r}")
        self.num_envs = num_envs
        self.loop = check_loop(loop)
        self.system_spec = make_spec(system, plant, pd, system_opts, limits)
        self.references = resolve_references(refs)
        system_view = open_system(self.loop, self.system_spec)
        if system_view.max_batch is not None and num_envs > system_view.max_batch:
            raise EfficientTrackError(
                f"{system_view.name}: takes single machines only; use gymnasium.vector.SyncVectorEnv over TrackingEnv"
            )
        if num_envs > 1 and not system_view.resets_machines:
            raise EfficientTrackError(
                f"{system_view.name}: cannot start one machine's episode while the others run (no 'reset_machines'); "
                "add it, or use gymnasium.vector.SyncVectorEnv over TrackingEnv"
            )
        self.episodes = Episodes(system_view, self.loop, self.references, history, future)
        self.single_observation_space, self.single_action_space = spaces_for(self.episodes.size)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._rngs = [seeding.np_random()[0] for _ in range(num_envs)]

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start N episodes.

        Args:
            seed: an int (sub-environment i gets ``seed + i``), N seeds, or None (keep the generators' streams).
            options: ``{"reference": index, name or N of them}`` to choose the references.

        Returns:
            Observations (N, D) float32 and the infos.
        """
        seeds = self._seeds(seed)
        if seed is not None:
            super().reset(seed=seeds[0])
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        options = dict(options or {})
        unknown = sorted(set(options) - set(RESET_OPTIONS))
        if unknown:
            raise EfficientTrackError(f"reset options: unknown key(s) {unknown} (known: {list(RESET_OPTIONS)})")
        choice = options.get("reference")
        if choice is None or isinstance(choice, str | int | np.integer):
            per_env = [None if choice is None else {"reference": choice}] * self.num_envs
        elif isinstance(choice, Sequence | np.ndarray) and len(choice) == self.num_envs:
            per_env = [{"reference": c} for c in choice]
        else:
            raise EfficientTrackError(f"reset options: 'reference' needs one entry per sub-environment ({self.num_envs})")
        k = np.array([chosen_reference(o, self.references, rng) for o, rng in zip(per_env, self._rngs, strict=True)])
        obs = self.episodes.start(k)
        return obs, self._infos(self.episodes.error())

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One control period for all N (one system call); sub-environments whose reference ended start their next.

        Args:
            actions: (N, 4) in [−1, 1] (clipped into it).

        Returns:
            Observations (N, D) float32, rewards (N,) float64, terminations (N,) bool (all False), truncations
            (N,) bool, infos.
        """
        result = self.episodes.step(check_actions(actions, self.num_envs))
        truncated = result.truncated
        obs = result.obs
        infos = self._infos(result.error)
        if truncated.any():
            ended = np.flatnonzero(truncated)
            final_obs = np.full(self.num_envs, None, dtype=object)
            for i in ended:
                final_obs[i] = obs[i].copy()
            infos["final_obs"], infos["_final_obs"] = final_obs, truncated.copy()
            infos["final_info"] = {key: value for key, value in infos.items() if not key.startswith(("final", "_final"))}
            infos["final_info"].update({key: truncated.copy() for key in infos["final_info"] if key.startswith("_")})
            infos["_final_info"] = truncated.copy()
            k = np.array([self._rngs[i].integers(len(self.references)) for i in ended])
            obs = self.episodes.restart(ended, k)
            infos.update(self._infos(self.episodes.error()))
        return obs, result.reward, np.zeros(self.num_envs, dtype=bool), truncated, infos

    def _seeds(self, seed: int | Sequence[int | None] | None) -> list[int | None]:
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, int | np.integer):
            return [int(seed) + i for i in range(self.num_envs)]
        seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise EfficientTrackError(f"reset: seed needs one entry per sub-environment ({self.num_envs}), got {len(seeds)}")
        return seeds

    def _infos(self, error: np.ndarray) -> dict[str, Any]:
        """The vector infos, every key with its all-true ``_key`` mask."""
        everyone = np.ones(self.num_envs, dtype=bool)
        names = np.array([self.references[k].name for k in self.episodes.k], dtype=object)
        values = {
            "reference": names,
            "reference_index": self.episodes.k.copy(),
            "step": self.episodes.t.copy(),
            "tracking_error": error.copy(),
        }
        infos: dict[str, Any] = {}
        for key, value in values.items():
            infos[key], infos[f"_{key}"] = value, everyone.copy()
        return infos
