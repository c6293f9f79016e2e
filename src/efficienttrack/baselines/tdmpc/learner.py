"""TD-MPC's learning: the TOLD loss over H-step sequences, π's update through Q, the target network.

One update (:meth:`Learner.update`), as in the public TD-MPC code:

1. Encode o_t, then roll the latent dynamics over the sampled actions: z_{t+1} = d(z_t, a_t), r̂_t = R(z_t, a_t).
2. Per step t (weight ρ^t): consistency ``‖z_{t+1} − h⁻(o_{t+1})‖²`` (mean over the latent; h⁻ the target encoder),
   reward ``(r̂_t − r_t)²``, value ``Σ_i (Q_i(z_t, a_t) − y_t)²`` with the TD target
   ``y_t = r_t + γ min_i Q⁻_i(h(o_{t+1}), π(h(o_{t+1})))`` (Q⁻ the target Qs, π with noise ``min_std``).
3. Loss = c_cons · consistency + c_rew · reward + c_val · value per sequence, times its importance weight, mean over
   the batch, gradients scaled by 1/H, clipped to ``grad_clip_norm``; one Adam step on h, d, R, Q1, Q2.
4. The sequences' priorities become ``Σ_t ρ^t Σ_i |Q_i − y_t|``.
5. π: maximize ``Σ_t ρ^t min_i Q_i(z_t, π(z_t))`` over the (detached) latents of step 1, Q frozen; one Adam step.
6. Every ``target_every`` updates: h⁻, Q⁻ ← (1 − τ) · h⁻, Q⁻ + τ · h, Q (Polyak).
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import torch
from torch import nn

from efficienttrack.baselines.tdmpc.buffer import Sequences
from efficienttrack.baselines.tdmpc.networks import TOLD
from efficienttrack.baselines.tdmpc.settings import TDMPCSettings

LOSS_CLAMP = 1e4
"""Each loss term is clamped to this per sequence (the public code's guard against divergence)."""


class UpdateInfo(NamedTuple):
    """The losses of one update (batch means, before the importance weights), for logs and tests.

    Attributes:
        consistency: the latent consistency loss.
        reward: the reward loss.
        value: the value loss.
        pi: π's loss (−ρ-weighted Q).
        total: the weighted TOLD loss that was minimized.
    """

    consistency: float
    reward: float
    value: float
    pi: float
    total: float


class Learner:
    """TOLD, its target copy, the two optimizers and the update.

    Args:
        model: the TOLD model to train (its target is a copy made here).
        settings: the loss weights, ρ, γ, learning rate, clip, τ, target period, ``min_std``.
        generator: torch generator of π's noise in the TD target and π's loss.
    """

    def __init__(self, model: TOLD, settings: TDMPCSettings, generator: torch.Generator) -> None:
        self.model, self.settings, self.generator = model, settings, generator
        self.target = copy.deepcopy(model).requires_grad_(False)
        self.model_params, self.pi_params = model.model_parameters(), list(model.pi_net.parameters())
        self.optim = torch.optim.Adam(self.model_params, lr=settings.learning_rate, foreach=True)
        self.pi_optim = torch.optim.Adam(self.pi_params, lr=settings.learning_rate, foreach=True)
        self.updates = 0

    def update(self, batch: Sequences) -> tuple[UpdateInfo, torch.Tensor]:
        """One update on a batch of sequences (see the module docstring).

        Args:
            batch: B sequences of H steps from the replay buffer.

        Returns:
            The losses, and the sequences' new priorities (B,) on the CPU.
        """
        s, model, device = self.settings, self.model, next(self.model.parameters()).device
        obs, next_obs, action, reward, weight = (
            torch.as_tensor(x, device=device) for x in (batch.obs, batch.next_obs, batch.action, batch.reward, batch.weight)
        )
        horizon = action.shape[0]
        # targets of every step at once (as TD-MPC2), from the observed next observations (H, B, D)
        with torch.no_grad():
            next_z = model.encode(next_obs)
            target_q = torch.minimum(*self.target.q(next_z, model.pi(next_z, s.min_std, self.generator)))
            td_target = reward + s.discount * target_q
            target_z = self.target.encode(next_obs)
        # rollout: latents predicted from the first observation
        z = model.encode(obs)
        latents = [z.detach()]
        consistency = torch.zeros_like(weight)
        reward_loss, value_loss, priority = torch.zeros_like(weight), torch.zeros_like(weight), torch.zeros_like(weight)
        for t in range(horizon):
            q1, q2 = model.q(z, action[t])
            z, reward_pred = model.next(z, action[t])
            latents.append(z.detach())
            rho = s.rho**t
            consistency = consistency + rho * (z - target_z[t]).pow(2).mean(-1)
            reward_loss = reward_loss + rho * (reward_pred - reward[t]).pow(2)
            value_loss = value_loss + rho * ((q1 - td_target[t]).pow(2) + (q2 - td_target[t]).pow(2))
            priority = priority + rho * ((q1 - td_target[t]).abs() + (q2 - td_target[t]).abs()).detach()
        # loss: weighted by the importance weights, gradients scaled by 1/H, clipped
        total = (
            s.consistency_coef * consistency.clamp(max=LOSS_CLAMP)
            + s.reward_coef * reward_loss.clamp(max=LOSS_CLAMP)
            + s.value_coef * value_loss.clamp(max=LOSS_CLAMP)
        )
        weighted = (total * weight).mean()
        self.optim.zero_grad(set_to_none=True)
        (weighted / horizon).backward()
        nn.utils.clip_grad_norm_(self.model_params, s.grad_clip_norm, foreach=True)
        self.optim.step()
        # π: through the (frozen) Qs, on the latents of the rollout
        pi_loss = self._update_pi(torch.stack(latents))
        # target network
        self.updates += 1
        if self.updates % s.target_every == 0:
            with torch.no_grad():
                for target, online in zip(self.target.parameters(), model.parameters(), strict=True):
                    target.lerp_(online, s.tau)
        info = UpdateInfo(
            consistency=float(consistency.detach().mean()),
            reward=float(reward_loss.detach().mean()),
            value=float(value_loss.detach().mean()),
            pi=pi_loss,
            total=float(weighted.detach()),
        )
        return info, priority.clamp(max=LOSS_CLAMP).cpu()

    def _update_pi(self, latents: torch.Tensor) -> float:
        s, model = self.settings, self.model
        rho = s.rho ** torch.arange(len(latents), device=latents.device, dtype=latents.dtype)  # (H + 1,)
        q1, q2 = model.q(latents, model.pi(latents, s.min_std, self.generator))  # (H + 1, B)
        loss = -(torch.minimum(q1, q2).mean(1) * rho).sum()
        self.pi_optim.zero_grad(set_to_none=True)
        loss.backward(inputs=self.pi_params)
        nn.utils.clip_grad_norm_(self.pi_params, s.grad_clip_norm, foreach=True)
        self.pi_optim.step()
        return float(loss.detach())
