"""TD-MPC's prioritized replay of H-step sequences: a ring of transitions, sampled ∝ priority^α with weights^β.

Transitions are stored in the order they happen. A sequence of H steps may start at position i once the H − 1
transitions after it, of the same episode, have been stored: from then on i has a priority (the largest seen so far,
as new data in the public code); before, and once i is overwritten, it has none and is never drawn. Sampling draws
B starts with probability ``P(i) = p_i^α / Σ p^α`` (``numpy.random.Generator.choice``, one call for the batch, no loop
over samples) and returns the importance weights ``(n · P(i))^−β / max``, n the number of starts that can be drawn.
After an update the starts' priorities become the sequences' TD errors (:meth:`PrioritizedBuffer.update`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from efficienttrack.core.errors import EfficientTrackError

PRIORITY_EPS = 1e-6
"""Added to every updated priority, so that no sequence drops out for good."""


class Sequences(NamedTuple):
    """A batch of B sequences of H steps (numpy, float32 except ``index``).

    Attributes:
        obs: (B, D) the first observations o_t.
        next_obs: (H, B, D) o_{t+1} … o_{t+H}.
        action: (H, B, A) a_t … a_{t+H−1}.
        reward: (H, B) r_t … r_{t+H−1}.
        index: (B,) int, the starts' positions (for :meth:`PrioritizedBuffer.update`).
        weight: (B,) importance weights in (0, 1].
    """

    obs: np.ndarray
    next_obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    index: np.ndarray  # type: ignore[assignment]  # a field named like tuple.index, which it hides
    weight: np.ndarray


class PrioritizedBuffer:
    """A prioritized replay buffer of transitions, sampled as H-step sequences.

    Args:
        capacity: transitions held; the oldest are overwritten.
        obs_dim: D.
        action_dim: A.
        horizon: H, the length of the sequences sampled.
        alpha: priority exponent α (0: uniform).
        beta: importance-weight exponent β (0: no correction).
    """

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, horizon: int, alpha: float, beta: float) -> None:
        if capacity < horizon:
            raise EfficientTrackError(f"replay buffer: capacity {capacity} is shorter than a sequence of {horizon} steps")
        self.capacity, self.horizon, self.alpha, self.beta = capacity, horizon, alpha, beta
        self.obs = np.zeros((capacity, obs_dim), dtype=np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), dtype=np.float32)
        self.action = np.zeros((capacity, action_dim), dtype=np.float32)
        self.reward = np.zeros(capacity, dtype=np.float32)
        self.priority = np.zeros(capacity, dtype=np.float64)
        """Priority of the sequence starting at each position; 0 where none may start."""
        self.max_priority = 1.0
        self.position = 0
        """Where the next transition goes."""
        self.run = 0
        """Transitions of the current episode stored so far."""

    @property
    def starts(self) -> int:
        """How many sequences can be drawn now."""
        return int(np.count_nonzero(self.priority))

    def add(self, obs: np.ndarray, action: np.ndarray, reward: float, next_obs: np.ndarray, first: bool) -> None:
        """Store one transition (o_t, a_t, r_t, o_{t+1}).

        Args:
            obs: (D,) o_t.
            action: (A,) a_t.
            reward: r_t.
            next_obs: (D,) o_{t+1} (the final observation when the episode ended with this step).
            first: this is the first transition of an episode.
        """
        i = self.position
        self.obs[i], self.action[i], self.reward[i], self.next_obs[i] = obs, action, reward, next_obs
        self.priority[i] = 0.0
        self.run = 1 if first else self.run + 1
        if self.run >= self.horizon:
            self.priority[(i - self.horizon + 1) % self.capacity] = self.max_priority
        self.position = (i + 1) % self.capacity

    def sample(self, batch: int, rng: np.random.Generator) -> Sequences:
        """Draw ``batch`` sequences ∝ priority^α (with replacement).

        Args:
            batch: B.
            rng: the generator drawn with.

        Returns:
            The sequences and their importance weights.

        Raises:
            EfficientTrackError: no sequence can be drawn yet.
        """
        scaled = self.priority**self.alpha * (self.priority > 0)
        total = scaled.sum()
        if total <= 0:
            raise EfficientTrackError(f"replay buffer: no sequence of {self.horizon} steps stored yet")
        probs = scaled / total
        index = rng.choice(self.capacity, size=batch, p=probs)
        weight = (self.starts * probs[index]) ** -self.beta
        steps = (index[None, :] + np.arange(self.horizon)[:, None]) % self.capacity  # (H, B)
        return Sequences(
            obs=self.obs[index],
            next_obs=self.next_obs[steps],
            action=self.action[steps],
            reward=self.reward[steps],
            index=index,
            weight=(weight / weight.max()).astype(np.float32),
        )

    def update(self, index: np.ndarray, priority: np.ndarray) -> None:
        """Set the priorities of sampled starts (their TD errors) and raise the maximum given to new sequences.

        Args:
            index: (B,) the starts (:attr:`Sequences.index`).
            priority: (B,) their new priorities, ≥ 0 (``PRIORITY_EPS`` is added).
        """
        alive = self.priority[index] > 0  # a start overwritten since it was drawn stays out
        values = np.asarray(priority, dtype=np.float64) + PRIORITY_EPS
        self.priority[index[alive]] = values[alive]
        self.max_priority = max(self.max_priority, float(values.max()))
