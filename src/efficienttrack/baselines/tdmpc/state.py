"""TD-MPC's state between two episodes, saved without pickle, so that an interrupted run resumes.

Saved at an episode's end, before the environment starts the next one, as tensors and plain values (read with
``weights_only=True``): the learner (TOLD, its target, both optimizers, the update count), the filled part of the
replay buffer with its priorities, the numpy and torch generators of the run, the environment's generator (which
draws the next reference), the interaction count and the curve. A run resumed from it continues exactly as the
uninterrupted run would (wall times aside).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from efficienttrack.baselines.resume import read_state, restoring
from efficienttrack.baselines.tdmpc.buffer import PrioritizedBuffer
from efficienttrack.baselines.tdmpc.learner import Learner
from efficienttrack.core.fileio import atomic_write

BUFFER_ARRAYS = ("obs", "next_obs", "action", "reward", "priority")
"""The arrays of :class:`~.buffer.PrioritizedBuffer` (``(capacity, ...)``), saved up to the rows ever written."""


class Generators(NamedTuple):
    """The random streams of a TD-MPC run.

    Attributes:
        rng: numpy: the seeding phase's actions and the replay sampling.
        torch: the planner's and π's noise (on the run's device).
        env: the environment's ``np_random``, which draws the next episode's reference.
    """

    rng: np.random.Generator
    torch: torch.Generator
    env: np.random.Generator


def save_state(
    path: Path,
    run: str,
    count: int,
    learner: Learner,
    buffer: PrioritizedBuffer,
    generators: Generators,
    curve: list[dict[str, Any]],
    wall_seconds: float,
) -> None:
    """Write the state after ``count`` interaction steps (an episode just ended) atomically to ``path``.

    Args:
        path: the state file.
        run: what the run is (its header and references, as JSON); a state of another run is refused on resume.
        count: interaction steps done.
        learner: the learner.
        buffer: the replay buffer (``count`` transitions added).
        generators: the run's random streams.
        curve: the points measured.
        wall_seconds: the training wall time (evaluations excluded).
    """
    rows = min(count, buffer.capacity)
    state = {
        "run": run,
        "count": int(count),
        "model": learner.model.state_dict(),
        "target": learner.target.state_dict(),
        "optim": learner.optim.state_dict(),
        "pi_optim": learner.pi_optim.state_dict(),
        "updates": int(learner.updates),
        "buffer": {name: torch.from_numpy(getattr(buffer, name)[:rows]) for name in BUFFER_ARRAYS},
        "buffer_counters": [float(buffer.max_priority), int(buffer.position), int(buffer.run)],
        "rng": json.dumps(generators.rng.bit_generator.state),
        "env_rng": json.dumps(generators.env.bit_generator.state),
        "torch_generator": generators.torch.get_state(),
        "curve": json.dumps(curve),
        "wall_seconds": float(wall_seconds),
    }
    atomic_write(path, lambda f: torch.save(state, f))


def restore_state(
    path: Path, run: str, learner: Learner, buffer: PrioritizedBuffer, generators: Generators
) -> tuple[int, list[dict[str, Any]], float]:
    """Load the state at ``path`` into a freshly built learner, buffer and generators of the same settings.

    Args:
        path: the state file written by :func:`save_state`.
        run: what this run is; it must equal the saved one.
        learner: the learner (its networks, optimizers and count are replaced).
        buffer: the empty replay buffer (filled from the state).
        generators: the run's random streams (their states are replaced).

    Returns:
        The interaction steps done, the curve measured and the training wall time at the state.

    Raises:
        EfficientTrackError: a file of another run, or an unreadable or damaged one, naming the file.
    """
    state = read_state(path, run)
    with restoring(path):
        learner.model.load_state_dict(state["model"])
        learner.target.load_state_dict(state["target"])
        learner.optim.load_state_dict(state["optim"])
        learner.pi_optim.load_state_dict(state["pi_optim"])
        learner.updates = int(state["updates"])
        for name in BUFFER_ARRAYS:
            rows = state["buffer"][name].numpy()
            getattr(buffer, name)[: len(rows)] = rows
        max_priority, position, episode_run = state["buffer_counters"]
        buffer.max_priority, buffer.position, buffer.run = float(max_priority), int(position), int(episode_run)
        generators.rng.bit_generator.state = json.loads(state["rng"])
        generators.env.bit_generator.state = json.loads(state["env_rng"])
        generators.torch.set_state(state["torch_generator"])
        return int(state["count"]), json.loads(state["curve"]), float(state["wall_seconds"])
