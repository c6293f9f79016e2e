"""The training state of a Stable-Baselines3 run, saved and restored without pickle, so an interrupted run resumes.

SB3's own ``save``/``load`` unpickles code, which nothing here may do on a file read back. This state holds tensors and
plain containers only (read with ``weights_only=True``): the networks and optimizers SB3 itself would save
(its ``_get_torch_save_params``), the filled part of an off-policy replay buffer, the step and update counters,
the global torch and numpy random states, and the curve measured so far. It is written at the start of a rollout
(after the previous update, so a PPO rollout or a SAC step is never cut in half) and restored into a freshly built
model with the same settings. The environments start fresh episodes on resume, so a resumed run is not
bit-identical to an uninterrupted one.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.save_util import recursive_getattr

from efficienttrack.baselines.resume import read_state, restoring
from efficienttrack.core.fileio import atomic_write

BUFFER_FIELDS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")
"""The arrays of SB3's ``ReplayBuffer`` (``(buffer_size, n_envs, ...)``) that are saved, up to the filled row."""


def save_state(model: BaseAlgorithm, path: Path, run: str, curve: list[dict[str, Any]], wall_seconds: float) -> None:
    """Write ``model``'s training state atomically to ``path``.

    Args:
        model: the SB3 model, between two rollouts.
        path: the state file.
        run: what the run is (its header and inputs, as JSON); a state of another run is refused on resume.
        curve: the points measured so far.
        wall_seconds: the training wall time so far (evaluations excluded).
    """
    names, variables = model._get_torch_save_params()
    state: dict[str, Any] = {
        "run": run,
        "num_timesteps": int(model.num_timesteps),
        "n_updates": int(model._n_updates),
        "episode_num": int(model._episode_num),
        "modules": {name: recursive_getattr(model, name).state_dict() for name in names},
        "variables": {name: recursive_getattr(model, name).detach().cpu() for name in variables},
        "torch_rng": torch.get_rng_state(),
        "numpy_rng": _numpy_state(),
        "curve": json.dumps(curve),
        "wall_seconds": float(wall_seconds),
    }
    if isinstance(model, OffPolicyAlgorithm):
        buffer = model.replay_buffer
        assert buffer is not None  # SB3 builds the buffer with the model
        filled = buffer.buffer_size if buffer.full else buffer.pos
        state["buffer"] = {
            field: torch.from_numpy(np.ascontiguousarray(getattr(buffer, field)[:filled]))
            for field in BUFFER_FIELDS
            if getattr(buffer, field, None) is not None
        }
        state["buffer_pos"], state["buffer_full"] = int(buffer.pos), bool(buffer.full)
    atomic_write(path, lambda f: torch.save(state, f))


def restore_state(model: BaseAlgorithm, path: Path, run: str) -> tuple[list[dict[str, Any]], float]:
    """Load the training state at ``path`` into ``model`` (freshly built with the same settings).

    Args:
        model: the SB3 model to continue.
        path: the state file written by :func:`save_state`.
        run: what this run is; it must equal the saved one.

    Returns:
        The curve measured before the state was saved, and the training wall time up to it.

    Raises:
        EfficientTrackError: a file of another run (other method, loop, seed, budget, system, settings or references),
            or an unreadable or damaged one; the message names the file and what to do.
    """
    state = read_state(path, run)
    with restoring(path):
        for name, tensors in state["modules"].items():
            recursive_getattr(model, name).load_state_dict(tensors)
        for name, tensor in state["variables"].items():
            recursive_getattr(model, name).data.copy_(tensor)
        if isinstance(model, OffPolicyAlgorithm):
            buffer = model.replay_buffer
            assert buffer is not None  # SB3 builds the buffer with the model
            for field, rows in state["buffer"].items():
                getattr(buffer, field)[: len(rows)] = rows.numpy()
            buffer.pos, buffer.full = int(state["buffer_pos"]), bool(state["buffer_full"])
        model.num_timesteps, model._n_updates = int(state["num_timesteps"]), int(state["n_updates"])
        model._episode_num = int(state["episode_num"])
        torch.set_rng_state(state["torch_rng"])
        np.random.set_state(_numpy_state(state["numpy_rng"]))
        curve, wall = json.loads(state["curve"]), float(state["wall_seconds"])
    return curve, wall


def _numpy_state(saved: dict[str, Any] | None = None) -> Any:
    """Numpy's global (legacy) random state as tensors and numbers, or back (``saved`` given): SB3 samples with it."""
    if saved is None:
        # The global generator is an MT19937, whose legacy state is this tuple (numpy's stubs give a union with a dict).
        kind, keys, pos, has_gauss, cached = cast("tuple[str, np.ndarray, int, int, float]", np.random.get_state())
        return {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                "has_gauss": int(has_gauss), "cached": float(cached)}  # fmt: skip
    keys = saved["keys"].numpy().astype(np.uint32)
    return saved["kind"], keys, saved["pos"], saved["has_gauss"], saved["cached"]
