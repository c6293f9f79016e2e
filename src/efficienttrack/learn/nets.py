"""What the dynamics model and the policy share: the paper's MLP, feature scaling, devices and sizes."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, TypeVar

import torch
from torch import nn

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.settings import DEVICE, Bounds
from efficienttrack.data.features import STD_FLOOR

ConfigT = TypeVar("ConfigT")


class MLP(nn.Module):
    """The paper's MLP: ``layers`` hidden blocks Linear → LayerNorm → ELU, then Linear → tanh × ``out_scale``.

    Args:
        in_dim: input features.
        out_dim: outputs.
        hidden: units per hidden layer (paper 512).
        layers: number of hidden blocks (paper 6).
        out_scale: bound of the output, a float or an (out_dim,) tensor; the output lies in (−out_scale, out_scale).
    """

    out_scale: torch.Tensor

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

    mean: torch.Tensor
    std: torch.Tensor

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
    if not Bounds(pattern=DEVICE).admits(device):
        raise EfficientTrackError(f"--device '{device}': expected {DEVICE[1]}")
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    resolved = torch.device(device)
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise EfficientTrackError(f"--device '{device}': CUDA is not available on this machine (use auto or cpu)")
    return resolved


def check_device_here(owner: str, device: str) -> None:
    """Refuse a settings' ``device`` this machine lacks, naming the field (a name :data:`DEVICE` admits, checked before).

    Args:
        owner: the settings class, named in the message.
        device: its ``device`` field.

    Raises:
        EfficientTrackError: CUDA is asked for and not available.
    """
    try:
        resolve_device(device)
    except EfficientTrackError:
        raise EfficientTrackError(
            f"{owner}.device must be auto or cpu (CUDA is not available on this machine), got {device!r}"
        ) from None


def check_size(owner: str, name: str, value: Any, low: int, high: int) -> None:
    """Check that a config's size field ``owner.name`` is an integer in [``low``, ``high``].

    Args:
        owner: the config class, named in the message.
        name: the field.
        value: its value.
        low: smallest value allowed.
        high: largest value allowed (a documented bound, e.g. :data:`MAX_HIDDEN`).

    Raises:
        EfficientTrackError: naming the field and the bound.
    """
    if not isinstance(value, int) or isinstance(value, bool):
        raise EfficientTrackError(f"{owner}.{name} must be an integer, got {value!r}")
    if value < low:
        raise EfficientTrackError(f"{owner}.{name} must be ≥ {low}, got {value}")
    if value > high:
        raise EfficientTrackError(f"{owner}.{name} must be ≤ {high} (the upper bound of this size), got {value}")


def device_memory(device: torch.device) -> int | None:
    """Total memory of ``device`` in bytes: the GPU's for CUDA, the machine's RAM for the CPU; None when unknown."""
    if device.type == "cuda":
        return torch.cuda.get_device_properties(device).total_memory
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


def training_bytes(batch: int, rollout: int, networks: Sequence[Any]) -> int:
    """Rough memory of one BPTT training step: float32 weights with their gradients and Adam moments, and activations.

    Each rollout step keeps, per window, the input and about four values per hidden unit (Linear, LayerNorm,
    ELU) of every network for the backward pass. A rough figure (within a factor of about 2): it catches sizes
    that cannot fit, not ones that nearly do.

    Args:
        batch: windows per step.
        rollout: steps each window is rolled.
        networks: configs of the networks run at each rollout step (``in_dim``, ``hidden``, ``layers``).

    Returns:
        Bytes.
    """
    params = sum(n.in_dim * n.hidden + (n.layers - 1) * n.hidden**2 + 8 * n.hidden for n in networks)
    units = sum(n.in_dim + 4 * n.layers * n.hidden for n in networks)
    return 4 * (4 * params + batch * rollout * units)


def check_training_memory(owner: str, batch: int, rollout: int, networks: Sequence[Any], device: torch.device) -> None:
    """Refuse a training run whose step needs more memory than ``device`` has (:func:`training_bytes`), before any work.

    Args:
        owner: the config class, named in the message.
        batch: windows per step (``batch_size``).
        rollout: steps each window is rolled (``horizon``).
        networks: configs of the networks run at each rollout step.
        device: where the training runs.

    Raises:
        EfficientTrackError: the estimate exceeds the device's memory, naming the fields to lower.
    """
    need, have = training_bytes(batch, rollout, networks), device_memory(device)
    if have is not None and need > have:
        raise EfficientTrackError(
            f"{owner}: a training step needs about {need / 2**30:.1f} GiB (batch_size {batch} × horizon {rollout} × "
            f"network sizes), more than the {have / 2**30:.1f} GiB of {device}; lower batch_size, horizon, hidden or layers"
        )
