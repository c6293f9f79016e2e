"""Training bookkeeping shared by the model and the policy: checkpoint files and :class:`TrainLoop`.

``TrainLoop`` handles resume, progress, the learning-rate schedule and atomic saves, so that
``dynamics.train_model`` and ``policy.train_policy`` show only the algorithm.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import pickle
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from torch import nn

from efficienttrack.errors import EfficientTrackError
from efficienttrack.fileio import atomic_write, write_json
from efficienttrack.provenance import provenance
from efficienttrack.records import EpisodeRecord


def fingerprint(records: Sequence[EpisodeRecord], seed: int, frozen: nn.Module | None = None) -> str:
    """SHA-256 identity of a training run's inputs: the records' arrays, the seed and a frozen network.

    Args:
        records: the training episodes (``q``, ``qd``, ``q_ref``, ``q_des`` are hashed).
        seed: the run's seed.
        frozen: a network the run trains through (the model, for a policy), or None.

    Returns:
        The hex digest.
    """
    digest = hashlib.sha256(str(seed).encode())
    for record in records:
        for array in (record.q, record.qd, record.q_ref, record.q_des):
            digest.update(np.ascontiguousarray(array).tobytes())
    if frozen is not None:
        for name, tensor in frozen.state_dict().items():
            digest.update(name.encode())
            digest.update(tensor.detach().cpu().numpy().tobytes())
    return digest.hexdigest()


def config_path(path: str | Path) -> Path:
    """The JSON config that lies next to checkpoint ``path`` (``model.pt`` → ``model.json``)."""
    path = Path(path)
    if path.suffix == ".json":
        raise EfficientTrackError(f"{path}: a checkpoint path must not end in .json (its config is written there)")
    return path.with_suffix(".json")


def save_checkpoint(module: nn.Module, kind: str, config: Any, path: str | Path) -> Path:
    """Write ``module``'s state_dict (``torch.save``) and its config as JSON next to it, both atomically.

    The JSON holds ``kind``, ``config``, ``weights_sha256`` and ``provenance`` (:func:`~efficienttrack.provenance.provenance`,
    with the device the module lies on).

    Args:
        module: the network (its buffers, e.g. feature scaling, are part of the state_dict).
        kind: what it is (``"closed_loop_model"``, ``"adjustment_policy"``), checked on load.
        config: the frozen config dataclass it was built from.
        path: checkpoint file, e.g. ``model.pt``; the config goes to ``model.json``.

    Returns:
        The checkpoint path.
    """
    path = Path(path)
    tensors = module.state_dict()
    state = {name: tensor.detach().cpu() for name, tensor in tensors.items()}
    atomic_write(path, lambda f: torch.save(state, f))
    device = next(iter(tensors.values())).device if tensors else None
    meta = {
        "kind": kind,
        "config": dataclasses.asdict(config),
        "weights_sha256": _file_sha256(path),
        "provenance": provenance(device),
    }
    write_json(config_path(path), meta)
    return path


def _file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def load_checkpoint(path: str | Path, kind: str) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """Read a checkpoint written by :func:`save_checkpoint`: tensors only (``weights_only=True``), never code.

    Args:
        path: the checkpoint file; its JSON config must lie next to it.
        kind: the expected kind.

    Returns:
        (config fields as a dict, state_dict) — the caller builds its config and module from them.

    Raises:
        EfficientTrackError: missing files, a config of another kind, or a file that is not a plain state_dict
            (e.g. a pickle holding code).
    """
    path = Path(path)
    cfg_file = config_path(path)
    if not path.is_file():
        raise EfficientTrackError(f"{path}: no such checkpoint file")
    if not cfg_file.is_file():
        raise EfficientTrackError(f"{path}: its config {cfg_file} is missing (a checkpoint is the .pt file plus its .json)")
    try:
        meta = json.loads(cfg_file.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise EfficientTrackError(f"{cfg_file}: not a readable JSON config ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("kind") != kind or not isinstance(meta.get("config"), dict):
        found = meta.get("kind") if isinstance(meta, dict) else type(meta).__name__
        raise EfficientTrackError(f"{cfg_file}: expected a '{kind}' config, found '{found}'")
    state = load_tensors(path)
    if not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()):
        raise EfficientTrackError(f"{path}: not a state_dict (expected a dict of named tensors)")
    if meta.get("weights_sha256") not in (None, _file_sha256(path)):
        raise EfficientTrackError(f"{cfg_file}: written for other weights than {path} (an interrupted save?); save both again")
    return meta["config"], state


def load_tensors(path: str | Path) -> dict[str, Any]:
    """``torch.load(path, weights_only=True)`` on CPU, with a clear error for anything but tensors and plain containers.

    Args:
        path: a file written by ``torch.save``.

    Returns:
        The loaded dict.
    """
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError, AttributeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise EfficientTrackError(
            f"{path}: refused to load: not a plain tensor checkpoint (files must hold data, never code): {first}"
        ) from exc
    if not isinstance(data, dict):
        raise EfficientTrackError(f"{path}: holds a {type(data).__name__}, expected a dict of tensors")
    return data


PROGRESS_EVERY = 10
"""Steps between progress-bar refreshes."""


class TrainLoop:
    """The bookkeeping around a BPTT loop: steps, sampling RNG, learning rate, loss log, progress, saves and resume.

    The training state (weights, optimizer, sampling generator, losses) is saved atomically every
    ``cfg.save_every`` steps and at the end; an existing state of the same run is resumed from.

    Iterate over it to get the step numbers still to do; call :meth:`record` once per step.

    Args:
        kind: ``"model"`` or ``"policy"`` (checked when resuming).
        cfg: the frozen config (needs ``lr``, ``cosine_decay``, ``save_every``); a resumed state must have the same.
        total: optimizer steps of the whole run.
        module: the network being trained.
        optimizer: its optimizer.
        seed: seeds the window-sampling generator.
        checkpoint: training-state file (resumed when it exists), or None.
        progress: show a rich progress bar.
        inputs: fingerprint of what the run learns from (:func:`fingerprint`); a saved state made from other
            inputs is refused instead of being resumed.
    """

    def __init__(
        self,
        kind: str,
        cfg: Any,
        total: int,
        module: nn.Module,
        optimizer: torch.optim.Optimizer,
        seed: int,
        checkpoint: str | Path | None,
        progress: bool,
        inputs: str = "",
    ) -> None:
        self.kind, self.cfg, self.total, self.inputs = kind, cfg, total, inputs
        self.module, self.optimizer = module, optimizer
        self.checkpoint = None if checkpoint is None else Path(checkpoint)
        self.progress = progress
        self.generator = torch.Generator().manual_seed(seed)
        self._losses = np.full(total, np.nan)
        self.start = 0
        self._config = json.dumps(dataclasses.asdict(cfg), sort_keys=True)
        if self.checkpoint is not None and self.checkpoint.exists():
            self._resume()

    def _resume(self) -> None:
        """Load the saved training state, refusing one from another kind or config."""
        state = load_tensors(self.checkpoint)
        same = (state.get("kind"), state.get("config"), state.get("total"), state.get("inputs"))
        if same != (self.kind, self._config, self.total, self.inputs):
            raise EfficientTrackError(
                f"{self.checkpoint}: training state of another run (kind, config, steps, data, seed or model differ); "
                "delete it to start afresh, or train with the config it was made with"
            )
        try:
            self.module.load_state_dict(state["module"])
            self.optimizer.load_state_dict(state["optimizer"])
            self.generator.set_state(state["generator"])
        except (KeyError, RuntimeError, ValueError) as exc:
            raise EfficientTrackError(f"{self.checkpoint}: unreadable training state ({exc})") from exc
        self.start = int(state["step"])
        self._losses[: self.start] = state["losses"].numpy()[: self.start]

    def save(self, step: int) -> None:
        """Write the training state after ``step`` steps atomically (no-op without a checkpoint path)."""
        if self.checkpoint is None:
            return
        state = {
            "kind": self.kind,
            "config": self._config,
            "total": self.total,
            "inputs": self.inputs,
            "step": step,
            "module": self.module.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "losses": torch.as_tensor(self._losses),
        }
        atomic_write(self.checkpoint, lambda f: torch.save(state, f))

    def sample(self, n: int, batch: int) -> torch.Tensor:
        """(batch,) int64 CPU indices drawn uniformly from range(n) with the loop's generator."""
        return torch.randint(n, (batch,), generator=self.generator)

    def set_lr(self, step: int) -> None:
        """Set the optimizer's learning rate for ``step``: ``cfg.lr``, cosine-decayed to 0 when ``cfg.cosine_decay``."""
        lr = self.cfg.lr * (0.5 * (1 + math.cos(math.pi * step / self.total)) if self.cfg.cosine_decay else 1.0)
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def record(self, step: int, loss: float) -> None:
        """Log the loss of ``step``; save the state every ``cfg.save_every`` steps."""
        self._losses[step] = loss
        if (step + 1) % self.cfg.save_every == 0 and step + 1 < self.total:
            self.save(step + 1)

    def losses(self) -> np.ndarray:
        """(total,) the loss of every step (NaN for steps not run)."""
        return self._losses.copy()

    def __iter__(self) -> Iterator[int]:
        """Yield the remaining step numbers, showing progress; save the final state at the end."""
        self.module.train()
        columns = (
            TextColumn(f"train {self.kind}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("loss {task.fields[loss]:.4g}"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
        )
        with Progress(*columns, disable=not self.progress, transient=False) as bar:
            task = bar.add_task("train", total=self.total, completed=self.start, loss=float("nan"))
            for step in range(self.start, self.total):
                yield step
                if (step + 1) % PROGRESS_EVERY == 0 or step + 1 == self.total:
                    recent = self._losses[max(self.start, step + 1 - PROGRESS_EVERY) : step + 1]
                    bar.update(task, completed=step + 1, loss=float(np.mean(recent)))
        if self.start < self.total:
            self.save(self.total)
