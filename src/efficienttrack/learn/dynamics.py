"""The closed-loop dynamics model ô_{t+1} = o_t + g_θ(o_H, q^r_H, q^r_{t+1}), its multi-step trainer and its error.

The same model and trainer learn a plant's own (open-loop, PWM-level) dynamics ô_{t+1} = o_t + g_θ(o_H, u_H, u_t)
(:class:`PlantModel`, ``train_model(..., network=PlantModel)``): the input channel is then the command u / 1000
instead of the reference (:class:`~efficienttrack.data.dataset.Sequences` with ``channel="u"``), taken as it is instead of
relative to q_t. Everything else (scaling, loss, schedule) is shared.

Implementation choices (numbered, referenced in the docs):

1. Inputs are seen from the current position (:func:`~efficienttrack.data.features.relative_features`): past positions
   and references as wrapped differences to ``q_t``, so the model works on any machine's angle offsets; every
   feature is standardized with statistics of the training windows (buffers, saved with the weights).
2. The output ``g_θ`` is the change of the observation, ``tanh × bound`` per channel with
   ``bound = max(4 σ_Δ, 1.25 max |Δ|)`` of the recorded one-step changes Δ.
3. The multi-step loss is the paper's mean squared rollout error with each channel divided by its one-step
   change scale σ_Δ (positions and velocities have very different scales; position errors are wrapped).
4. Weight decay w is decoupled (AdamW): θ ← θ − lr·w·θ each step, the L2 term of the paper for plain SGD.
5. Windows are sampled uniformly with replacement from every start with a full horizon; a run is ``steps``
   optimizer steps (or ``epochs`` passes of ``windows / batch_size`` steps); optional cosine learning-rate decay.
6. The history the model sees may be shorter than the training horizon (``history``; the ``cpu`` preset uses
   5 steps = 0.25 s). On the XE75 logs (train: PD data, test: policy_round1_train), histories of 5 / 10 / 20
   steps gave Te.MPE 0.87° / 0.86° / 0.93° after 2000 steps, and 5 / 10 steps 0.77° / 0.80° after 4000 steps
   (Tr.MPE 0.39° / 0.37°): a short history generalizes better to policy-driven data.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import MAX_HORIZON
from efficienttrack.data.dataset import Sequences
from efficienttrack.data.features import relative_features
from efficienttrack.data.metrics import MPE_STEPS, position_error
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.windows import push
from efficienttrack.learn.checkpoints import load_checkpoint, save_checkpoint, warm_start
from efficienttrack.learn.nets import (
    MLP,
    Standardizer,
    check_size,
    check_training_memory,
    resolve_device,
)
from efficienttrack.learn.settings import ModelConfig
from efficienttrack.learn.training import TrainLoop, fingerprint, held_out_subset

NORM_SAMPLES = 65536
"""Windows used to fit the feature and output scaling."""
MPE_CHUNK = 8192
"""Windows per batch in :func:`model_error` (bounds memory)."""
HELD_OUT_TAG = "held_out/mpe_deg"
"""Scalar tag of the 20-step prediction error on held-out episodes, logged during training (docs/logged-metrics.md)."""
HELD_OUT_LABEL = "held-out 20-step MPE (°)"
"""What :data:`HELD_OUT_TAG` is, for plot axes."""
LOSS_LABEL = "multi-step loss (1/h) Σᵢ ‖(ô − o)/σ_Δ‖²"
"""What the model's training loss is, for plot axes (dimensionless: each channel in units of its σ_Δ)."""


class ClosedLoopModel(nn.Module):
    """g_θ: predicts the next observation of a closed-loop system from histories and the next reference.

    Args:
        cfg: the model config (sizes; history length ``cfg.history_length``).
    """

    channel = "q_ref"
    """What the model is driven by (:data:`~efficienttrack.data.dataset.CHANNELS`): the references sent."""
    kind = "closed_loop_model"
    """Its checkpoint kind (:func:`save_model`)."""
    delta_scale: torch.Tensor
    """(8,) σ_Δ: scale of the one-step change of each observation channel [rad, rad/s] (a buffer)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.features = Standardizer(cfg.in_dim)
        self.g_theta = MLP(cfg.in_dim, 8, cfg.hidden, cfg.layers)
        self.register_buffer("delta_scale", torch.ones(8))

    @torch.no_grad()
    def fit_scaling(
        self, obs_hist: torch.Tensor, qref_hist: torch.Tensor, qref_next: torch.Tensor, obs_next: torch.Tensor
    ) -> None:
        """Set feature statistics, σ_Δ and the output bound from recorded windows (shapes as in :meth:`forward`).

        Args:
            obs_hist: (N, h, 8) [rad, rad/s].
            qref_hist: (N, h, 4) rad.
            qref_next: (N, 4) rad, ``q^r_{t+1}``.
            obs_next: (N, 8) [rad, rad/s], the recorded ``o_{t+1}``.
        """
        self.features.fit(self._features(obs_hist, qref_hist, qref_next))
        delta = observation_error(obs_next, obs_hist[:, -1])
        scale = delta.std(0).clamp(min=1e-6)
        self.delta_scale.copy_(scale)
        self.g_theta.out_scale.copy_(torch.maximum(4 * scale, 1.25 * delta.abs().amax(0)))

    def forward(self, obs_hist: torch.Tensor, qref_hist: torch.Tensor, qref_next: torch.Tensor) -> torch.Tensor:
        """One step: ô_{t+1} = o_t + g_θ(o_H, q^r_H, q^r_{t+1}).

        Args:
            obs_hist: (B, h', 8) [rad, rad/s], ``o_{t−h'+1} … o_t`` with h' ≥ ``cfg.history_length`` (the last ones
                are used).
            qref_hist: (B, h', 4) rad, ``q^r_{t−h'+1} … q^r_t``.
            qref_next: (B, 4) rad, ``q^r_{t+1}``.

        Returns:
            (B, 8) [rad, rad/s], the predicted ``ô_{t+1}``.
        """
        return obs_hist[:, -1] + self.g_theta(self.features(self._features(obs_hist, qref_hist, qref_next)))

    def _features(self, obs_hist: torch.Tensor, qref_hist: torch.Tensor, qref_next: torch.Tensor) -> torch.Tensor:
        h = self.cfg.history_length
        return relative_features(obs_hist[:, -h:], qref_hist[:, -h:], qref_next[:, None])


class PlantModel(ClosedLoopModel):
    """g_θ of a plant itself (the open loop): ô_{t+1} = o_t + g_θ(o_H, u_H, u_t), u in PWM / 1000.

    The forward pass and :meth:`fit_scaling` take the commands where :class:`ClosedLoopModel` takes the references:
    ``qref_hist`` (B, h', 4) is ``u_{t−h'} … u_{t−1}`` and ``qref_next`` (B, 4) is ``u_t``, PWM / 1000. Its features are
    those of :func:`~efficienttrack.data.features.relative_features` with the commands taken as they are (``u_t`` appended to
    the command history), as many as the closed-loop model's.

    Args:
        cfg: the model config (sizes; history length ``cfg.history_length``).
    """

    channel = "u"
    """Driven by the commands u / 1000."""
    kind = "plant_model"
    """Its checkpoint kind (:func:`save_model`)."""

    def _features(self, obs_hist: torch.Tensor, qref_hist: torch.Tensor, qref_next: torch.Tensor) -> torch.Tensor:
        h = self.cfg.history_length
        commands = torch.cat([qref_hist[:, -h:], qref_next[:, None]], dim=1)
        return relative_features(obs_hist[:, -h:], commands, qref_next[:, :0, None], commands=True)


def observation_error(obs_a: torch.Tensor, obs_b: torch.Tensor) -> torch.Tensor:
    """Difference ``a − b`` of observations (..., 8): positions wrapped to (−π, π], velocities plain.

    Args:
        obs_a: (..., 8) [rad, rad/s], observations ``a``.
        obs_b: (..., 8) [rad, rad/s], observations ``b`` (broadcastable against ``obs_a``).

    Returns:
        (..., 8) [rad, rad/s], ``a − b``.
    """
    return torch.cat([wrap(obs_a[..., :4] - obs_b[..., :4]), obs_a[..., 4:] - obs_b[..., 4:]], dim=-1)


def rollout(
    model: ClosedLoopModel, obs_hist: torch.Tensor, qref_hist: torch.Tensor, qref_future: torch.Tensor
) -> torch.Tensor:
    """Roll the model on its own predictions, driven by the references ``q^r_{t+1} … q^r_{t+H}`` (or the commands).

    Args:
        model: g_θ.
        obs_hist: (B, h', 8) [rad, rad/s], recorded ``o_H`` at t (h' ≥ model h).
        qref_hist: (B, h', 4) rad, ``q^r_H`` at t (:class:`PlantModel`: ``u_H``, PWM / 1000).
        qref_future: (B, H, 4) rad, the references driving steps t+1 … t+H (:class:`PlantModel`: ``u_t … u_{t+H−1}``).

    Returns:
        (B, H, 8) [rad, rad/s], predicted ``ô_{t+1} … ô_{t+H}``.
    """
    predictions = []
    for i in range(qref_future.shape[1]):
        q_r = qref_future[:, i]
        o_hat = model(obs_hist, qref_hist, q_r)
        obs_hist, qref_hist = push(obs_hist, o_hat), push(qref_hist, q_r)
        predictions.append(o_hat)
    return torch.stack(predictions, dim=1)


class ModelTrainResult(NamedTuple):
    """Outcome of :func:`train_model`.

    Attributes:
        model: the trained g_θ (on the training device, eval mode).
        losses: (steps,) float, the multi-step loss of every optimizer step (normalized units).
        seconds: wall time of this call (a resumed run counts only its own part).
        steps: optimizer steps in total.
        windows: training windows available (starts with a full horizon).
        fingerprint: what it was trained from (:func:`~efficienttrack.learn.training.fingerprint`), for its checkpoint.
    """

    model: ClosedLoopModel
    losses: np.ndarray
    seconds: float
    steps: int
    windows: int
    fingerprint: str


def train_model(
    cfg: ModelConfig,
    records: Sequence[EpisodeRecord],
    device: str | torch.device = "auto",
    seed: int = 0,
    progress: bool = True,
    checkpoint: str | Path | None = None,
    log_dir: str | Path | None = None,
    held_out: Sequence[EpisodeRecord] = (),
    init: ClosedLoopModel | None = None,
    network: type[ClosedLoopModel] = ClosedLoopModel,
) -> ModelTrainResult:
    """Train g_θ by multi-step backpropagation through ``cfg.rollout_length``-step rollouts (Algorithm 1, TrainModel).

    Args:
        cfg: model config (see :data:`MODEL_PRESETS`).
        records: the training episodes.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``.
        seed: seeds initialization and window sampling; equal seeds give equal models on one device.
        progress: show a progress bar with the loss.
        checkpoint: training-state file; saved every ``cfg.save_every`` steps and at the end, resumed from
            when present (it must come from the same config).
        log_dir: folder for the scalar log (``scalars.csv`` and TensorBoard events; see :class:`TrainLog`), or None.
        held_out: episodes not trained on; with ``log_dir``, their 20-step MPE (:data:`HELD_OUT_TAG`, on at most
            :data:`~efficienttrack.learn.training.HELD_OUT_STEPS` recorded steps) is logged every ``cfg.eval_every`` steps.
        init: a trained g_θ to start from (a warm start, e.g. the previous round's), with its feature and output
            scaling; None starts from a fresh initialization scaled on ``records``.
        network: :class:`ClosedLoopModel` (driven by the recorded references) or :class:`PlantModel` (the open loop,
            driven by the recorded commands ``u``, which every record then needs).

    Returns:
        The model, per-step losses, time, steps and window count.
    """
    started = time.perf_counter()
    device = resolve_device(device)
    H = cfg.rollout_length
    check_training_memory("ModelConfig", cfg.batch_size, H, [cfg], device)
    torch.manual_seed(seed)
    data = Sequences(records, history=cfg.history_length, future=H, device=device, channel=network.channel)
    starts = data.starts(H)
    g_theta = network(cfg).to(device)
    if init is not None:
        if type(init) is not network:
            raise EfficientTrackError(f"initial model: a {type(init).__name__}, but a {network.__name__} is trained")
        warm_start(g_theta, init, "initial model")
    else:
        sample = data.window(starts[torch.randperm(len(starts))[:NORM_SAMPLES].to(device)], horizon=1)
        g_theta.fit_scaling(sample.obs_hist, sample.qref_hist, sample.qref_future[:, 0], sample.obs_future[:, 0])
    sigma = g_theta.delta_scale
    optimizer = torch.optim.AdamW(g_theta.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    inputs = fingerprint(records, seed, init)
    subset = held_out_subset(held_out)
    evaluate = (lambda: {HELD_OUT_TAG: model_error(g_theta, subset).mpe_deg}) if subset else None
    total = cfg.total_steps(len(starts))
    loop = TrainLoop("model", cfg, total, g_theta, optimizer, seed, checkpoint, progress, inputs, log_dir, evaluate)

    for step in loop:
        window = data.window(starts[loop.sample(len(starts), cfg.batch_size).to(device)], horizon=H)
        # rollout: ô_{t+1..t+H} on the model's own predictions, driven by the recorded q^r_{t+1..t+H}
        o_hat = rollout(g_theta, window.obs_hist, window.qref_hist, window.qref_future)
        # loss: (1/H) Σ_i ‖ô_{t+i} − o_{t+i}‖², each channel in units of its one-step change σ_Δ
        loss = (observation_error(o_hat, window.obs_future) / sigma).pow(2).sum(-1).mean()
        # step: Adam with decoupled weight decay w
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip is not None:
            nn.utils.clip_grad_norm_(g_theta.parameters(), cfg.grad_clip)
        loop.set_lr(step)
        optimizer.step()
        # log
        loop.record(step, loss.item())

    g_theta.eval()
    return ModelTrainResult(g_theta, loop.losses(), time.perf_counter() - started, loop.total, len(starts), inputs)


class MPE(NamedTuple):
    """Multi-step model prediction error (the paper's Tr.MPE / Te.MPE), positions only, degrees.

    Attributes:
        mpe_deg: mean |wrap(q̂ − q)| over all windows, steps and joints, deg.
        per_joint_deg: (4,) mean per joint (boom, arm, bucket, swing), deg.
        per_step_deg: (steps,) mean per prediction step (1 … steps), deg.
        windows: number of windows (starts with a full horizon).
    """

    mpe_deg: float
    per_joint_deg: list[float]
    per_step_deg: list[float]
    windows: int


@torch.inference_mode()
def model_error(
    model: ClosedLoopModel, records: Sequence[EpisodeRecord], steps: int = MPE_STEPS, device: str | torch.device | None = None
) -> MPE:
    """Multi-step prediction error (MPE) of the model on recorded episodes, in degrees.

    From every start with ``steps`` recorded steps ahead, roll the model driven by the recorded ``q^r`` (or ``u``)
    and compare the predicted positions with the recorded ones. All windows are batched (in chunks of
    :data:`MPE_CHUNK`); the only loop is over the steps.

    Args:
        model: g_θ.
        records: the episodes to evaluate on.
        steps: prediction horizon (paper 20).
        device: where to compute (the model's device when None).

    Returns:
        The error overall, per joint and per step, in degrees.
    """
    check_size("model_error", "steps", steps, 1, MAX_HORIZON)
    device = next(model.parameters()).device if device is None else resolve_device(device)
    was_training = model.training
    model.eval().to(device)
    data = Sequences(records, history=model.cfg.history_length, future=steps, device=device, channel=model.channel)
    starts = data.starts(steps)
    total = torch.zeros(steps, 4, dtype=torch.float64, device=device)
    for chunk in starts.split(MPE_CHUNK):
        window = data.window(chunk, horizon=steps)
        o_hat = rollout(model, window.obs_hist, window.qref_hist, window.qref_future)
        total += position_error(o_hat[..., :4], window.obs_future[..., :4]).sum(0).double()
    model.train(was_training)
    mean = torch.rad2deg(total / len(starts)).cpu().numpy()
    return MPE(float(mean.mean()), mean.mean(0).tolist(), mean.mean(1).tolist(), len(starts))


def save_model(model: ClosedLoopModel, path: str | Path, fingerprint: str | None = None) -> Path:
    """Save g_θ: state_dict at ``path`` (e.g. ``model.pt``) and its ModelConfig as JSON next to it (``model.json``).

    ``fingerprint`` is what it was trained from (``ModelTrainResult.fingerprint``), kept in the JSON; None when not known.
    """
    return save_checkpoint(model, model.kind, model.cfg, path, fingerprint)


def load_model(
    path: str | Path, device: str | torch.device = "cpu", network: type[ClosedLoopModel] = ClosedLoopModel
) -> ClosedLoopModel:
    """Load a model saved by :func:`save_model` (tensors only, ``weights_only=True``), in eval mode on ``device``.

    Args:
        path: the ``.pt`` file written by :func:`save_model`; its JSON config must lie next to it.
        device: where to put the model (``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or a torch device).
        network: the class saved: :class:`ClosedLoopModel` or :class:`PlantModel` (a file of the other is refused).
    """
    return load_checkpoint(path, network.kind, ModelConfig.from_stored, network, device)
