"""What the methods trained by backpropagation through a model share: their networks as environment agents, seeded noise.

Open-loop EfficientTrack (:mod:`.openloop`) and SuperTrack (:mod:`.supertrack`) train a policy π_φ of
:mod:`efficienttrack.learn.policy` through a dynamics model of :mod:`efficienttrack.learn.dynamics`, and are measured (and, for
SuperTrack, collect their data) through :func:`efficienttrack.envs.evaluate`, whose agent sees the environments'
332-value observation. :func:`policy_act` turns π_φ into such an agent:

- closed loop: π_φ = :class:`~efficienttrack.learn.policy.AdjustmentPolicy` with ``max_adjust`` = the system's bound, so
  the environment's action is ``a / max_adjust`` ∈ (−1, 1) (the environment sends ``q*_{t+1} + action · max_adjust``);
- open loop: π_φ = :class:`~efficienttrack.learn.policy.PWMPolicy`, whose output u / 1000 ∈ (−1, 1) is the action itself.

The observation's second history (the references sent, or the last actions) is what the policy's ``qref_hist`` is in
either loop, so the networks see in the environments what they saw in training.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import N_JOINTS, OBS_DIM
from efficienttrack.envs.core import FUTURE, HISTORY, check_loop
from efficienttrack.learn.policy import AdjustmentPolicy, PWMPolicy

Act = Callable[[np.ndarray], np.ndarray]
"""An agent: observations (N, 332) float32 → actions (N, 4) in [−1, 1]."""


class Observation(NamedTuple):
    """The environments' flat observation, unflattened (float32 tensors).

    Attributes:
        obs_hist: (N, h, 8) [rad, rad/s], ``o_{t−h+1} … o_t``.
        qref_hist: (N, h, 4), the references sent (rad, closed loop) or the last actions (PWM / 1000, open loop).
        qdes_future: (N, F, 4) rad, ``q*_{t+1} … q*_{t+F}``.
    """

    obs_hist: torch.Tensor
    qref_hist: torch.Tensor
    qdes_future: torch.Tensor


def split_observation(obs: np.ndarray, history: int = HISTORY, future: int = FUTURE) -> Observation:
    """Unflatten observations (:func:`efficienttrack.envs.core.observe` in reverse).

    Args:
        obs: (N, h·8 + h·4 + F·4) float32.
        history: h.
        future: F.

    Returns:
        The three parts.
    """
    flat = torch.as_tensor(np.asarray(obs, dtype=np.float32))
    n, a, b = len(flat), history * OBS_DIM, history * (OBS_DIM + N_JOINTS)
    if flat.shape[1:] != (b + future * N_JOINTS,):
        raise EfficientTrackError(f"observation: expected (N, {b + future * N_JOINTS}) values, got {tuple(flat.shape)}")
    return Observation(
        flat[:, :a].reshape(n, history, OBS_DIM),
        flat[:, a:b].reshape(n, history, N_JOINTS),
        flat[:, b:].reshape(n, future, N_JOINTS),
    )


def check_seen(policy: AdjustmentPolicy) -> None:
    """Refuse a policy that would see more than the environments show (h ≤ 21, F ≤ 20).

    Args:
        policy: the policy.

    Raises:
        EfficientTrackError: naming the policy config's ``horizon``.
    """
    if policy.cfg.history_length > HISTORY or policy.cfg.future_length > FUTURE:
        raise EfficientTrackError(
            f"policy.horizon {policy.cfg.horizon}: the environments show {HISTORY} past and {FUTURE} future steps; "
            f"use a horizon ≤ {FUTURE}"
        )


class Noise:
    """Seeded exploration noise for N machines, AR(1) in time: n_t = ρ n_{t−1} + √(1 − ρ²) σ ε_t, ε_t ~ N(0, 1).

    Args:
        sigma: σ, the stationary standard deviation, in action units (the environments' [−1, 1]).
        rho: ρ ∈ [0, 1), the correlation of consecutive steps (0: white noise).
        rng: the generator.
    """

    def __init__(self, sigma: float, rho: float, rng: np.random.Generator) -> None:
        self.sigma, self.rho, self.rng = sigma, rho, rng
        self._n: np.ndarray | None = None

    @property
    def last(self) -> np.ndarray | None:
        """The last (n, 4) noise drawn (None before the first draw): what the next one is correlated with."""
        return self._n

    def resume(self, last: np.ndarray | None) -> None:
        """Continue from a saved :attr:`last` (the generator's state is restored by its owner)."""
        self._n = last

    def __call__(self, n: int) -> np.ndarray:
        """The next (n, 4) noise; a new batch size starts from the stationary distribution."""
        fresh = self.rng.normal(0.0, self.sigma, size=(n, N_JOINTS))
        if self._n is None or len(self._n) != n:
            self._n = fresh
        else:
            self._n = self.rho * self._n + np.sqrt(1.0 - self.rho**2) * fresh
        return self._n


def policy_act(policy: AdjustmentPolicy | None, loop: str, noise: Noise | None = None) -> Act:
    """π_φ (None: zero actions) as an environment agent for :func:`efficienttrack.envs.evaluate`, optionally noisy.

    Args:
        policy: an :class:`~efficienttrack.learn.policy.AdjustmentPolicy` (closed loop; its ``max_adjust`` is the system's
            bound) or a :class:`~efficienttrack.learn.policy.PWMPolicy` (open loop), on the CPU; None for zero actions.
        loop: ``"closed"`` or ``"open"``.
        noise: exploration noise added to the action (then clipped by the environment), or None.

    Returns:
        observations (N, 332) float32 → actions (N, 4).
    """
    loop = check_loop(loop)
    if policy is not None:
        if (loop == "open") != isinstance(policy, PWMPolicy):
            raise EfficientTrackError(f"the {loop} loop cannot be driven by a {type(policy).__name__}")
        check_seen(policy)
        policy = policy.eval()
        scale = 1.0 if loop == "open" else np.asarray(policy.cfg.max_adjust)

    def act(obs: np.ndarray) -> np.ndarray:
        if policy is None:
            a = np.zeros((len(obs), N_JOINTS))
        else:
            with torch.inference_mode():
                a = policy(*split_observation(obs)).double().numpy() / scale
        return a if noise is None else a + noise(len(a))

    return act
