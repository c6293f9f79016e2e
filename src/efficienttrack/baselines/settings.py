"""The settings of the Stable-Baselines3 baselines: one frozen dataclass per method; presets paper, cpu, sb3, tiny.

``paper`` takes the research code's values (``comparative_experiments/PidExcavatorRL``: ``PPO_Agent.py``,
``train_ppo.py``, ``SAC_Agent.py``, ``train_sac.py`` in the public repository ZiqingZou/EfficientTrack) where SB3 can
express them; docs/baselines.md lists each field and its source. ``cpu`` is what one CPU thread carries and learns
with, each choice measured (docs/baselines.md): for PPO the paper's 16 parallel environments, rollouts of 16 × 256
steps in minibatches of 512, the research code's γ 0.98 and an initial action std of 0.2 (SB3's 1 spans the whole
action range); for SAC the research code's γ and learning rate and the paper's 100,000-transition buffer, with SB3's
(256, 256) networks and batch of 256 and one gradient step per 4 interaction steps (4 environments), so that the
paper's 442,892 steps take about 45 minutes of one CPU thread instead of 3 hours. ``sb3`` is Stable-Baselines3's own
defaults (SB3 2.x, ``MlpPolicy``) with the paper's 16 PPO environments and 100,000-transition SAC buffer: the
dataclasses' defaults, the second variant, and the ``cpu`` preset until 2026-11-26. ``tiny`` shrinks networks,
rollouts and batches so that a few thousand interaction steps take seconds on a CPU (tests and smoke runs; its curves
say nothing about the methods).

Every preset gives the learner the input EfficientTrack's networks see (``inputs="relative"``:
:class:`~efficienttrack.envs.features.ObservationPipeline`) and starts it at the PD controller: the action mean's
last layer is zero, so the untrained deterministic policy sends a = 0. ``inputs="raw"`` keeps the raw 332 absolute
values, for comparison.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.settings import DEVICE, canonical_preset, check_fields, setting

INPUTS = ("relative", "raw")
"""What a baseline sees: the standardized relative features every learner shares, or the raw flat observation."""


def _check_net_arch(settings: PPOSettings | SACSettings) -> None:
    """Refuse networks without a hidden layer (what :func:`~efficienttrack.core.settings.check_fields` cannot say)."""
    if not settings.net_arch:
        raise EfficientTrackError(
            f"{type(settings).__name__}.net_arch must be a list of at least one integer ≥ 1, got {settings.net_arch!r}"
        )


def start_at_pd(head: nn.Module) -> None:
    """Zero the layer that outputs the action mean: the untrained policy's deterministic action is a = 0 (PD alone).

    Its gradient is not zero (it is the layer's input), so learning starts at once, as EfficientTrack's policy, whose
    last layer also starts at zero.

    Args:
        head: the action-mean layer (SB3's ``actor.mu`` for SAC, ``policy.action_net`` for PPO), an ``nn.Linear``.
    """
    assert isinstance(head, nn.Linear), f"the action mean is a Linear layer in SB3 2.x, got {type(head).__name__}"
    with torch.no_grad():
        head.weight.zero_()
        head.bias.zero_()


@dataclass(frozen=True)
class PPOSettings:
    """Settings of PPO (SB3's ``PPO`` with an ``MlpPolicy``): the paper's where it gives them, SB3's defaults otherwise."""

    n_envs: int = setting(16, ge=1)
    """Parallel environments stepping together (the paper: 16 workers; SB3 has no default, it takes the env given)."""
    n_steps: int = setting(2048, ge=1)
    """Steps per environment in one rollout, so a rollout is ``n_envs · n_steps`` interaction steps (SB3 default)."""
    batch_size: int = setting(64, ge=1)
    """Minibatch size of the updates (SB3 default)."""
    n_epochs: int = setting(10, ge=1)
    """Passes over each rollout (SB3 default)."""
    learning_rate: float = setting(3e-4, gt=0)
    """Adam learning rate, constant (SB3 default)."""
    gamma: float = setting(0.99, ge=0, le=1)
    """Discount factor (SB3 default)."""
    gae_lambda: float = setting(0.95, ge=0, le=1)
    """λ of generalized advantage estimation (SB3 default)."""
    clip_range: float = setting(0.2, gt=0)
    """PPO's clip range ε (SB3 default)."""
    ent_coef: float = setting(0.0, ge=0)
    """Entropy bonus coefficient (SB3 default)."""
    vf_coef: float = setting(0.5, ge=0)
    """Value-loss coefficient (SB3 default)."""
    max_grad_norm: float = setting(0.5, gt=0)
    """Gradient-norm clip (SB3 default)."""
    net_arch: tuple[int, ...] = setting((64, 64), ge=1)
    """Hidden layers of the policy and (separately) of the value network, tanh (SB3's default ``MlpPolicy``)."""
    log_std_init: float = setting(0.0)
    """Initial log standard deviation of the Gaussian actions (SB3 default 0: σ = 1 over the whole ±1 action range)."""
    inputs: str = setting("relative", choices=INPUTS)
    """What the policy sees (:data:`INPUTS`): the relative standardized features every learner shares, or ``"raw"``."""
    device: str = setting("auto", pattern=DEVICE)
    """Torch device: ``"auto"`` takes CUDA when present, else the CPU (SB3 default)."""

    def __post_init__(self) -> None:
        """Check the fields (:func:`~efficienttrack.core.settings.check_fields`), a hidden layer and a rollout of 2 steps."""
        check_fields(self)
        _check_net_arch(self)
        if self.n_steps * self.n_envs < 2:
            raise EfficientTrackError(
                f"PPOSettings.n_steps must make a rollout (n_steps · n_envs) of at least 2 steps, got {self.n_steps} "
                f"with n_envs = {self.n_envs}"
            )

    def build(self, env: VecEnv, seed: int) -> PPO:
        """A fresh SB3 ``PPO`` with these settings on ``env``, seeded (SB3 seeds Python, numpy, torch and the env).

        Args:
            env: the vectorized environment; its ``num_envs`` must equal :attr:`n_envs`.
            seed: the seed.

        Returns:
            The untrained model, its action mean at zero (:func:`start_at_pd`).
        """
        skip = ("n_envs", "net_arch", "device", "log_std_init", "inputs")
        options = {k: v for k, v in asdict(self).items() if k not in skip}
        policy_kwargs = {"net_arch": list(self.net_arch), "log_std_init": self.log_std_init}
        model = PPO("MlpPolicy", env, seed=seed, device=self.device, policy_kwargs=policy_kwargs, verbose=0, **options)
        start_at_pd(model.policy.action_net)
        return model


@dataclass(frozen=True)
class SACSettings:
    """Settings of SAC (SB3's ``SAC`` with an ``MlpPolicy``): the paper's where it gives them, SB3's defaults otherwise."""

    n_envs: int = setting(1, ge=1)
    """Parallel environments on one batched system (the paper: one; SB3's SAC examples use one). With ``train_freq``
    and ``gradient_steps`` of 1, SB3 takes one gradient step per vector step, i.e. one per ``n_envs`` interaction
    steps."""
    buffer_size: int = setting(100_000, ge=1)
    """Replay buffer capacity in transitions (the paper: 100,000; SB3's default is 1,000,000)."""
    learning_starts: int = setting(100, ge=0)
    """Interaction steps of random actions before the first update (SB3 default)."""
    batch_size: int = setting(256, ge=1)
    """Minibatch size of each update (SB3 default)."""
    learning_rate: float = setting(3e-4, gt=0)
    """Adam learning rate of actor, critics and entropy coefficient (SB3 default)."""
    gamma: float = setting(0.99, ge=0, le=1)
    """Discount factor (SB3 default)."""
    tau: float = setting(0.005, ge=0, le=1)
    """Polyak coefficient of the target critics (SB3 default)."""
    train_freq: int = setting(1, ge=1)
    """Vector-environment steps (each ``n_envs`` interaction steps) between updates (SB3 default)."""
    gradient_steps: int = setting(1, ge=1)
    """Gradient steps per update (SB3 default)."""
    ent_coef: float | None = setting(None, gt=0)
    """Entropy coefficient α; None learns it from an initial 1.0 towards the target entropy −dim(A) (SB3's ``"auto"``)."""
    net_arch: tuple[int, ...] = setting((256, 256), ge=1)
    """Hidden layers of the actor and of each critic, ReLU (SB3's default for SAC)."""
    inputs: str = setting("relative", choices=INPUTS)
    """What the policy and critics see (:data:`INPUTS`): the relative standardized features, or ``"raw"``."""
    device: str = setting("auto", pattern=DEVICE)
    """Torch device: ``"auto"`` takes CUDA when present, else the CPU (SB3 default)."""

    def __post_init__(self) -> None:
        """Check the fields (:func:`~efficienttrack.core.settings.check_fields`), then that there is a hidden layer."""
        check_fields(self)
        _check_net_arch(self)

    def build(self, env: VecEnv, seed: int) -> SAC:
        """A fresh SB3 ``SAC`` with these settings on ``env``, seeded (SB3 seeds Python, numpy, torch and the env).

        Args:
            env: the vectorized environment; its ``num_envs`` must equal :attr:`n_envs`.
            seed: the seed.

        Returns:
            The untrained model, its action mean at zero (:func:`start_at_pd`).
        """
        skip = ("n_envs", "net_arch", "device", "inputs")
        options: dict[str, Any] = {k: v for k, v in asdict(self).items() if k not in skip}
        options["ent_coef"] = "auto" if self.ent_coef is None else self.ent_coef
        policy_kwargs = {"net_arch": list(self.net_arch)}
        model = SAC("MlpPolicy", env, seed=seed, device=self.device, policy_kwargs=policy_kwargs, verbose=0, **options)
        start_at_pd(model.actor.mu)
        return model


PAPER_NET = (512, 512, 512, 128)
"""The research code's hidden layers for both methods' networks (ReLU; it also puts LayerNorms in its critics)."""

PPO_PRESETS: dict[str, PPOSettings] = {
    "paper": PPOSettings(
        n_envs=8,
        n_steps=512,
        batch_size=4096,
        n_epochs=8,
        learning_rate=3e-5,
        gamma=0.98,
        gae_lambda=0.99,
        clip_range=3.0,
        net_arch=PAPER_NET,
    ),
    "cpu": PPOSettings(n_steps=256, batch_size=512, gamma=0.98, log_std_init=-1.6),
    "sb3": PPOSettings(),
    "tiny": PPOSettings(n_envs=4, n_steps=32, batch_size=32, n_epochs=2, net_arch=(32, 32)),
}
"""PPO's presets: ``paper`` (the research code's), ``cpu`` (16 environments × 256 steps a rollout, minibatches of 512,
γ 0.98, initial action std e^−1.6 ≈ 0.2: 244 updates in a million steps, where SB3's 2,048-step rollouts give 30),
``sb3`` (the paper's 16 environments, SB3's defaults; ``cpu`` until 2026-11-26), ``tiny``."""

SAC_PRESETS: dict[str, SACSettings] = {
    "paper": SACSettings(batch_size=4096, learning_rate=3e-5, gamma=0.98, net_arch=PAPER_NET),
    "cpu": SACSettings(n_envs=4, learning_rate=3e-5, gamma=0.98),
    "sb3": SACSettings(),
    "tiny": SACSettings(buffer_size=10_000, learning_starts=50, batch_size=32, net_arch=(32, 32)),
}
"""SAC's presets: ``paper`` (the research code's), ``cpu`` (the research code's γ 0.98 and learning rate 3e-5, its
100,000-transition buffer, SB3's (256, 256) networks and batch 256, one gradient step per 4 interaction steps on 4
environments: about 6 ms of CPU a step on one thread, against 24 ms at one gradient step per step), ``sb3`` (SB3's
defaults with the 100,000 buffer: one environment, one gradient step per step, learning rate 3e-4, γ 0.99; the
``cpu`` preset until 2026-11-26, which the xe75 SAC results made before then used), ``tiny``."""

PRESETS: dict[str, dict[str, PPOSettings] | dict[str, SACSettings]] = {"ppo": PPO_PRESETS, "sac": SAC_PRESETS}
"""Presets by method name, then preset name."""


def method_settings(method: str, preset: str | PPOSettings | SACSettings = "cpu") -> PPOSettings | SACSettings:
    """The settings of ``method`` by preset name, or ``preset`` itself when it is a settings object of that method.

    Args:
        method: ``"ppo"`` or ``"sac"``.
        preset: ``"paper"``, ``"cpu"``, ``"sb3"``, ``"tiny"`` (``"full"``, ``"quick"``: earlier names), or a
            :class:`PPOSettings` / :class:`SACSettings` of the method.

    Returns:
        The settings.

    Raises:
        EfficientTrackError: an unknown method or preset, or settings of the other method.
    """
    if method not in PRESETS:
        raise EfficientTrackError(f"method '{method}': unknown baseline (known: {', '.join(PRESETS)})")
    presets = PRESETS[method]
    if isinstance(preset, str):
        preset = canonical_preset(preset)
        if preset not in presets:
            raise EfficientTrackError(f"preset '{preset}': unknown for {method} (known: {', '.join(presets)})")
        return presets[preset]
    expected = type(presets["cpu"])
    if not isinstance(preset, expected):
        raise EfficientTrackError(f"preset: {method} takes a preset name or {expected.__name__}, got {type(preset).__name__}")
    return preset
