"""The single definition of angle wrapping: every angle difference in the package goes through it."""

from __future__ import annotations

import math
import sys

import numpy as np


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
