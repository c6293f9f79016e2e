"""Baselines the study compares EfficientTrack with, and the ILC oracle (a lower bound, not a competitor).

PPO and SAC through Stable-Baselines3 (:mod:`.sb3`); iterative learning control on the test references themselves
(:mod:`.ilc`: it sees the test references, so it only says how much error is left to win).
"""

from efficienttrack.baselines.curve import CurveRecorder, default_eval_points
from efficienttrack.baselines.ilc import ILC_PRESETS, ILCSettings, train_ilc
from efficienttrack.baselines.sb3 import train_baseline
from efficienttrack.baselines.settings import PPO_PRESETS, PRESETS, SAC_PRESETS, PPOSettings, SACSettings, method_settings
from efficienttrack.baselines.vec_env import SB3VecEnv

__all__ = [
    "CurveRecorder",
    "ILCSettings",
    "ILC_PRESETS",
    "PPO_PRESETS",
    "PRESETS",
    "SAC_PRESETS",
    "PPOSettings",
    "SACSettings",
    "SB3VecEnv",
    "default_eval_points",
    "method_settings",
    "train_baseline",
    "train_ilc",
]
