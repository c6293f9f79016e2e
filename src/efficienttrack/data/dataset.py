"""Windows for multi-step training; the runtime's rolling histories are padded the same way (:mod:`.windows`).

Time indexing (paper notation, T = len(record)):

- ``o_t = record.obs[t]``, t = 0 … T−1.
- ``q^r_{t+1} = record.q_ref[t]`` and ``q*_{t+1} = record.q_des[t]``, t = 0 … T−1; ``q^r_0 := q*_0 := q_0``.
- History of length h at time t: ``o_H = (o_{t−h+1} … o_t)``, ``q^r_H = (q^r_{t−h+1} … q^r_t)``, padded at the
  episode start with ``o_0`` / ``q^r_0``.
- The open loop (``channel="u"``) puts the commands where the references are: the channel at time t holds
  ``u_{t−1} / 1000`` (``record.u[t−1]``, PWM / 1000, the action of the open-loop environment), so ``q^r_H`` becomes
  the last commands ``u_{t−h} … u_{t−1}`` (padded with 0, the machine at rest, as the environment pads its actions)
  and ``q^r_{t+1}`` the command ``u_t`` applied at step t.
- Future desired positions ``q*_F = (q*_{t+1} … q*_{t+F})``, padded past the episode end with the last desired
  position (``q_des[T−1]``); future references past the end likewise repeat ``q_ref[T−1]``.

:class:`Sequences` stores all episodes once, each padded in front by h−1 copies of its start and behind by
``future`` copies of its end, as flat tensors; a window is a gather at ``flat index of t + offsets``, so
sampling a batch is one indexing operation (on the training device).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import PWM_SCALE
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.windows import window_starts

# ------------------------------------------------------------------------------------------- training windows

CHANNELS = ("q_ref", "u")
"""What the input channel of the windows holds: the references sent (closed loop) or the commands / 1000 (open loop)."""


class Window(NamedTuple):
    """A batch of B training windows starting at times t (float32 tensors on the buffer's device).

    Attributes:
        obs_hist: (B, h, 8) [rad, rad/s], ``o_{t−h+1} … o_t``.
        qref_hist: (B, h, 4) rad, ``q^r_{t−h+1} … q^r_t`` (open loop: ``u_{t−h} … u_{t−1}``, PWM / 1000).
        qref_future: (B, H, 4) rad, ``q^r_{t+1} … q^r_{t+H}`` (recorded references; open loop: ``u_t … u_{t+H−1}``).
        obs_future: (B, H, 8) [rad, rad/s], ``o_{t+1} … o_{t+H}`` (recorded observations; the targets).
        qdes_future: (B, F, 4) rad, ``q*_{t+1} … q*_{t+F}``.
    """

    obs_hist: torch.Tensor
    qref_hist: torch.Tensor
    qref_future: torch.Tensor
    obs_future: torch.Tensor
    qdes_future: torch.Tensor


class Sequences:
    """All episodes, padded and concatenated, ready for window gathers.

    Args:
        records: the episodes (each validated ``EpisodeRecord``).
        history: h, the history length of the windows.
        future: how many steps past t a window may look (≥ the rollout horizon; the policy's ``desired_length``).
        device: where the tensors live.
        channel: ``"q_ref"`` (the references sent, closed loop) or ``"u"`` (the commands / 1000, open loop; every
            record needs ``u``), what the ``q_ref`` tensors and the windows' ``qref_*`` hold (module docstring).

    Attributes:
        obs: (L, 8) float32 [rad, rad/s], padded observations.
        q_ref: (L, 4) float32 rad, padded ``q^r`` (open loop: padded ``u / 1000``).
        q_des: (L, 4) float32 rad, padded ``q*``.
        origin: (E,) int64, flat index of t = 0 of each episode.
        lengths: (E,) int64, T of each episode.
    """

    def __init__(
        self,
        records: Sequence[EpisodeRecord],
        history: int,
        future: int,
        device: torch.device | str = "cpu",
        channel: str = "q_ref",
    ) -> None:
        if history < 1 or future < 1:
            raise EfficientTrackError(f"windows need history ≥ 1 and future ≥ 1, got {history} and {future}")
        if not records:
            raise EfficientTrackError("no episode records given to build training windows from")
        if channel not in CHANNELS:
            raise EfficientTrackError(f"windows: channel must be one of {', '.join(CHANNELS)}, got {channel!r}")
        if channel == "u" and any(record.u is None for record in records):
            name = next(record.meta.get("name", "?") for record in records if record.u is None)
            raise EfficientTrackError(f"open-loop windows need the PWM u of every record; record '{name}' has none")
        self.history, self.future, self.device, self.channel = history, future, torch.device(device), channel
        front = history - 1
        obs, q_ref, q_des, origin, lengths, offset = [], [], [], [], [], 0
        for record in records:
            o = record.obs
            q0 = record.q[:1]
            T = len(o)
            obs.append(np.concatenate([np.repeat(o[:1], front, 0), o, np.repeat(o[-1:], future, 0)]))
            # q^r_t / q*_t for t = 0 … T (t = 0 is q_0), then padding: row front + t holds time t
            if channel == "q_ref":
                start, channel_values = q0, record.q_ref
            else:
                assert record.u is not None  # the "u" channel was checked above: every record has its PWM
                start, channel_values = np.zeros((1, 4)), record.u / PWM_SCALE
            q_ref.append(
                np.concatenate([np.repeat(start, front + 1, 0), channel_values, np.repeat(channel_values[-1:], future - 1, 0)])
            )
            q_des.append(
                np.concatenate([np.repeat(q0, front + 1, 0), record.q_des, np.repeat(record.q_des[-1:], future - 1, 0)])
            )
            origin.append(offset + front)
            lengths.append(T)
            offset += front + T + future

        def tensor(parts: list[np.ndarray]) -> torch.Tensor:
            return torch.as_tensor(np.concatenate(parts), dtype=torch.float32, device=self.device)

        self.obs, self.q_ref, self.q_des = tensor(obs), tensor(q_ref), tensor(q_des)
        self.origin = torch.as_tensor(origin, dtype=torch.int64)
        self.lengths = torch.as_tensor(lengths, dtype=torch.int64)
        self._hist_offsets = torch.arange(-front, 1, device=self.device)
        self._future_offsets = torch.arange(1, future + 1, device=self.device)

    @property
    def steps(self) -> int:
        """Total recorded steps Σ T."""
        return int(self.lengths.sum())

    def starts(self, horizon: int) -> torch.Tensor:
        """Flat indices of every t with a full recorded horizon, t + horizon ≤ T − 1 (:func:`window_starts`).

        Args:
            horizon: steps of recorded future the windows need (model: rollout length; policy: 0).

        Returns:
            (M,) int64 on the buffer's device, episode by episode in time order.

        Raises:
            EfficientTrackError: no episode is long enough, or the horizon exceeds ``future``.
        """
        if horizon > self.future:
            raise EfficientTrackError(f"windows of horizon {horizon} need future ≥ {horizon}, the buffer has {self.future}")
        episode, t0 = window_starts(self.lengths.numpy(), horizon)
        return torch.as_tensor(self.origin.numpy()[episode] + t0, device=self.device)

    def window(self, start: torch.Tensor, horizon: int, desired: int = 0) -> Window:
        """Gather windows at flat indices ``start`` (B,) (from :meth:`starts`), batch-major (B, H, C) for torch.

        The simulator fit gathers the same windows time-major (H, W, C) (:func:`efficienttrack.systems.fit.make_windows`).

        Args:
            start: (B,) int64 flat indices of t.
            horizon: H, recorded future steps (references and target observations) to include.
            desired: F, future desired positions to include (≤ ``future``).

        Returns:
            The batch of windows.
        """
        s = start[:, None]
        hist = s + self._hist_offsets
        ahead = s + self._future_offsets[:horizon]
        want = s + self._future_offsets[:desired]
        return Window(
            obs_hist=self.obs[hist],
            qref_hist=self.q_ref[hist],
            qref_future=self.q_ref[ahead],
            obs_future=self.obs[ahead],
            qdes_future=self.q_des[want],
        )
