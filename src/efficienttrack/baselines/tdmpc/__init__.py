"""TD-MPC (Hansen, Wang and Su 2022) written compactly for the tracking environments: TOLD, the planner, replay.

:func:`train_tdmpc` has the shape of :func:`efficienttrack.baselines.sb3.train_baseline` without the method argument.
See docs/tdmpc.md.
"""

from efficienttrack.baselines.tdmpc.buffer import PrioritizedBuffer, Sequences
from efficienttrack.baselines.tdmpc.learner import Learner, UpdateInfo
from efficienttrack.baselines.tdmpc.networks import TOLD
from efficienttrack.baselines.tdmpc.planner import LatentModel, Plan, PlannerConfig, estimate_value, plan
from efficienttrack.baselines.tdmpc.settings import PRESETS, TDMPCSettings, tdmpc_settings
from efficienttrack.baselines.tdmpc.train import train_tdmpc

__all__ = [
    "PRESETS",
    "LatentModel",
    "Learner",
    "Plan",
    "PlannerConfig",
    "PrioritizedBuffer",
    "Sequences",
    "TDMPCSettings",
    "TOLD",
    "UpdateInfo",
    "estimate_value",
    "plan",
    "tdmpc_settings",
    "train_tdmpc",
]
