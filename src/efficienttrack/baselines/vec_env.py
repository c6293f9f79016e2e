"""Stable-Baselines3's ``VecEnv`` over a Gymnasium vector environment that steps one batched system.

SB3 drives N environments through its own ``VecEnv`` interface (``reset() -> obs``, ``step(actions) -> obs, rewards,
dones, infos`` with one info dict per environment). Its ``DummyVecEnv`` would step N single environments one after
another, N simulator calls per step; :class:`SB3VecEnv` instead hands the whole ``(N, 4)`` action batch to a Gymnasium
``VectorEnv`` (:class:`efficienttrack.envs.TrackingVectorEnv`), which steps all N machines in one call of the batched
system. The conventions map directly because the vector environment resets in the same step
(``AutoresetMode.SAME_STEP``): where an episode ends, the observation returned is already the next episode's first,
the last one is in ``infos["final_obs"]`` and becomes SB3's ``infos[i]["terminal_observation"]``, and
``infos[i]["TimeLimit.truncated"]`` says whether the episode was cut (a reference's end is a truncation).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, cast

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn, VecEnvWrapper

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.envs.features import ObservationPipeline

FINAL_KEYS = frozenset({"final_obs", "_final_obs", "final_info", "_final_info"})
"""The keys a SAME_STEP vector environment adds to ``infos`` where an episode ended."""


def env_info(infos: Mapping[str, Any], i: int) -> dict[str, Any]:
    """Environment ``i``'s own info dict out of Gymnasium's batched vector infos.

    Gymnasium batches infos as ``{key: (N,) array, "_key": (N,) bool mask}`` (nested dicts likewise); SB3 wants
    one plain dict per environment.

    Args:
        infos: the vector environment's infos (keys ``"final_obs"``/``"final_info"`` included, if present).
        i: the environment's index in ``[0, N)``.

    Returns:
        The values present for environment ``i`` (masks dropped; nested dicts unbatched the same way).
    """
    out: dict[str, Any] = {}
    for key, value in infos.items():
        mask = infos.get(f"_{key}")
        if key.startswith("_") or (mask is not None and not mask[i]):
            continue
        out[key] = env_info(value, i) if isinstance(value, Mapping) else value[i]
    return out


class SB3VecEnv(VecEnv):
    """SB3's ``VecEnv`` over a Gymnasium ``VectorEnv`` with same-step autoreset: one batched call per step for all N.

    Observations ``(N, *single_observation_space.shape)``, actions ``(N, *single_action_space.shape)``, rewards
    ``(N,)`` float32, dones ``(N,)`` bool (terminated or truncated), one info dict per environment. Where environment
    ``i``'s episode ends, ``obs[i]`` is the next episode's first observation, ``infos[i]`` is the ending step's info
    plus ``"terminal_observation"`` (the last observation of the ended episode), and ``reset_infos[i]`` is the new
    episode's reset info. Every step's ``infos[i]`` holds ``"TimeLimit.truncated"``: the episode was truncated, not
    terminated (False while it runs), as SB3's ``DummyVecEnv`` writes it.

    Seeds set by SB3 (``seed(s)`` gives environment ``i`` the seed ``s + i``) and reset options reach the vector
    environment at the next :meth:`reset`, as one seed per environment.

    Args:
        venv: the vector environment; its ``metadata["autoreset_mode"]`` must be ``AutoresetMode.SAME_STEP``.
    """

    def __init__(self, venv: VectorEnv) -> None:
        mode = venv.metadata.get("autoreset_mode")
        if mode != AutoresetMode.SAME_STEP:
            raise EfficientTrackError(
                f"{type(venv).__name__}: SB3VecEnv needs a vector environment with autoreset mode SAME_STEP, got {mode}"
            )
        self.venv = venv
        space = venv.single_action_space
        self.actions = np.zeros((venv.num_envs, *space.shape), dtype=space.dtype)  # type: ignore[misc]  # a Box: shape is set
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    def reset(self) -> VecEnvObs:
        """Reset every environment, with the seeds and options set since the last reset (then forgotten).

        Returns:
            The first observations, ``(N, *obs_shape)``.
        """
        seeds = None if all(seed is None for seed in self._seeds) else self._seeds
        if any(options != self._options[0] for options in self._options):
            raise EfficientTrackError("SB3VecEnv: reset options must be the same for all environments")
        # Gymnasium's base class annotates one int seed; vector environments take one per environment (a list).
        obs, infos = self.venv.reset(seed=seeds, options=self._options[0] or None)  # type: ignore[arg-type]
        self.reset_infos = [env_info(infos, i) for i in range(self.num_envs)]
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        """Keep the actions for :meth:`step_wait`.

        Args:
            actions: ``(N, *action_shape)``, one action per environment.
        """
        self.actions = np.asarray(actions, dtype=self.action_space.dtype).reshape(self.actions.shape)

    def step_wait(self) -> VecEnvStepReturn:
        """Step all N environments in one call of the vector environment.

        Returns:
            ``(obs (N, *obs_shape), rewards (N,) float32, dones (N,) bool, infos)``, as described in the class docstring.
        """
        obs, rewards, terminated, truncated, infos = self.venv.step(self.actions)
        dones = np.logical_or(terminated, truncated)
        running = {key: value for key, value in infos.items() if key not in FINAL_KEYS}
        out: list[dict[str, Any]] = []
        for i in range(self.num_envs):  # SB3's convention: one info dict per environment
            if dones[i]:
                info = env_info(infos["final_info"], i) if "final_info" in infos else {}
                info["terminal_observation"] = infos["final_obs"][i]
                self.reset_infos[i] = env_info(running, i)
            else:
                info = env_info(running, i)
            info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            out.append(info)
        return obs, np.asarray(rewards, dtype=np.float32), dones, out

    def close(self) -> None:
        """Close the vector environment."""
        self.venv.close()

    def _indices(self, indices: VecEnvIndices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """An attribute of the vector environment, once per environment asked for (they share it).

        Args:
            attr_name: the attribute.
            indices: which environments (all when None).

        Returns:
            The attribute's value, repeated for each index.
        """
        value = getattr(self.venv, attr_name)
        return [value for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set an attribute of the vector environment; only for all environments at once (they share it).

        Args:
            attr_name: the attribute.
            value: its new value.
            indices: must name all environments (or be None).
        """
        if sorted(self._indices(indices)) != list(range(self.num_envs)):
            raise EfficientTrackError(f"SB3VecEnv: '{attr_name}' is shared by all environments; set it for all of them")
        setattr(self.venv, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list[Any]:
        """Call a method of the vector environment once and return its result for each environment asked for.

        Args:
            method_name: the method.
            *method_args: its positional arguments.
            indices: which environments (all when None).
            **method_kwargs: its keyword arguments.

        Returns:
            The result, repeated for each index.
        """
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        """Whether the environments are wrapped with ``wrapper_class``: never (the vector environment is not a wrapper).

        Args:
            wrapper_class: the wrapper asked about.
            indices: which environments (all when None).

        Returns:
            False for each index.
        """
        return [False for _ in self._indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        """No images: the tracking environments do not render.

        Returns:
            None for each environment.
        """
        return [None for _ in range(self.num_envs)]


class FeatureVecEnv(VecEnvWrapper):
    """SB3's view of the environments through an :class:`~efficienttrack.envs.features.ObservationPipeline`.

    Observations, the ``terminal_observation`` of ended episodes included, become the standardized relative features
    (N, D) float32; actions, rewards and dones pass unchanged.

    Args:
        venv: the environments (:class:`SB3VecEnv`).
        pipeline: the observation pipeline (fitted on the training references).
    """

    def __init__(self, venv: VecEnv, pipeline: ObservationPipeline) -> None:
        self.pipeline = pipeline
        space = gym.spaces.Box(-np.inf, np.inf, shape=(pipeline.size,), dtype=np.float32)
        super().__init__(venv, observation_space=space)

    def reset(self) -> VecEnvObs:
        """Reset every environment; return the first features (N, D)."""
        return self.pipeline(cast(np.ndarray, self.venv.reset()))  # Box observations: an array

    def step_wait(self) -> VecEnvStepReturn:
        """Step every environment; return features (N, D), rewards, dones and infos (terminal observations as features)."""
        obs, rewards, dones, infos = self.venv.step_wait()
        for info in infos:
            if "terminal_observation" in info:
                info["terminal_observation"] = self.pipeline(info["terminal_observation"][None])[0]
        return self.pipeline(cast(np.ndarray, obs)), rewards, dones, infos
