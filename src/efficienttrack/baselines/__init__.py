"""Baselines the study compares EfficientTrack with, and the ILC oracle (a lower bound, not a competitor).

PPO and SAC through Stable-Baselines3 (:mod:`.sb3`); iterative learning control on the test references themselves
(:mod:`.ilc`: it sees the test references, so it only says how much error is left to win). Each ``train_<method>``
takes one checked run, :func:`training_run` (:mod:`.curve`), and its settings.

The names load their module when first used, so that the ILC oracle (numpy and scipy) does not import
Stable-Baselines3.
"""

from __future__ import annotations

import importlib
from typing import Any

_HOMES = {
    "CurveRecorder": "curve",
    "TrainingRun": "curve",
    "default_eval_points": "curve",
    "training_run": "curve",
    "ILC_PRESETS": "ilc",
    "ILCSettings": "ilc",
    "train_ilc": "ilc",
    "train_baseline": "sb3",
    "PPO_PRESETS": "settings",
    "PRESETS": "settings",
    "SAC_PRESETS": "settings",
    "PPOSettings": "settings",
    "SACSettings": "settings",
    "method_settings": "settings",
    "SB3VecEnv": "vec_env",
}
"""Public name → the module of this package that defines it."""

__all__ = list(_HOMES)


def __getattr__(name: str) -> Any:
    """The public names, imported from their module on first use."""
    if name not in _HOMES:
        raise AttributeError(f"module 'efficienttrack.baselines' has no attribute '{name}'")
    return getattr(importlib.import_module(f"efficienttrack.baselines.{_HOMES[name]}"), name)
