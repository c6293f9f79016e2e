"""The trajectory adjustment policy a_t = π_φ(o_H, q^r_H, q*_F), q^r_{t+1} = q*_{t+1} + a_t, and its trainer.

The policy is trained by multi-step backpropagation through the frozen closed-loop dynamics model: from each
recorded window, the model is rolled h steps under the policy with the future desired positions, and the loss
is the paper's discounted tracking error plus the smoothness regularizer

    L(φ) = (1/h) Σ_{i=1..h} γ^i ‖wrap(q̂_{t+i} − q*_{t+i})‖² + k_smooth (1/(h−1)) Σ_{i=2..h} ‖a_{t+i} − a_{t+i−1}‖²

in rad² (the paper's units, for which γ = 0.98 and k_smooth = 1.0 are tuned). Implementation choices:

1. Inputs as for the model (:func:`~efficienttrack.data.features.relative_features`, standardized on the training windows),
   with the h future desired positions as targets.
2. The output is ``tanh × max_adjust`` per joint, and its last layer starts at zero: the untrained policy is
   the position controller alone (a = 0).
3. Windows start at every recorded step; desired positions past an episode's end repeat its last one.
4. With ``burn_in`` B > 0, the policy first drives the model B steps from the window's start without gradient, and the
   loss is taken over the h steps after them: the histories it then sees hold its own adjustments, as when deployed,
   where the recorded windows hold the collection's references and noise. Windows start where B steps still lie
   within the episode; with ``burn_in_share`` below 1, the rest of each batch are recorded windows from any step.
5. With ``imagined_share`` > 0, that share of each batch are imagined deployments carried across optimizer steps
   (truncated backpropagation through whole episodes, :class:`ImaginedDeployments`); the rest are recorded windows.
6. With ``truncate`` K > 0, the gradient through the predicted histories is cut every K steps of the rollout; with
   ``row_cap`` τ > 0, each window's gradient through them is cut to τ × the batch's median at every step.

The open loop (:class:`PWMPolicy` through a :class:`~efficienttrack.learn.dynamics.PlantModel`): the policy outputs the
command u_t / 1000 = π_φ(o_H, u_H, q*_F) ∈ (−1, 1)⁴ (tanh × 1: PWM within ±1000), the model is driven by it, and the
smoothness term weighs the change of the command (PWM / 1000)². The loss and the trainer are the same.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import ENV_FUTURE
from efficienttrack.data.dataset import Sequences
from efficienttrack.data.features import relative_features
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.windows import push
from efficienttrack.learn.checkpoints import load_checkpoint, save_checkpoint, warm_start
from efficienttrack.learn.dynamics import NORM_SAMPLES, ClosedLoopModel
from efficienttrack.learn.nets import (
    MLP,
    Standardizer,
    check_training_memory,
    resolve_device,
)
from efficienttrack.learn.settings import PolicyConfig
from efficienttrack.learn.training import TrainLoop, fingerprint, held_out_subset

EVAL_CHUNK = 8192
"""Windows per batch in :func:`predicted_tracking_error`."""
HELD_OUT_TAG = "held_out/tracking_error_deg"
"""Scalar tag of the model-predicted tracking error on held-out episodes, logged during training (docs/logged-metrics.md)."""
HELD_OUT_LABEL = "held-out model-predicted tracking error (°)"
"""What :data:`HELD_OUT_TAG` is, for plot axes."""
LOSS_LABEL = "L_track + k_smooth·L_reg (rad²)"
"""What the policy's training loss is, for plot axes."""


class SeenLengths(NamedTuple):
    """What a policy sees at time t.

    Attributes:
        history: h, length of the histories o_H, q^r_H.
        future: F, future desired positions q*_F.
    """

    history: int
    future: int


def seen_lengths(cfg: PolicyConfig | None) -> SeenLengths:
    """History and future lengths a policy with config ``cfg`` sees; (1, 1) without a policy (a = 0 needs q*_{t+1}).

    Args:
        cfg: the policy's config, or None for the position controller alone.
    """
    return SeenLengths(1, 1) if cfg is None else SeenLengths(cfg.history_length, cfg.future_length)


def desired_length(cfg: PolicyConfig | None, steps: int) -> int:
    """Future desired positions a ``steps``-step rollout under the policy needs: q*_{t+1} … q*_{t+steps−1+F}.

    Args:
        cfg: the policy's config, or None for the position controller alone (F = 1).
        steps: H, rollout length.
    """
    return steps - 1 + seen_lengths(cfg).future


class AdjustmentPolicy(nn.Module):
    """π_φ: the bounded adjustment added to the next desired position.

    Args:
        cfg: the policy config (sizes, ``history_length`` h, ``future_length`` F, ``max_adjust``).
    """

    channel = "q_ref"
    """What the policy's output drives (:data:`~efficienttrack.data.dataset.CHANNELS`): the reference, q*_{t+1} + a_t."""
    kind = "adjustment_policy"
    """Its checkpoint kind (:func:`save_policy`)."""

    def __init__(self, cfg: PolicyConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.features = Standardizer(cfg.in_dim)
        self.pi_phi = MLP(cfg.in_dim, 4, cfg.hidden, cfg.layers, out_scale=self._bound(cfg))
        last = self.pi_phi.body[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    @torch.no_grad()
    def fit_scaling(self, obs_hist: torch.Tensor, qref_hist: torch.Tensor, qdes_future: torch.Tensor) -> None:
        """Set the feature statistics from recorded windows (shapes as in :meth:`forward`).

        Args:
            obs_hist: (B, h', 8) [rad, rad/s], recorded observation histories, h' ≥ h (the last h are used).
            qref_hist: (B, h', 4) rad, the matching reference histories.
            qdes_future: (B, F', 4) rad, the desired positions that follow, F' ≥ F (the first F are used).
        """
        self.features.fit(self._features(obs_hist, qref_hist, qdes_future))

    def forward(self, obs_hist: torch.Tensor, qref_hist: torch.Tensor, qdes_future: torch.Tensor) -> torch.Tensor:
        """a_t = π_φ(o_H, q^r_H, q*_F).

        Args:
            obs_hist: (B, h', 8) [rad, rad/s], ``o_{t−h'+1} … o_t``, h' ≥ h (the last h are used).
            qref_hist: (B, h', 4) rad, ``q^r_{t−h'+1} … q^r_t``.
            qdes_future: (B, F', 4) rad, ``q*_{t+1} … q*_{t+F'}``, F' ≥ F (the first F are used).

        Returns:
            (B, 4) rad, the adjustment a_t, |a| < max_adjust per joint.
        """
        return self.pi_phi(self.features(self._features(obs_hist, qref_hist, qdes_future)))

    @torch.no_grad()
    def predict(
        self,
        observation: np.ndarray,
        state: object = None,
        episode_start: object = None,
        deterministic: bool = True,
        future: int | None = None,
    ) -> tuple[np.ndarray, object]:
        """The policy as an agent of the environments (``EfficientTrack/ClosedLoop-v0``, SB3's ``evaluate_policy``).

        Args:
            observation: (D,) or (N, D), the environments' flat observation (:func:`efficienttrack.envs.core.observe`:
                h observations, h references, F desired positions), h ≥ the policy's history.
            state: passed back (the policy has no recurrent state).
            episode_start: not used (the observation holds the histories).
            deterministic: not used (the policy is deterministic).
            future: F of the observation (the environments' default, :data:`~efficienttrack.core.joints.ENV_FUTURE`, when
                None), ≥ the policy's.

        Returns:
            (4,) or (N, 4), the action a / max_adjust ∈ [−1, 1] (the environments' scale: the adjustment for ±1 is the
            system's ``max_adjust``, the policy's bound when the system's is the same), and ``state``.

        Raises:
            EfficientTrackError: an observation whose size fits no history h with that F.
        """
        obs = np.asarray(observation, dtype=np.float32)
        batch = np.atleast_2d(obs)
        n, size = batch.shape
        F = ENV_FUTURE if future is None else future
        h, rest = divmod(size - 4 * F, 12)
        if rest or h < self.cfg.history_length or F < self.cfg.future_length:
            raise EfficientTrackError(
                f"predict: an observation of {size} values is not h·8 + h·4 + {F}·4 with h ≥ {self.cfg.history_length} "
                f"and {F} ≥ the policy's F = {self.cfg.future_length} (give future= when the environment's F is not {F})"
            )
        device = next(self.parameters()).device
        parts = np.split(batch, [8 * h, 12 * h], axis=1)
        obs_hist, qref_hist, qdes_future = (
            torch.as_tensor(part, device=device).reshape(n, -1, width) for part, width in zip(parts, (8, 4, 4), strict=True)
        )
        a = self(obs_hist, qref_hist, qdes_future).cpu().numpy()
        actions = np.clip(a / self._bound(self.cfg).numpy(), -1.0, 1.0)
        return (actions[0] if obs.ndim == 1 else actions), state

    def _features(self, obs_hist: torch.Tensor, qref_hist: torch.Tensor, qdes_future: torch.Tensor) -> torch.Tensor:
        h, F = seen_lengths(self.cfg)
        return relative_features(obs_hist[:, -h:], qref_hist[:, -h:], qdes_future[:, :F], commands=self.channel == "u")

    @staticmethod
    def _bound(cfg: PolicyConfig) -> torch.Tensor:
        """(4,) bound of the output: ``max_adjust`` rad."""
        return torch.tensor(cfg.max_adjust)


class PWMPolicy(AdjustmentPolicy):
    """π_φ of the open loop: the command u_t / 1000 = π_φ(o_H, u_H, q*_F) ∈ (−1, 1)⁴ sent to the plant.

    Inputs as :class:`AdjustmentPolicy`'s with ``qref_hist`` the last commands ``u_{t−h} … u_{t−1}`` / 1000 (taken as
    they are); the output bound is 1 (PWM ±1000) and ``cfg.max_adjust`` is not used. The last layer starts at zero:
    the untrained policy sends u = 0.

    Args:
        cfg: the policy config (sizes, ``history_length`` h, ``future_length`` F).
    """

    channel = "u"
    """Its output is the command u / 1000."""
    kind = "pwm_policy"
    """Its checkpoint kind (:func:`save_policy`)."""

    @staticmethod
    def _bound(cfg: PolicyConfig) -> torch.Tensor:
        """(4,) bound of the output: 1 (PWM / 1000)."""
        return torch.ones(4)


class PolicyRollout(NamedTuple):
    """The model rolled under the policy (time-major within each window: axis 1 is the step).

    Attributes:
        q_hat: (B, H, 4) rad, predicted positions ``q̂_{t+1} … q̂_{t+H}``.
        a: (B, H, 4) rad, adjustments ``a_t … a_{t+H−1}``.
        q_ref: (B, H, 4) rad, references ``q^r_{t+1} … q^r_{t+H}`` the policy produced.
        obs_hist: (B, h', 8) [rad, rad/s], the histories at the rollout's end, ``o_{t+H−h'+1} … ô_{t+H}``.
        qref_hist: (B, h', 4) rad, ``q^r_{t+H−h'+1} … q^r_{t+H}``.
    """

    q_hat: torch.Tensor
    a: torch.Tensor
    q_ref: torch.Tensor
    obs_hist: torch.Tensor
    qref_hist: torch.Tensor


def drive(channel: str, a: torch.Tensor, q_next: torch.Tensor) -> torch.Tensor:
    """What an action drives the model with: the reference ``q*_{t+1} + a_t`` (closed loop) or the command ``a_t`` (open).

    Args:
        channel: the model's :attr:`~efficienttrack.learn.dynamics.ClosedLoopModel.channel` (``"q_ref"`` or ``"u"``).
        a: (B, 4), the action (rad, or PWM / 1000).
        q_next: (B, 4) rad, ``q*_{t+1}``.

    Returns:
        (B, 4), ``q^r_{t+1}`` rad or ``u_t`` / 1000.
    """
    return a if channel == "u" else q_next + a


class _RowGradientCap(torch.autograd.Function):
    """Identity forward; backward, each row's gradient scaled down to at most ``cap`` × the batch's median row norm."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, x: torch.Tensor, cap: float) -> torch.Tensor:
        ctx.cap = cap  # type: ignore[attr-defined]
        return x.view_as(x)

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        norm = grad.flatten(1).norm(dim=1)
        median = norm.median()
        limit = torch.where(median > 0, ctx.cap * median, torch.inf)  # type: ignore[attr-defined]  # no sync on a GPU
        scale = torch.where(norm > limit, limit / norm.clamp_min(torch.finfo(norm.dtype).tiny), 1.0)
        return grad * scale.view(-1, *(1,) * (grad.dim() - 1)), None


def cap_row_gradients(x: torch.Tensor, cap: float) -> torch.Tensor:
    """``x`` unchanged; in the backward pass each row's gradient is cut to at most ``cap`` × the median row's norm.

    Args:
        x: (B, …), one row per window.
        cap: τ > 0, the largest ratio of a row's gradient norm to the batch's median row norm that passes unchanged.

    Returns:
        ``x``, the same values.
    """
    return _RowGradientCap.apply(x, cap)


def policy_rollout(
    g_theta: ClosedLoopModel,
    pi_phi: AdjustmentPolicy | None,
    obs_hist: torch.Tensor,
    qref_hist: torch.Tensor,
    qdes_future: torch.Tensor,
    steps: int,
    truncate: int = 0,
    row_cap: float = 0.0,
) -> PolicyRollout:
    """Roll g_θ ``steps`` steps under π_φ: a_i = π_φ(o_H, q^r_H, q*_F), q^r_{i+1} = q*_{i+1} + a_i, ô_{i+1} = g_θ(…).

    With a :class:`~efficienttrack.learn.dynamics.PlantModel` (the open loop) the action is the command: u_i = a_i
    (:func:`drive`).

    Args:
        g_theta: the (frozen) closed-loop dynamics model, or a plant model with a :class:`PWMPolicy`.
        pi_phi: the policy, or None for a = 0 (the position controller alone; the open loop: u = 0).
        obs_hist: (B, h', 8) [rad, rad/s], recorded ``o_H`` at t, h' ≥ both networks' h.
        qref_hist: (B, h', 4) rad, recorded ``q^r_H`` at t.
        qdes_future: (B, F', 4) rad, ``q*_{t+1} … q*_{t+F'}`` with F' ≥ :func:`desired_length` (policy, steps).
        steps: H, rollout length.
        truncate: K > 0 cuts the gradient through the histories before steps K, 2K, …: a loss term then reaches back
            through the model's predictions to the actions of at most K steps before (0: through the whole rollout).
        row_cap: τ > 0 cuts, at every step, each window's gradient through the prediction and the reference that enter
            the histories to at most τ × the batch's median (:func:`cap_row_gradients`; 0: never).

    Returns:
        Predicted positions, adjustments and references.
    """
    cfg = pi_phi.cfg if pi_phi is not None else None
    if pi_phi is not None and pi_phi.channel != g_theta.channel:
        raise EfficientTrackError(f"policy_rollout: a {type(pi_phi).__name__} cannot drive a {type(g_theta).__name__}")
    needed = desired_length(cfg, steps)
    if qdes_future.shape[1] < needed:
        raise EfficientTrackError(f"policy_rollout: needs {needed} future desired positions, got {qdes_future.shape[1]}")
    F = seen_lengths(cfg).future
    capped = row_cap and torch.is_grad_enabled()  # the loss's own terms stay whole: only what later steps send back is cut
    enter = (lambda x: cap_row_gradients(x, row_cap)) if capped else (lambda x: x)
    q_hat, actions, refs = [], [], []
    for i in range(steps):
        if truncate and i and i % truncate == 0:
            obs_hist, qref_hist = obs_hist.detach(), qref_hist.detach()
        q_star_F = qdes_future[:, i : i + F]
        a_i = pi_phi(obs_hist, qref_hist, q_star_F) if pi_phi is not None else torch.zeros_like(q_star_F[:, 0])
        q_r = drive(g_theta.channel, a_i, q_star_F[:, 0])
        o_hat = g_theta(obs_hist, qref_hist, q_r)
        obs_hist, qref_hist = push(obs_hist, enter(o_hat)), push(qref_hist, enter(q_r))
        q_hat.append(o_hat[:, :4])
        actions.append(a_i)
        refs.append(q_r)
    return PolicyRollout(torch.stack(q_hat, 1), torch.stack(actions, 1), torch.stack(refs, 1), obs_hist, qref_hist)


def policy_loss(q_hat: torch.Tensor, a: torch.Tensor, q_star: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The two terms of the policy's loss, per window: L = L_track + k_smooth · L_reg (module docstring).

    Args:
        q_hat: (B, H, 4) rad, positions ``q_{t+1} … q_{t+H}`` (predicted by the model, or measured).
        a: (B, H, 4), the actions ``a_t … a_{t+H−1}`` (rad; open loop PWM / 1000).
        q_star: (B, H, 4) rad, the desired positions ``q*_{t+1} … q*_{t+H}``.
        gamma: γ, the discount over the steps.

    Returns:
        (B,) L_track = (1/H) Σ γ^i ‖wrap(q̂_{t+i} − q*_{t+i})‖² and (B,) L_reg = (1/(H−1)) Σ ‖a_{t+i} − a_{t+i−1}‖², rad².
    """
    H = q_hat.shape[1]
    gamma_i = gamma ** torch.arange(1, H + 1, device=q_hat.device, dtype=q_hat.dtype)
    L_track = (gamma_i * wrap(q_hat - q_star).pow(2).sum(-1)).sum(1) / H
    L_reg = (a[:, 1:] - a[:, :-1]).pow(2).sum(-1).sum(1) / (H - 1)
    return L_track, L_reg


def path_roughness(q_hat: torch.Tensor) -> torch.Tensor:
    """The predicted path's roughness per window, the term of ``k_path``.

    Args:
        q_hat: (B, H, 4) rad, positions ``q_{t+1} … q_{t+H}``, H ≥ 3.

    Returns:
        (B,) (1/(H−2)) Σ ‖Δ²q̂‖², rad², each difference wrapped.
    """
    step = wrap(q_hat[:, 1:] - q_hat[:, :-1])
    return (step[:, 1:] - step[:, :-1]).pow(2).sum(-1).mean(1)


class ImaginedDeployments:
    """Rows that deploy the policy on the frozen model across optimizer steps, h steps each (``imagined_share``).

    The rows begin at recorded windows of random steps, then go on from the model's own predictions; a row that would
    run past its episode's end restarts at the start of a random episode, at rest, as a deployment begins. A row whose
    predicted tracking error leaves what the records hold (on any joint, more than the largest |q − q*| recorded)
    restarts at a recorded window: there the model has no data, and a policy in training can drive an accurate but
    stiff model's imagined closed loop that far (the ×3 model of docs/comparison.md did, and tracked at 0.88° after).

    Args:
        data: the training episodes.
        starts: (M,) flat indices to begin the first rows at.
        rows: R, rows in the batch.
        horizon: h, steps per optimizer step.
        sample: draws (n,) indices from range(m) with the training loop's generator: ``sample(m, n)``.
    """

    def __init__(
        self, data: Sequences, starts: torch.Tensor, rows: int, horizon: int, sample: Callable[[int, int], torch.Tensor]
    ) -> None:
        self.data, self.starts, self.horizon, self.sample = data, starts, horizon, sample
        self.bound = wrap(data.obs[:, :4] - data.q_des).abs().amax(0)
        """(4,) rad, the largest tracking error of the records per joint."""
        self.t = starts[sample(len(starts), rows).to(starts.device)]
        self.end = self._last_step(self.t)
        window = data.window(self.t, horizon=0)
        self.obs_hist, self.qref_hist = window.obs_hist, window.qref_hist

    def batch(self, desired: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(R, h', 8) observation and (R, h', 4) reference histories where the rows stand, (R, ``desired``, 4) q* ahead."""
        return self.obs_hist, self.qref_hist, self.data.window(self.t, horizon=0, desired=desired).qdes_future

    def advance(self, obs_hist: torch.Tensor, qref_hist: torch.Tensor) -> None:
        """Move the rows on to the histories the rollout ended with, without gradient.

        Args:
            obs_hist: (B, h', 8) the rollout's end observation histories; the first R rows are these rows'.
            qref_hist: (B, h', 4) its end reference histories.
        """
        rows = len(self.t)
        self.obs_hist, self.qref_hist = obs_hist[:rows].detach().clone(), qref_hist[:rows].detach().clone()
        self.t = self.t + self.horizon
        device = self.t.device
        error = wrap(self.obs_hist[:, -1, :4] - self.data.q_des[self.t])
        lost = torch.nonzero((error.abs() > self.bound).any(1)).flatten()
        if len(lost):  # left the data: begin again at a recorded window
            self._begin(lost, self.starts[self.sample(len(self.starts), len(lost)).to(device)])
        over = torch.nonzero(self.t + self.horizon > self.end + 1).flatten()
        if len(over):  # at the episode's end: begin a deployment at a random episode's start
            self._begin(over, self.data.origin.to(device)[self.sample(len(self.data.origin), len(over)).to(device)])

    def _last_step(self, t: torch.Tensor) -> torch.Tensor:
        """(R,) flat index of the last step of the episode that holds each flat index of ``t`` (R,)."""
        origin = self.data.origin.to(t.device)
        episode = torch.searchsorted(origin, t, right=True) - 1
        return origin[episode] + self.data.lengths.to(t.device)[episode] - 1

    def _begin(self, rows: torch.Tensor, t: torch.Tensor) -> None:
        """Restart ``rows`` at flat indices ``t``, from the recorded histories there."""
        self.t[rows], self.end[rows] = t, self._last_step(t)
        window = self.data.window(t, horizon=0)
        self.obs_hist[rows], self.qref_hist[rows] = window.obs_hist, window.qref_hist


class PolicyTrainResult(NamedTuple):
    """Outcome of :func:`train_policy`.

    Attributes:
        policy: the trained π_φ (on the training device, eval mode).
        losses: (steps,) float, L_track + k_smooth·L_reg of every optimizer step, rad².
        seconds: wall time of this call.
        steps: optimizer steps in total.
        windows: training windows available.
        fingerprint: what it was trained from (:func:`~efficienttrack.learn.training.fingerprint`), for its checkpoint.
    """

    policy: AdjustmentPolicy
    losses: np.ndarray
    seconds: float
    steps: int
    windows: int
    fingerprint: str


def train_policy(
    cfg: PolicyConfig,
    model: ClosedLoopModel,
    records: Sequence[EpisodeRecord],
    device: str | torch.device = "auto",
    seed: int = 0,
    progress: bool = True,
    checkpoint: str | Path | None = None,
    log_dir: str | Path | None = None,
    held_out: Sequence[EpisodeRecord] = (),
    init: AdjustmentPolicy | None = None,
    network: type[AdjustmentPolicy] = AdjustmentPolicy,
) -> PolicyTrainResult:
    """Train π_φ by multi-step backpropagation through the frozen model (Algorithm 1, TrainPolicy).

    Args:
        cfg: policy config (see :data:`POLICY_PRESETS`).
        model: the trained g_θ; it is not changed (its parameters get no gradient).
        records: episodes whose windows (observations, references, desired positions) start the rollouts.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``.
        seed: seeds initialization and window sampling.
        progress: show a progress bar with the loss.
        checkpoint: training-state file, saved every ``cfg.save_every`` steps and resumed from when present.
        log_dir: folder for the scalar log (``scalars.csv`` and TensorBoard events; see :class:`TrainLog`), or None.
        held_out: episodes not trained on; with ``log_dir``, the h-step model-predicted tracking error of the
            policy from their windows (:data:`HELD_OUT_TAG`, on at most
            :data:`~efficienttrack.learn.training.HELD_OUT_STEPS` recorded steps) is logged every ``cfg.eval_every`` steps.

        init: a trained π_φ to start from (a warm start, e.g. the previous round's), with its feature scaling;
            None starts at a = 0 (a zero last layer) scaled on ``records``.
        network: :class:`AdjustmentPolicy`, or :class:`PWMPolicy` with a :class:`~efficienttrack.learn.dynamics.PlantModel`
            (the open loop; every record then needs its commands ``u``).

    Returns:
        The policy, per-step losses, time, steps and window count.
    """
    started = time.perf_counter()
    device = resolve_device(device)
    H, B, F = cfg.rollout_length, cfg.burn_in, cfg.future_length
    desired = desired_length(cfg, B + H)
    check_training_memory("PolicyConfig", cfg.batch_size, H, [cfg, model.cfg], device)
    if network.channel != model.channel or (init is not None and type(init) is not network):
        raise EfficientTrackError(f"train_policy: a {network.__name__} is trained through a {type(model).__name__}, "
                                  f"from {type(init).__name__}")  # fmt: skip
    torch.manual_seed(seed)
    history = max(cfg.history_length, model.cfg.history_length)
    data = Sequences(records, history=history, future=desired, device=device, channel=model.channel)
    starts = data.starts(B)
    recorded = data.starts(0) if B and cfg.burn_in_share < 1 else None
    burned_windows = cfg.batch_size if recorded is None else max(1, round(cfg.batch_size * cfg.burn_in_share))
    g_theta = type(model)(model.cfg).to(device)
    g_theta.load_state_dict(model.state_dict())
    g_theta.eval().requires_grad_(False)
    pi_phi = network(cfg).to(device)
    if init is not None:
        warm_start(pi_phi, init, "initial policy")
    else:
        sample = data.window(starts[torch.randperm(len(starts))[:NORM_SAMPLES].to(device)], horizon=0, desired=F)
        pi_phi.fit_scaling(sample.obs_hist, sample.qref_hist, sample.qdes_future)
    optimizer = torch.optim.AdamW(pi_phi.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    inputs = fingerprint(records, seed, model, init)
    subset = held_out_subset(held_out)
    evaluate = (lambda: {HELD_OUT_TAG: predicted_tracking_error(g_theta, subset, pi_phi, H).mae_deg}) if subset else None
    total = cfg.total_steps(len(starts))
    loop = TrainLoop("policy", cfg, total, pi_phi, optimizer, seed, checkpoint, progress, inputs, log_dir, evaluate)

    imagined_rows = round(cfg.batch_size * cfg.imagined_share)
    imagined = ImaginedDeployments(data, starts, imagined_rows, H, loop.sample) if imagined_rows else None

    for step in loop:
        window = data.window(starts[loop.sample(len(starts), burned_windows - imagined_rows).to(device)], horizon=0,
                             desired=desired)  # fmt: skip
        obs_hist, qref_hist, q_star = window.obs_hist, window.qref_hist, window.qdes_future
        if imagined is not None:  # the rows that go on deploying the policy on the model
            rows = imagined.batch(desired)
            obs_hist, qref_hist, q_star = (
                torch.cat([mine, recorded]) for mine, recorded in zip(rows, (obs_hist, qref_hist, q_star), strict=True)
            )
        # burn-in: B steps under π_φ without gradient, so that the loss starts from the policy's own histories
        if B:
            with torch.no_grad():
                burned = policy_rollout(g_theta, pi_phi, obs_hist, qref_hist, q_star, steps=B)
            obs_hist, qref_hist, q_star = burned.obs_hist, burned.qref_hist, q_star[:, B:]
        if recorded is not None:  # the rest of the batch: recorded windows from any step
            plain = data.window(recorded[loop.sample(len(recorded), cfg.batch_size - burned_windows).to(device)],
                                horizon=0, desired=desired - B)  # fmt: skip
            obs_hist, qref_hist = torch.cat([obs_hist, plain.obs_hist]), torch.cat([qref_hist, plain.qref_hist])
            q_star = torch.cat([q_star, plain.qdes_future])
        # rollout: H steps of g_θ under π_φ, q^r_{i+1} = q*_{i+1} + a_i, q*_F sliding along q*_{t+1..t+H−1+F}
        q_hat, a, _, end_obs, end_qref = policy_rollout(g_theta, pi_phi, obs_hist, qref_hist, q_star, H, cfg.truncate,
                                                        cfg.row_cap)  # fmt: skip
        if imagined is not None:
            imagined.advance(end_obs, end_qref)
        L_track, L_reg = policy_loss(q_hat, a, q_star[:, :H], cfg.gamma)
        loss = L_track.mean() + cfg.k_smooth * L_reg.mean()
        if cfg.k_path:
            loss = loss + cfg.k_path * path_roughness(q_hat).mean()
        # step
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip is not None:
            nn.utils.clip_grad_norm_(pi_phi.parameters(), cfg.grad_clip)
        loop.set_lr(step)
        optimizer.step()
        # log
        loop.record(step, loss.item())

    pi_phi.eval()
    return PolicyTrainResult(pi_phi, loop.losses(), time.perf_counter() - started, loop.total, len(starts), inputs)


class TrackingError(NamedTuple):
    """Model-predicted tracking error of a policy (or of a = 0), degrees.

    Attributes:
        mae_deg: mean |wrap(q̂ − q*)| over windows, steps and joints, deg.
        per_joint_deg: (4,) mean per joint, deg.
        windows: number of rollouts (one per recorded step).
    """

    mae_deg: float
    per_joint_deg: list[float]
    windows: int


@torch.inference_mode()
def predicted_tracking_error(
    model: ClosedLoopModel,
    records: Sequence[EpisodeRecord],
    policy: AdjustmentPolicy | None = None,
    steps: int = 20,
    device: str | torch.device | None = None,
) -> TrackingError:
    """How well ``policy`` (None: a = 0) tracks the desired positions according to ``model``.

    From every recorded step t, roll the model ``steps`` steps under the policy and average
    |wrap(q̂_{t+i} − q*_{t+i})|.

    Args:
        model: g_θ.
        records: episodes giving the start histories and desired positions.
        policy: π_φ, or None for the position controller alone.
        steps: rollout length.
        device: where to compute (the model's device when None).

    Returns:
        The mean error overall and per joint, in degrees.
    """
    device = next(model.parameters()).device if device is None else resolve_device(device)
    model = model.eval().to(device)
    policy = policy.eval().to(device) if policy is not None else None
    cfg = policy.cfg if policy is not None else None
    desired = desired_length(cfg, steps)
    history = max(seen_lengths(cfg).history, model.cfg.history_length)
    data = Sequences(records, history=history, future=desired, device=device, channel=model.channel)
    starts = data.starts(0)
    total = torch.zeros(4, dtype=torch.float64, device=device)
    for chunk in starts.split(EVAL_CHUNK):
        window = data.window(chunk, horizon=0, desired=desired)
        rolled = policy_rollout(model, policy, window.obs_hist, window.qref_hist, window.qdes_future, steps)
        total += wrap(rolled.q_hat - window.qdes_future[:, :steps]).abs().sum((0, 1)).double()
    per_joint = torch.rad2deg(total / (len(starts) * steps)).cpu().numpy()
    return TrackingError(float(per_joint.mean()), per_joint.tolist(), len(starts))


def save_policy(policy: AdjustmentPolicy, path: str | Path, fingerprint: str | None = None) -> Path:
    """Save π_φ: state_dict at ``path`` (e.g. ``policy.pt``) and its PolicyConfig as JSON next to it.

    ``fingerprint`` is what it was trained from (``PolicyTrainResult.fingerprint``), kept in the JSON and carried into
    an export's contract; None when not known.
    """
    return save_checkpoint(policy, policy.kind, policy.cfg, path, fingerprint)


def load_policy(
    path: str | Path, device: str | torch.device = "cpu", network: type[AdjustmentPolicy] = AdjustmentPolicy
) -> AdjustmentPolicy:
    """Load a policy saved by :func:`save_policy` (tensors only, ``weights_only=True``), in eval mode on ``device``.

    Args:
        path: the ``.pt`` file written by :func:`save_policy`; its JSON config must lie next to it.
        device: where to put the policy (``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or a torch device).
        network: the class saved: :class:`AdjustmentPolicy` or :class:`PWMPolicy` (a file of the other is refused).
    """
    return load_checkpoint(path, network.kind, PolicyConfig.from_stored, network, device)
