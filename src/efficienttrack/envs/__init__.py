"""Gymnasium environments over any system: the closed loop (adjust the PD reference) and the open loop (send PWM).

Importing this package registers :data:`CLOSED_LOOP_ID` and :data:`OPEN_LOOP_ID` (``import efficienttrack`` has it
imported once Gymnasium is), so ``gymnasium.make(CLOSED_LOOP_ID, system="xe75", refs=DIR)`` and
``gymnasium.make_vec(CLOSED_LOOP_ID, num_envs=16, ...)`` (the native :class:`TrackingVectorEnv`, one batched system
call per step) work. The observation,
action and reward are defined in :mod:`efficienttrack.envs.core` and tabled in ``docs/envs.md``; :func:`evaluate`
runs a trained agent on held-out references as records that :func:`efficienttrack.data.metrics.compute_metrics` scores.

Only the ids and the registration are imported with this package; the other names load their module when first
used.
"""

from __future__ import annotations

import importlib
from typing import Any

from efficienttrack.envs.registration import CLOSED_LOOP_ID, OPEN_LOOP_ID, register_envs

_HOMES = {
    "FUTURE": "core",
    "HISTORY": "core",
    "LOOPS": "core",
    "observation_size": "core",
    "reward": "core",
    "evaluate": "evaluation",
    "ClosedLoopEnv": "single",
    "OpenLoopEnv": "single",
    "TrackingEnv": "single",
    "TrackingVectorEnv": "vector",
}
"""Public name → the module of this package that defines it."""

__all__ = ["CLOSED_LOOP_ID", "OPEN_LOOP_ID", "register_envs", *_HOMES]

register_envs()


def __getattr__(name: str) -> Any:
    """The public names other than the ids, imported from their module on first use."""
    if name not in _HOMES:
        raise AttributeError(f"module 'efficienttrack.envs' has no attribute '{name}'")
    return getattr(importlib.import_module(f"efficienttrack.envs.{_HOMES[name]}"), name)
