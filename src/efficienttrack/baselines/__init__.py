"""Baselines the study compares EfficientTrack with; PPO and SAC through Stable-Baselines3 (:mod:`.sb3`)."""

from efficienttrack.baselines.sb3 import default_eval_points, train_baseline
from efficienttrack.baselines.settings import PPO_PRESETS, PRESETS, SAC_PRESETS, PPOSettings, SACSettings, method_settings
from efficienttrack.baselines.vec_env import SB3VecEnv

__all__ = [
    "PPO_PRESETS",
    "PRESETS",
    "SAC_PRESETS",
    "PPOSettings",
    "SACSettings",
    "SB3VecEnv",
    "default_eval_points",
    "method_settings",
    "train_baseline",
]
