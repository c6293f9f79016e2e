"""Episodes of different lengths on one time axis: time-major padding, and which windows exist.

Both the learning side (:class:`efficienttrack.dataset.Sequences`, batch-major torch windows) and the
simulation side (:mod:`efficienttrack.systems.fit`, time-major numpy windows) ask these two questions; they are
answered here once, and each side gathers its windows in its own axis order.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from efficienttrack.errors import EfficientTrackError


def pad_time_major(arrays: Sequence[np.ndarray], extra: int = 0) -> np.ndarray:
    """Stack arrays of different lengths time-major, each padded with its own last row.

    Args:
        arrays: N arrays (L_i, C) (e.g. references or logged positions (L_i, 4) rad), each with L_i ≥ 1.
        extra: rows to add beyond the longest array (e.g. room for a future window).

    Returns:
        (max L_i + extra, N, C) float64; row t of array i is ``arrays[i][min(t, L_i − 1)]``.

    Raises:
        EfficientTrackError: no array, or an empty one.
    """
    lengths = np.array([len(a) for a in arrays], dtype=np.int64)
    if len(lengths) == 0 or lengths.min() < 1:
        raise EfficientTrackError("padding needs at least one array and no empty one")
    flat = np.concatenate([np.asarray(a, dtype=np.float64) for a in arrays])  # (Σ L_i, C)
    first = np.cumsum(lengths) - lengths
    rows = np.minimum(np.arange(int(lengths.max()) + extra)[:, None], lengths[None, :] - 1)  # (T, N)
    return flat[first[None, :] + rows]


class Starts(NamedTuple):
    """Window starts: pairs (episode, t0), episode by episode in time order.

    Attributes:
        episode: (M,) int64, index of the episode.
        t0: (M,) int64, step of the window start within its episode.
    """

    episode: np.ndarray
    t0: np.ndarray


def window_starts(lengths: Sequence[int] | np.ndarray, horizon: int, stride: int = 1) -> Starts:
    """Every ``stride``-th start t0 = 0, stride, … with a full recorded horizon: ``t0 + horizon ≤ T − 1``.

    A window from t0 uses the steps t0 … t0 + horizon of its episode (the start and ``horizon`` steps after it);
    horizon 0 gives every step.

    Args:
        lengths: (E,) T of each episode, steps.
        horizon: steps after t0 the windows need, ≥ 0.
        stride: distance between the starts of one episode, steps, ≥ 1.

    Returns:
        The starts (M of them).

    Raises:
        EfficientTrackError: no episode is long enough.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    counts = np.maximum(-((horizon - lengths) // stride), 0)  # ceil((T − horizon) / stride)
    if int(counts.sum()) == 0:
        longest = int(lengths.max()) if len(lengths) else 0
        raise EfficientTrackError(f"no episode is long enough for a {horizon}-step window (longest has {longest} steps)")
    first = np.repeat(np.cumsum(counts) - counts, counts)
    return Starts(np.repeat(np.arange(len(lengths)), counts), (np.arange(int(counts.sum())) - first) * stride)
