"""What the dynamics model and the policy share: the paper's MLP, feature scaling, devices and checkpoint files.

Also the bookkeeping of a training loop (:class:`TrainLoop`: resume, progress, learning-rate schedule), so that
``dynamics.train_model`` and ``policy.train_policy`` show only the algorithm.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pickle
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TypeVar, Union, get_args, get_origin, get_type_hints

import numpy as np
import torch
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from torch import nn

from efficienttrack.angles import wrap
from efficienttrack.errors import EfficientTrackError
from efficienttrack.fileio import atomic_write, write_json

ConfigT = TypeVar("ConfigT")

STD_FLOOR = 1e-6
"""Smallest standard deviation used to scale a feature; constant features are only centred."""


class MLP(nn.Module):
    """The paper's MLP: ``layers`` hidden blocks Linear → LayerNorm → ELU, then Linear → tanh × ``out_scale``.

    Args:
        in_dim: input features.
        out_dim: outputs.
        hidden: units per hidden layer (paper 512).
        layers: number of hidden blocks (paper 6).
        out_scale: bound of the output, a float or an (out_dim,) tensor; the output lies in (−out_scale, out_scale).
    """

    def __init__(self, in_dim: int, out_dim: int, hidden: int, layers: int, out_scale: float | torch.Tensor = 1.0) -> None:
        super().__init__()
        if min(in_dim, out_dim, hidden, layers) < 1:
            raise EfficientTrackError(
                f"MLP sizes must be positive: in_dim={in_dim}, out_dim={out_dim}, hidden={hidden}, layers={layers}"
            )
        blocks: list[nn.Module] = []
        width = in_dim
        for _ in range(layers):
            blocks += [nn.Linear(width, hidden), nn.LayerNorm(hidden), nn.ELU()]
            width = hidden
        blocks.append(nn.Linear(width, out_dim))
        self.body = nn.Sequential(*blocks)
        self.register_buffer("out_scale", torch.as_tensor(out_scale, dtype=torch.float32).expand(out_dim).clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Map features ``x`` (B, in_dim) to bounded outputs (B, out_dim)."""
        return torch.tanh(self.body(x)) * self.out_scale


class Standardizer(nn.Module):
    """Per-feature affine scaling ``(x − mean) / std`` with the statistics kept as buffers (saved with the weights).

    Args:
        dim: number of features.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))

    @torch.no_grad()
    def fit(self, x: torch.Tensor) -> None:
        """Set the statistics from samples ``x`` (N, dim); features with std < STD_FLOOR keep std 1."""
        self.mean.copy_(x.mean(0))
        std = x.std(0) if len(x) > 1 else torch.ones_like(self.std)
        self.std.copy_(torch.where(std < STD_FLOOR, torch.ones_like(std), std))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Scale ``x`` (..., dim)."""
        return (x - self.mean) / self.std


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """Turn ``"auto"`` (CUDA when available, else CPU), ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` into a torch device.

    Args:
        device: the requested device.

    Returns:
        The device.

    Raises:
        EfficientTrackError: unknown name, or CUDA requested but not available.
    """
    if isinstance(device, torch.device):
        return device
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except RuntimeError as exc:
        raise EfficientTrackError(f"--device '{device}': expected auto, cpu, cuda or cuda:N ({exc})") from exc
    if resolved.type not in ("cpu", "cuda"):
        raise EfficientTrackError(f"--device '{device}': expected auto, cpu, cuda or cuda:N")
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise EfficientTrackError(f"--device '{device}': CUDA is not available on this machine (use auto or cpu)")
    return resolved


def relative_features(obs_hist: torch.Tensor, qref_hist: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """The network input: histories and targets as seen from the current position, so any machine's offsets drop out.

    Features, in order: the current position ``q_t`` (4), past positions ``wrap(q_{t−k} − q_t)``
    (h−1 × 4), velocities (h × 4), references ``wrap(q^r_{t−k} − q_t)`` (h × 4) and targets
    ``wrap(target − q_t)`` (K × 4): 12h + 4K values (callers scale them with a :class:`Standardizer`).

    Args:
        obs_hist: (B, h, 8) [rad, rad/s], ``o_{t−h+1} … o_t``.
        qref_hist: (B, h, 4) rad, ``q^r_{t−h+1} … q^r_t``.
        targets: (B, K, 4) rad, absolute positions ahead (``q^r_{t+1}`` for the model, ``q*_F`` for the policy).

    Returns:
        (B, 12h + 4K) features.
    """
    q_t = obs_hist[:, -1:, :4]
    parts = (
        q_t,
        wrap(obs_hist[:, :-1, :4] - q_t),
        obs_hist[:, :, 4:],
        wrap(qref_hist - q_t),
        wrap(targets - q_t),
    )
    return torch.cat([p.flatten(1) for p in parts], dim=1)


# ------------------------------------------------------------------------------------------------ checkpoints


def config_path(path: str | Path) -> Path:
    """The JSON config that lies next to checkpoint ``path`` (``model.pt`` → ``model.json``)."""
    path = Path(path)
    if path.suffix == ".json":
        raise EfficientTrackError(f"{path}: a checkpoint path must not end in .json (its config is written there)")
    return path.with_suffix(".json")


def save_checkpoint(module: nn.Module, kind: str, config: Any, path: str | Path) -> Path:
    """Write ``module``'s state_dict (``torch.save``) and its config as JSON next to it, both atomically.

    Args:
        module: the network (its buffers, e.g. feature scaling, are part of the state_dict).
        kind: what it is (``"closed_loop_model"``, ``"adjustment_policy"``), checked on load.
        config: the frozen config dataclass it was built from.
        path: checkpoint file, e.g. ``model.pt``; the config goes to ``model.json``.

    Returns:
        The checkpoint path.
    """
    path = Path(path)
    state = {name: tensor.detach().cpu() for name, tensor in module.state_dict().items()}
    write_json(config_path(path), {"kind": kind, "config": dataclasses.asdict(config)})
    atomic_write(path, lambda f: torch.save(state, f))
    return path


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


def config_from_dict(cls: type[ConfigT], data: dict[str, Any], source: str) -> ConfigT:
    """Build the frozen config dataclass ``cls`` from JSON/YAML ``data``, validating names and types field by field.

    Args:
        cls: the config class (a dataclass whose fields have int, float, bool, str, tuple or ``X | None`` types).
        data: the loaded mapping; missing fields keep their defaults.
        source: the file or option the data came from, for messages.

    Returns:
        The config.
    """
    if not isinstance(data, dict):
        raise EfficientTrackError(f"{source}: expected a mapping of {cls.__name__} fields, got {type(data).__name__}")
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        raise EfficientTrackError(
            f"{source}: unknown {cls.__name__} field(s) {', '.join(unknown)}; known: {', '.join(sorted(names))}"
        )
    values = {name: _coerce(hints[name], value, f"{source}: field '{name}'") for name, value in data.items()}
    try:
        return cls(**values)
    except (TypeError, ValueError) as exc:
        raise EfficientTrackError(f"{source}: {exc}") from exc


def _coerce(hint: Any, value: Any, where: str) -> Any:
    """Check ``value`` against the type ``hint`` (int, float, bool, str, tuple[float, ...], X | None) and convert."""
    origin = get_origin(hint)
    if origin in (Union, types.UnionType):
        options = get_args(hint)
        if value is None and type(None) in options:
            return None
        (inner,) = [option for option in options if option is not type(None)]
        return _coerce(inner, value, where)
    if origin is tuple:
        if not isinstance(value, list | tuple) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in value
        ):
            raise EfficientTrackError(f"{where} must be a list of numbers, got {value!r}")
        return tuple(float(v) for v in value)
    if hint is bool:
        if not isinstance(value, bool):
            raise EfficientTrackError(f"{where} must be true or false, got {value!r}")
        return value
    if hint is int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise EfficientTrackError(f"{where} must be an integer, got {value!r}")
        return value
    if hint is float:
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise EfficientTrackError(f"{where} must be a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise EfficientTrackError(f"{where} must be a string, got {value!r}")
        return value
    raise EfficientTrackError(f"{where}: unsupported config type {hint}")


# --------------------------------------------------------------------------------------------- training loop

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
    ) -> None:
        self.kind, self.cfg, self.total = kind, cfg, total
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
        if state.get("kind") != self.kind or state.get("config") != self._config or state.get("total") != self.total:
            raise EfficientTrackError(
                f"{self.checkpoint}: training state of another run (kind, config or number of steps differ); "
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
