"""TOLD, TD-MPC's task-oriented latent dynamics model: encoder h, latent dynamics d, reward R, two Q-functions, π.

As in the public TD-MPC code (state observations): h is Linear → ELU → Linear; d, R and π are two hidden layers with
ELU; each Q is Linear → LayerNorm → tanh → Linear → ELU → Linear. Weights are orthogonal, biases zero, and the last
layers of R and of the Qs start at zero, and so does π's (unlike the public code): the untrained π sends a = 0, the PD
controller alone in the closed loop, as every learner here starts. Every network takes any leading batch shape
(``(..., features)``), so the planner runs (N machines × K sequences) in one call.
"""

from __future__ import annotations

from typing import cast

import torch
from torch import nn

from efficienttrack.baselines.tdmpc.settings import TDMPCSettings

NOISE_CLIP = 0.3
"""π's noise is clipped to ±this before it is added (the public code's truncated normal)."""


def _mlp(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ELU(), nn.Linear(hidden, hidden), nn.ELU(), nn.Linear(hidden, out_dim))


def _q(in_dim: int, hidden: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(in_dim, hidden), nn.LayerNorm(hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.ELU(), nn.Linear(hidden, 1)
    )


class TOLD(nn.Module):
    """The TOLD model of one agent.

    Args:
        obs_dim: D, the observation's length (332).
        action_dim: A, the action's length (4).
        settings: the sizes (``latent_dim``, ``hidden``, ``encoder_hidden``).
    """

    def __init__(self, obs_dim: int, action_dim: int, settings: TDMPCSettings) -> None:
        super().__init__()
        latent, hidden = settings.latent_dim, settings.hidden
        self.action_dim = action_dim
        self.h = nn.Sequential(
            nn.Linear(obs_dim, settings.encoder_hidden), nn.ELU(), nn.Linear(settings.encoder_hidden, latent)
        )
        self.d = _mlp(latent + action_dim, hidden, latent)
        self.R = _mlp(latent + action_dim, hidden, 1)
        self.pi_net = _mlp(latent, hidden, action_dim)
        self.Q1, self.Q2 = _q(latent + action_dim, hidden), _q(latent + action_dim, hidden)
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.orthogonal_(module.weight)
                nn.init.zeros_(module.bias)
        for last in (self.R[-1], self.Q1[-1], self.Q2[-1], self.pi_net[-1]):
            nn.init.zeros_(cast(nn.Linear, last).weight)  # _mlp and _q end in a Linear

    def encode(self, obs: torch.Tensor) -> torch.Tensor:
        """The latent state z = h(o).

        Args:
            obs: (..., D) observations.

        Returns:
            (..., latent_dim).
        """
        return self.h(obs)

    def next(self, z: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One latent step: the next latent state d(z, a) and the reward R(z, a).

        Args:
            z: (..., latent_dim).
            a: (..., A) in [−1, 1].

        Returns:
            ``(z_next (..., latent_dim), reward (...))``.
        """
        x = torch.cat([z, a], dim=-1)
        return self.d(x), self.R(x).squeeze(-1)

    def q(self, z: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Both Q-values.

        Args:
            z: (..., latent_dim).
            a: (..., A).

        Returns:
            ``(Q1 (...), Q2 (...))``.
        """
        x = torch.cat([z, a], dim=-1)
        return self.Q1(x).squeeze(-1), self.Q2(x).squeeze(-1)

    def pi(self, z: torch.Tensor, std: float = 0.0, generator: torch.Generator | None = None) -> torch.Tensor:
        """π's action: ``tanh(π(z))``, plus Gaussian noise of ``std`` when ``std`` > 0, clipped into [−1, 1].

        As the public code's truncated normal: the noise is clipped to ±``NOISE_CLIP``, and the action's clip into
        [−1, 1] passes the gradient to π's mean as if it were the identity.

        Args:
            z: (..., latent_dim).
            std: the noise's standard deviation (0: the mean action).
            generator: the torch generator the noise is drawn with.

        Returns:
            (..., A) in [−1, 1].
        """
        mu = torch.tanh(self.pi_net(z))
        if std <= 0:
            return mu
        eps = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype) * std
        noisy = mu + eps.clamp(-NOISE_CLIP, NOISE_CLIP)
        return noisy - (noisy - noisy.clamp(-1.0, 1.0)).detach()

    def model_parameters(self) -> list[nn.Parameter]:
        """The parameters the TOLD loss trains: h, d, R, Q1 and Q2 (π has its own optimizer).

        Returns:
            The parameters.
        """
        return [p for name, p in self.named_parameters() if not name.startswith("pi_net.")]
