"""TD-MPC's planner: MPPI-style sampling in the latent space of TOLD, vectorized over machines and samples.

Per step and machine, ``iterations`` rounds of: sample ``num_samples`` action sequences (H, A) from a Gaussian
(mean, std), add ``int(mixture_coef · num_samples)`` sequences rolled out with π, score each by its latent return
``Σ_t γ^t R(z_t, a_t) + γ^H min(Q1, Q2)(z_H, π(z_H))``, keep the ``num_elites`` best, and refit the Gaussian to them
with weights ``softmax(temperature · value)``: mean = momentum · mean + (1 − momentum) · weighted mean, std = the
weighted std clipped to [min_std, 2]. The mean starts from the previous step's plan shifted by one step (zero at an
episode's start). The action taken is the first action of one elite drawn by its weight, plus exploration noise of the
final std in training: the public TD-MPC code's rule. All N machines and all samples are one batch for the networks.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import torch

MAX_STD = 2.0
"""Upper bound (and starting value) of the planner's standard deviation, as in the public code."""


class LatentModel(Protocol):
    """What the planner needs of a model: latent steps, Q-values and π (:class:`~.networks.TOLD` is one)."""

    def next(self, z: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(z_next (..., L), reward (...))`` of ``z`` (..., L) and ``a`` (..., A)."""
        ...

    def q(self, z: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(Q1 (...), Q2 (...))`` of ``z`` (..., L) and ``a`` (..., A)."""
        ...

    def pi(self, z: torch.Tensor, std: float = 0.0, generator: torch.Generator | None = None) -> torch.Tensor:
        """π's action (..., A) for ``z`` (..., L), with noise ``std`` drawn with ``generator``."""
        ...


class PlannerConfig(NamedTuple):
    """The planner's knobs (from :class:`~.settings.TDMPCSettings` and its schedules).

    Attributes:
        horizon: H, steps planned.
        action_dim: A, the action's length.
        iterations: refits of the Gaussian.
        num_samples: Gaussian sequences per iteration.
        num_pi_samples: π sequences added to them.
        num_elites: best sequences refitted to.
        temperature: of the elites' weights.
        momentum: weight of the previous mean.
        min_std: lower bound of the std (the schedule's value at this step).
        pi_std: π's noise in its sequences and in the terminal value (the settings' final ``min_std``).
        discount: γ.
    """

    horizon: int
    action_dim: int
    iterations: int
    num_samples: int
    num_pi_samples: int
    num_elites: int
    temperature: float
    momentum: float
    min_std: float
    pi_std: float
    discount: float


class Plan(NamedTuple):
    """The planner's result for N machines.

    Attributes:
        action: (N, A) in [−1, 1], the action to take (noise included when exploring).
        mean: (H, N, A), the final mean, the next step's warm start.
    """

    action: torch.Tensor
    mean: torch.Tensor


@torch.no_grad()
def estimate_value(
    model: LatentModel, z: torch.Tensor, actions: torch.Tensor, config: PlannerConfig, generator: torch.Generator
) -> torch.Tensor:
    """The latent return of action sequences: ``Σ_t γ^t R(z_t, a_t) + γ^H min(Q1, Q2)(z_H, π(z_H))``.

    Args:
        model: the latent model.
        z: (N, K, L) start latents (one per sequence).
        actions: (H, N, K, A) action sequences.
        config: the planner's knobs (``discount``; π's action at the end has noise ``pi_std``, as in the public code).
        generator: torch generator of π's noise.

    Returns:
        (N, K) values.
    """
    value = torch.zeros(z.shape[:-1], device=z.device, dtype=z.dtype)
    discount = 1.0
    for a in actions:
        z, reward = model.next(z, a)
        value = value + discount * reward
        discount *= config.discount
    q1, q2 = model.q(z, model.pi(z, config.pi_std, generator))
    return value + discount * torch.minimum(q1, q2)


@torch.no_grad()
def plan(
    model: LatentModel,
    z0: torch.Tensor,
    config: PlannerConfig,
    generator: torch.Generator,
    warm: torch.Tensor | None = None,
    explore: bool = True,
) -> Plan:
    """Plan for N machines at once (see the module docstring).

    Args:
        model: the latent model.
        z0: (N, L) latent states of the machines.
        config: the planner's knobs.
        generator: torch generator of the samples, the elite drawn, π's noise and the exploration noise.
        warm: (H', N, A) the previous plan's mean (shifted by one step here), or None at an episode's start.
        explore: add exploration noise of the final std to the action (training) or not (evaluation).

    Returns:
        The action (N, A) and the final mean (H, N, A).
    """
    n, device = z0.shape[0], z0.device
    horizon, action_dim = config.horizon, config.action_dim
    z = z0[:, None, :].expand(n, config.num_samples + config.num_pi_samples, z0.shape[-1])
    pi_actions = None
    if config.num_pi_samples > 0:
        zp = z0[:, None, :].expand(n, config.num_pi_samples, z0.shape[-1])
        steps = []
        for _ in range(horizon):
            steps.append(model.pi(zp, config.pi_std, generator))
            zp, _ = model.next(zp, steps[-1])
        pi_actions = torch.stack(steps)  # (H, N, P, A)
    mean = torch.zeros(horizon, n, action_dim, device=device)
    std = torch.full((horizon, n, action_dim), MAX_STD, device=device)
    if warm is not None:
        shifted = warm[1 : horizon + 1]
        mean[: len(shifted)] = shifted
    for _ in range(config.iterations):
        noise = torch.randn((horizon, n, config.num_samples, action_dim), generator=generator, device=device)
        actions = (mean[:, :, None] + std[:, :, None] * noise).clamp(-1.0, 1.0)
        if pi_actions is not None:
            actions = torch.cat([actions, pi_actions], dim=2)
        value = estimate_value(model, z, actions, config, generator).nan_to_num(0.0)  # (N, K)
        elite_value, elite_index = value.topk(config.num_elites, dim=1)  # (N, E)
        index = elite_index[None, :, :, None].expand(horizon, n, config.num_elites, action_dim)
        elites = actions.gather(2, index)  # (H, N, E, A)
        score = torch.softmax(config.temperature * elite_value, dim=1)  # (N, E)
        weights = score[None, :, :, None]
        new_mean = (weights * elites).sum(2)
        new_std = ((weights * (elites - new_mean[:, :, None]) ** 2).sum(2)).sqrt().clamp(config.min_std, MAX_STD)
        mean, std = config.momentum * mean + (1 - config.momentum) * new_mean, new_std
    chosen = torch.multinomial(score, 1, generator=generator)[:, 0]  # (N,)
    action = elites[0, torch.arange(n, device=device), chosen]  # (N, A)
    if explore:
        action = action + std[0] * torch.randn(action.shape, generator=generator, device=device)
    return Plan(action.clamp(-1.0, 1.0), mean)
