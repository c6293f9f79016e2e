"""SuperTrack's state between two iterations, saved without pickle, so that an interrupted run resumes.

Everything an iteration hands the next is saved as tensors and plain values (read with ``weights_only=True``):
the world model's and the policy's weights, the replay buffer's episodes, the generator of the reference draws and
the noise, the noise's last value, the counts, and the curve so far. A run resumed from it continues exactly as
the uninterrupted run would (wall times aside).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn

from efficienttrack.baselines.agent import Noise
from efficienttrack.baselines.resume import read_state, restoring
from efficienttrack.core.fileio import atomic_write
from efficienttrack.data.records import EpisodeRecord

ARRAYS = ("q", "qd", "q_ref", "q_des", "u", "t")
"""The arrays of an :class:`~efficienttrack.data.records.EpisodeRecord` (``u`` may be None)."""


class Progress(NamedTuple):
    """Where a SuperTrack run stands after an iteration.

    Attributes:
        count: interaction steps collected.
        iteration: iterations done.
        buffer: the replay buffer's episodes, oldest first.
        curve: the points measured.
        wall_seconds: the training wall time (evaluations excluded).
    """

    count: int  # type: ignore[assignment]  # a field named like tuple.count, which it hides
    iteration: int
    buffer: list[EpisodeRecord]
    curve: list[dict[str, Any]]
    wall_seconds: float


def save_state(
    path: Path, run: str, progress: Progress, model: nn.Module, policy: nn.Module, rng: np.random.Generator, noise: Noise
) -> None:
    """Write the state after an iteration atomically to ``path``.

    Args:
        path: the state file.
        run: what the run is (its header and references, as JSON); a state of another run is refused on resume.
        progress: the counts, buffer and curve.
        model: the world model.
        policy: the policy.
        rng: the generator of the reference draws and the noise.
        noise: the exploration noise.
    """
    state = {
        "run": run,
        "count": progress.count,
        "iteration": progress.iteration,
        "buffer": [_record_state(record) for record in progress.buffer],
        "curve": json.dumps(progress.curve),
        "wall_seconds": float(progress.wall_seconds),
        "model": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "policy": {k: v.detach().cpu() for k, v in policy.state_dict().items()},
        "rng": json.dumps(rng.bit_generator.state),
        "noise": None if noise.last is None else torch.from_numpy(np.array(noise.last)),
    }
    atomic_write(path, lambda f: torch.save(state, f))


def restore_state(
    path: Path, run: str, model: nn.Module, policy: nn.Module, rng: np.random.Generator, noise: Noise
) -> Progress:
    """Load the state at ``path`` into freshly built networks, the generator and the noise.

    Args:
        path: the state file written by :func:`save_state`.
        run: what this run is; it must equal the saved one.
        model: a world model built from the run's config (its weights are replaced).
        policy: a policy built from the run's config (its weights are replaced).
        rng: the run's generator (its state is replaced).
        noise: the run's noise (its last value is replaced).

    Returns:
        The counts, buffer and curve of the saved iteration.

    Raises:
        EfficientTrackError: a file of another run, or an unreadable or damaged one, naming the file.
    """
    state = read_state(path, run)
    with restoring(path):
        model.load_state_dict(state["model"])
        policy.load_state_dict(state["policy"])
        rng.bit_generator.state = json.loads(state["rng"])
        noise.resume(None if state["noise"] is None else state["noise"].numpy())
        buffer = [_record(saved) for saved in state["buffer"]]
        return Progress(int(state["count"]), int(state["iteration"]), buffer, json.loads(state["curve"]),
                        float(state["wall_seconds"]))  # fmt: skip


def _record_state(record: EpisodeRecord) -> dict[str, Any]:
    arrays = {name: torch.from_numpy(np.array(getattr(record, name))) for name in ARRAYS if getattr(record, name) is not None}
    return {**arrays, "meta": json.dumps(record.meta)}


def _record(saved: dict[str, Any]) -> EpisodeRecord:
    arrays: dict[str, Any] = {name: saved[name].numpy() if name in saved else None for name in ARRAYS}
    return EpisodeRecord(**arrays, meta=json.loads(saved["meta"]))
