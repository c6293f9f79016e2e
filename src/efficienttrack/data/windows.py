"""Episodes of different lengths on one time axis: time-major padding, which windows exist, and rolling histories.

Both the learning side (:class:`efficienttrack.data.dataset.Sequences`, batch-major torch windows) and the
simulation side (:mod:`efficienttrack.systems.fit`, time-major numpy windows) ask the first two questions; they
are answered here once, and each side gathers its windows in its own axis order.

The rolling histories a runtime keeps step by step (:class:`History`) are padded at an episode start exactly as
:class:`~efficienttrack.data.dataset.Sequences` pads the training windows. They live here, without torch, so that the
torch-free ONNX runtime (:mod:`efficienttrack.deploy.onnx_runtime`) keeps them with the same code as the torch runtime.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple, TypeVar, cast

import numpy as np

from efficienttrack.core.errors import EfficientTrackError

if TYPE_CHECKING:
    import torch

ArrayT = TypeVar("ArrayT", np.ndarray, "torch.Tensor")


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


# ------------------------------------------------------------------------------------------ rolling histories


class History(NamedTuple):
    """The histories the model and the policy see at time t, for N machines.

    Attributes:
        obs: (N, h, 8) [rad, rad/s], ``o_{t−h+1} … o_t`` (oldest first).
        q_ref: (N, h, 4) rad, ``q^r_{t−h+1} … q^r_t`` (oldest first).
    """

    obs: np.ndarray
    q_ref: np.ndarray


def push(history: ArrayT, new: ArrayT) -> ArrayT:
    """Drop the oldest entry of ``history`` (N, h, C) and append ``new`` (N, C); numpy or torch.

    Torch is not imported here: a tensor can only exist once something else has imported it.

    Args:
        history: (N, h, C), oldest first.
        new: (N, C), the newest entry.

    Returns:
        (N, h, C), the same kind of array.
    """
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(history, torch.Tensor):
        return torch.cat([history[:, 1:], new[:, None]], dim=1)
    # Not a tensor (a tensor means torch is imported), so a numpy array, as ArrayT is here.
    return cast(ArrayT, np.concatenate([history[:, 1:], np.asarray(new)[:, None]], axis=1))


def initial_history(obs0: np.ndarray, h: int) -> History:
    """Histories at an episode start, padded as training pads them: ``o_H = [o_0]*h``, ``q^r_H = [q_0]*h``.

    Use with :func:`push_observation` (each new ``o_t``, also ``o_0``) then :func:`push_reference` (the
    reference ``q^r_{t+1}`` sent); pushing ``o_0`` onto this start leaves it unchanged.

    Args:
        obs0: (N, 8) [rad, rad/s], the measured start observation.
        h: history length (``horizon`` of the model/policy config).

    Returns:
        The start histories, obs (N, h, 8) and q_ref (N, h, 4).
    """
    obs0 = np.asarray(obs0, dtype=np.float64)
    if obs0.ndim != 2 or obs0.shape[1] != 8:
        raise EfficientTrackError(f"initial_history: obs0 must have shape (N, 8), got {obs0.shape}")
    if h < 1:
        raise EfficientTrackError(f"initial_history: history length h must be ≥ 1, got {h}")
    obs = np.repeat(obs0[:, None], h, axis=1)
    return History(obs=obs, q_ref=obs[:, :, :4].copy())


def push_observation(history: History, obs: np.ndarray) -> History:
    """Append the new observation ``o_t`` (N, 8) [rad, rad/s] to ``history.obs``; q_ref is kept."""
    return History(obs=push(history.obs, np.asarray(obs, dtype=np.float64)), q_ref=history.q_ref)


def push_reference(history: History, q_ref: np.ndarray) -> History:
    """Append the reference just sent, ``q^r_{t+1}`` (N, 4) rad, to ``history.q_ref``; obs is kept."""
    return History(obs=history.obs, q_ref=push(history.q_ref, np.asarray(q_ref, dtype=np.float64)))
