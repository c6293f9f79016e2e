"""The single definition of angle wrapping (every angle difference in the package goes through it), and of a pose as text."""

from __future__ import annotations

import math
import sys

import numpy as np

from efficienttrack.core.errors import EfficientTrackError


def wrap(angle):
    """Wrap angles (rad) to (-π, π].

    Args:
        angle: numpy array, torch tensor or float, any shape, rad.

    Returns:
        The same kind and shape (a float becomes a 0-d numpy float), each value in (-π, π].
    """
    torch = sys.modules.get("torch")  # not imported here: the torch-free runtime wraps angles too
    if torch is not None and isinstance(angle, torch.Tensor):
        return math.pi - torch.remainder(math.pi - angle, 2 * math.pi)
    return math.pi - np.remainder(math.pi - np.asarray(angle, dtype=np.float64), 2 * math.pi)


def parse_pose(text: str, source: str) -> np.ndarray:
    """``"q_boom,q_arm,q_bucket,q_swing"`` (rad) as a (4,) array, else a clear error naming ``source``.

    Args:
        text: the pose as written (an option's value).
        source: what gave it (``--home``, ``simulated machine: start``), for the error.
    """
    try:
        pose = np.array([float(value) for value in str(text).split(",")])
    except ValueError as exc:
        raise EfficientTrackError(f"{source} '{text}': expected four numbers in rad, boom,arm,bucket,swing ({exc})") from exc
    if pose.shape != (4,) or not np.all(np.isfinite(pose)):
        raise EfficientTrackError(f"{source} '{text}': expected four finite numbers in rad, boom,arm,bucket,swing")
    return pose
