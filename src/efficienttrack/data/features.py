"""The network input: histories and targets seen from the current position, one definition for every learner.

EfficientTrack's model and policy (:mod:`efficienttrack.learn`) and the reinforcement-learning baselines
(:mod:`efficienttrack.envs.features`) all see these features, standardized. Works on numpy arrays and torch tensors
alike, so that the torch-free environments compute exactly what the networks compute.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.joints import N_JOINTS

STD_FLOOR = 1e-6
"""Smallest standard deviation used to scale a feature; constant features are only centred."""


def _concatenate(parts: tuple[Any, ...]) -> Any:
    """Flatten each part to (B, −1) and join them along the features, numpy or torch."""
    torch = sys.modules.get("torch")  # not imported here: the environments run without torch
    if torch is not None and isinstance(parts[0], torch.Tensor):
        return torch.cat([p.flatten(1) for p in parts], dim=1)
    return np.concatenate([np.reshape(p, (len(p), -1)) for p in parts], axis=1)


def feature_width(history: int, targets: int) -> int:
    """Width of :func:`relative_features` for histories of length ``history`` and ``targets`` positions ahead.

    Args:
        history: h, length of the observation and reference histories.
        targets: K, positions ahead (1 for the model: ``q^r_{t+1}``; F for the policy: ``q*_F``).

    Returns:
        12h + 4K: ``q_t``, h−1 past positions, h velocities, h references and K targets, 4 joints each.
    """
    return N_JOINTS * (1 + (history - 1) + history + history + targets)


def relative_features(obs_hist: Any, qref_hist: Any, targets: Any, commands: bool = False) -> Any:
    """The network input: histories and targets as seen from the current position, so any machine's offsets drop out.

    Features, in order: the current position ``q_t`` (4), past positions ``wrap(q_{t−k} − q_t)`` (h−1 × 4), velocities
    (h × 4), references ``wrap(q^r_{t−k} − q_t)`` (h × 4) and targets ``wrap(target − q_t)`` (K × 4):
    :func:`feature_width` (h, K) = 12h + 4K values (callers scale them with a
    :class:`~efficienttrack.learn.nets.Standardizer`). In the open loop (``commands``) the second history holds PWM
    commands, which are no angles: they are taken as they are.

    Args:
        obs_hist: (B, h, 8) [rad, rad/s], ``o_{t−h+1} … o_t``; a numpy array or a torch tensor (all three alike).
        qref_hist: (B, h', 4) rad, ``q^r_{t−h'+1} … q^r_t`` (h' = h); with ``commands``, (B, h', 4) PWM / 1000, any h'.
        targets: (B, K, 4) rad, absolute positions ahead (``q^r_{t+1}`` for the model, ``q*_F`` for the policy).
        commands: ``qref_hist`` holds commands (PWM / 1000), not references.

    Returns:
        (B, 8h + 4h' + 4K − 4) features (12h + 4K for h' = h).
    """
    q_t = obs_hist[:, -1:, :4]
    parts = (
        q_t,
        wrap(obs_hist[:, :-1, :4] - q_t),
        obs_hist[:, :, 4:],
        qref_hist if commands else wrap(qref_hist - q_t),
        wrap(targets - q_t),
    )
    return _concatenate(parts)
