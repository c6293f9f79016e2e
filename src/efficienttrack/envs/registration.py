"""The environments' Gymnasium ids and their registration (imports nothing of ours until an environment is made)."""

from __future__ import annotations

from typing import Any

from gymnasium.envs.registration import register, registry

CLOSED_LOOP_ID = "EfficientTrack/ClosedLoop-v0"
"""The closed loop: the action adjusts the PD controller's reference (:class:`~efficienttrack.envs.single.ClosedLoopEnv`)."""
OPEN_LOOP_ID = "EfficientTrack/OpenLoop-v0"
"""The open loop: the action is PWM / 1000 (:class:`~efficienttrack.envs.single.OpenLoopEnv`)."""


def closed_loop_vector_env(num_envs: int = 16, **kwargs: Any) -> Any:
    """``gymnasium.make_vec(CLOSED_LOOP_ID, num_envs=N, ...)``: a closed-loop :class:`TrackingVectorEnv`.

    Args:
        num_envs: N.
        **kwargs: the keyword arguments of :class:`~efficienttrack.envs.vector.TrackingVectorEnv`.
    """
    from efficienttrack.envs.vector import TrackingVectorEnv

    return TrackingVectorEnv(num_envs, "closed", **kwargs)


def open_loop_vector_env(num_envs: int = 16, **kwargs: Any) -> Any:
    """``gymnasium.make_vec(OPEN_LOOP_ID, num_envs=N, ...)``: an open-loop :class:`TrackingVectorEnv`.

    Args:
        num_envs: N.
        **kwargs: the keyword arguments of :class:`~efficienttrack.envs.vector.TrackingVectorEnv`.
    """
    from efficienttrack.envs.vector import TrackingVectorEnv

    return TrackingVectorEnv(num_envs, "open", **kwargs)


def register_envs() -> None:
    """Register both ids with Gymnasium (single and vector entry points); registering again changes nothing."""
    for env_id, single, vector in (
        (CLOSED_LOOP_ID, "efficienttrack.envs.single:ClosedLoopEnv", closed_loop_vector_env),
        (OPEN_LOOP_ID, "efficienttrack.envs.single:OpenLoopEnv", open_loop_vector_env),
    ):
        if env_id not in registry:
            register(id=env_id, entry_point=single, vector_entry_point=vector, disable_env_checker=False)
