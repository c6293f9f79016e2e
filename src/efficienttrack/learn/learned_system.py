"""A trained closed-loop dynamics model as a reference-level system: a learned simulator of a machine under its controller.

``load_system("learned", model="model.pt")`` (``--system learned --system-opt model=model.pt`` on the CLI) drives
the model g_θ of :mod:`efficienttrack.learn.dynamics` on its own predictions, one reference at a time, so that it can
stand wherever a :class:`~efficienttrack.systems.protocol.ClosedLoopSystem` can: ``sim fidelity`` compares it
with real logs exactly as it does the physical simulator, and ``evaluate`` runs a policy against it. A reset puts
every machine at rest with a history of that one observation and the reference at its position, as the training
windows begin an episode; ``reset_machines`` does the same for some machines while the others run on, so the
environments can run N episodes side by side on it (:class:`~efficienttrack.envs.TrackingVectorEnv`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT, N_JOINTS, OBS_DIM, SWING
from efficienttrack.data.windows import push
from efficienttrack.learn.dynamics import ClosedLoopModel, load_model
from efficienttrack.learn.nets import resolve_device


class LearnedSystem:
    """A :class:`~efficienttrack.learn.dynamics.ClosedLoopModel` stepped as a batched ClosedLoopSystem.

    ====== ============ ========================== ==========================================
    name   shape        unit                       meaning
    ====== ============ ========================== ==========================================
    q0     (4,)/(N, 4)  rad                        ``reset``: positions, at rest
    index  (K,)         –                          ``reset_machines``: which machines restart
    q_ref  (4,)/(N, 4)  rad                        ``step``: the reference for the next step
    obs    (8,)/(N, 8)  [q rad, q̇ rad/s]           the model's prediction (swing wrapped to (−π, π])
    ====== ============ ========================== ==========================================

    Output rank follows the ``q0`` given to ``reset``.

    Args:
        model: the trained model g_θ.
        dt: control period the model was trained at, s (the logs' sample period).
        device: where to run the model: ``"auto"``, ``"cpu"``, ``"cuda"``.
    """

    batched = True

    def __init__(self, model: ClosedLoopModel, dt: float = DT, device: str | torch.device = "auto") -> None:
        if not dt > 0:
            raise EfficientTrackError(f"learned system: dt must be a positive number of seconds, got {dt!r}")
        self.device = resolve_device(device)
        self.model = model.to(self.device).eval()
        self.dt = float(dt)
        self._obs_hist: torch.Tensor | None = None
        self._qref_hist: torch.Tensor | None = None
        self._single = False

    @torch.inference_mode()
    def reset(self, q0: np.ndarray) -> np.ndarray:
        """Machines at rest at ``q0`` (4,)/(N, 4) rad; return obs (8,)/(N, 8)."""
        q0 = np.asarray(q0, dtype=np.float64)
        if q0.shape[-1:] != (N_JOINTS,) or q0.ndim not in (1, 2):
            raise EfficientTrackError(f"learned system: reset expects q0 of shape (4,) or (N, 4), got {q0.shape}")
        self._single = q0.ndim == 1
        obs, history = self._at_rest(q0.reshape(-1, N_JOINTS))
        self._obs_hist, self._qref_hist = history, history[..., :N_JOINTS].clone()
        return obs[0] if self._single else obs

    @torch.inference_mode()
    def reset_machines(self, index: np.ndarray, q0: np.ndarray) -> np.ndarray:
        """Put machines ``index`` (K,) at rest at ``q0`` (K, 4) rad, as :meth:`reset` does; the others run on.

        The indices and shapes are checked by the system protocol's wrapper
        (:meth:`~efficienttrack.systems.protocol.BatchedSystem.reset_machines`), as for the other systems.

        Returns:
            (K, 8) [rad, rad/s], their observations.
        """
        if self._obs_hist is None or self._qref_hist is None or self._single:
            raise EfficientTrackError("learned system: reset_machines needs a batched reset (N, 4) first")
        obs, history = self._at_rest(np.asarray(q0, dtype=np.float64))
        rows = torch.as_tensor(np.asarray(index, dtype=np.int64), device=self.device)
        self._obs_hist[rows], self._qref_hist[rows] = history, history[..., :N_JOINTS]
        return obs

    def _at_rest(self, q0: np.ndarray) -> tuple[np.ndarray, torch.Tensor]:
        """Observations (K, 8) of machines at rest at ``q0`` (K, 4), and their history (K, h, 8): that one repeated."""
        obs = np.hstack([q0, np.zeros_like(q0)])
        h = self.model.cfg.history_length
        return obs, torch.as_tensor(obs, dtype=torch.float32, device=self.device)[:, None].repeat(1, h, 1)

    @torch.inference_mode()
    def step(self, q_ref: np.ndarray) -> np.ndarray:
        """Track ``q_ref`` (4,)/(N, 4) rad for one period; return the predicted obs (8,)/(N, 8)."""
        if self._obs_hist is None or self._qref_hist is None:
            raise EfficientTrackError("learned system: step called before reset")
        n = len(self._obs_hist)
        q_ref = np.asarray(q_ref, dtype=np.float64)
        if q_ref.size != n * N_JOINTS:
            raise EfficientTrackError(f"learned system: step expects q_ref of shape ({n}, 4) after reset, got {q_ref.shape}")
        q_r = torch.as_tensor(q_ref.reshape(n, N_JOINTS), dtype=torch.float32, device=self.device)
        obs = self.model(self._obs_hist, self._qref_hist, q_r)
        obs[:, SWING] = wrap(obs[:, SWING])
        self._obs_hist, self._qref_hist = push(self._obs_hist, obs), push(self._qref_hist, q_r)
        return self._out(obs)

    def _out(self, obs: torch.Tensor) -> np.ndarray:
        out = obs.double().cpu().numpy().reshape(-1, OBS_DIM)
        return out[0] if self._single else out


def learned_system(model: str | Path, dt: float = DT, device: str = "auto") -> LearnedSystem:
    """The built-in system ``learned``: a model checkpoint from ``train-model`` (or ``run``) as a simulator.

    Args:
        model: the model checkpoint (``model.pt``, its ``model.json`` next to it).
        dt: control period the model was trained at, s.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``.

    Returns:
        A batched :class:`LearnedSystem`.
    """
    return LearnedSystem(load_model(model, device=device), dt=float(dt), device=device)
