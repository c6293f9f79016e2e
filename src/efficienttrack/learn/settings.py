"""The learners' settings: the optimizer schedule, the model's and the policy's configs and their presets.

Torch-free, so that ``efficienttrack config show`` and a run's settings are read on the core install; the networks
and their training live in :mod:`~efficienttrack.learn.dynamics`, :mod:`~efficienttrack.learn.policy` and
:mod:`~efficienttrack.learn.training`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Self

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import MAX_HORIZON
from efficienttrack.core.settings import check_fields, inherit, setting, settings_from_dict
from efficienttrack.data.features import feature_width
from efficienttrack.systems.limits import XE75_MAX_ADJUST

MAX_HIDDEN = 8192
"""Most units per hidden layer a config may ask for (the paper: 512)."""
MAX_LAYERS = 64
"""Most hidden blocks a config may ask for (the paper: 6)."""
MAX_BATCH_SIZE = 65_536
"""Most windows per optimizer step a config may ask for (the paper: 2048)."""
MAX_STEPS = 10_000_000
"""Most optimizer steps of a training run (the paper: 2000 epochs of its data, about 170,000 steps)."""
MAX_EPOCHS = 100_000
"""Most passes over the training windows a config may ask for (the paper: 2000)."""


MAX_LR = 10.0
"""Largest learning rate a config may ask for: far above any useful one (the paper: 1e-3), low enough that a typo
(``lr: 1e300``) is refused before collection instead of overflowing the optimizer's float32 step after it."""
MAX_WEIGHT_DECAY = 100.0
"""Largest decoupled weight decay a config may ask for (the paper: 0.003)."""


@dataclass(frozen=True)
class TrainingSchedule:
    """The optimizer and schedule settings that the model's and the policy's configs share (their base class).

    A config class derives from this one and adds its network and loss fields; it may give a field here another
    default by declaring it again.
    """

    batch_size: int = setting(256, ge=1, le=MAX_BATCH_SIZE)
    """Windows per optimizer step (paper 2048)."""
    lr: float = setting(1e-3, gt=0, le=MAX_LR)
    """Adam learning rate (paper 1e-5)."""
    weight_decay: float = setting(0.0, ge=0, le=MAX_WEIGHT_DECAY)
    """Decoupled weight decay w (AdamW: θ ← θ − lr·w·θ each step; the paper: 0.003 for g_θ, none for π_φ)."""
    steps: int | None = setting(1500, ge=1, le=MAX_STEPS)
    """Optimizer steps; None to use ``epochs``."""
    epochs: int | None = setting(None, ge=1, le=MAX_EPOCHS)
    """Passes over the windows (paper 2000), used when ``steps`` is None."""
    cosine_decay: bool = setting(True)
    """Decay the learning rate to 0 along a cosine over the run (paper: constant)."""
    grad_clip: float | None = setting(1.0, gt=0)
    """Clip the gradient norm to this (None: no clipping)."""
    warmup: float = setting(0.0, ge=0, le=0.5, before=0.0)
    """Share of the steps over which the learning rate rises linearly to ``lr`` at the start (0: from the first step).
    For a warm start: Adam's first steps, with fresh moments, move every weight by about ``lr`` whatever its gradient,
    which throws a trained network off (``RunConfig.round_warmup``)."""
    save_every: int = setting(200, ge=1, le=MAX_STEPS)
    """Save the training state every this many steps when a checkpoint path is given."""
    eval_every: int | None = setting(None, ge=1, le=MAX_STEPS)
    """Optimizer steps between held-out evaluations when training logs (None: a tenth of the run)."""

    def __post_init__(self) -> None:
        """Check the fields (:func:`~efficienttrack.core.settings.check_fields`), then that one of steps, epochs is set."""
        check_fields(self)
        if (self.steps is None) == (self.epochs is None):
            raise EfficientTrackError(f"{type(self).__name__}: set exactly one of steps and epochs")

    def total_steps(self, windows: int) -> int:
        """Optimizer steps of a run on ``windows`` training windows (``steps``, or ``epochs`` passes over them).

        Args:
            windows: training windows available.

        Raises:
            EfficientTrackError: ``epochs`` passes over ``windows`` make more than :data:`MAX_STEPS` steps.
        """
        if self.steps is not None:
            return self.steps
        assert self.epochs is not None  # exactly one of steps and epochs is set (__post_init__)
        total = self.epochs * math.ceil(windows / self.batch_size)
        if total > MAX_STEPS:
            raise EfficientTrackError(
                f"{type(self).__name__}.epochs: {self.epochs} passes over {windows} windows make {total} optimizer steps, "
                f"more than the {MAX_STEPS} allowed; lower epochs or raise batch_size"
            )
        return total

    def scaled(self, share: float) -> Self:
        """This schedule with ``share`` × its optimizer steps (or epochs), at least one; everything else kept.

        Args:
            share: > 0, e.g. 0.5 for a warm-started round that trains half as long as the first.
        """
        if not (math.isfinite(share) and share > 0):
            raise EfficientTrackError(f"{type(self).__name__}: a schedule is scaled by a share > 0, got {share}")
        if self.steps is not None:
            return dataclasses.replace(self, steps=max(1, round(self.steps * share)))
        assert self.epochs is not None  # exactly one of steps and epochs is set (__post_init__)
        return dataclasses.replace(self, epochs=max(1, round(self.epochs * share)))

    @classmethod
    def from_dict(cls, data: dict, source: str | None = None) -> Self:
        """Build the config from a JSON/YAML mapping, validated field by field.

        Args:
            data: field name → value, as read from a JSON/YAML config; missing fields keep their defaults.
            source: where ``data`` came from, named in error messages (the class name when None).
        """
        return settings_from_dict(cls, data, source or cls.__name__)

    @classmethod
    def from_stored(cls, data: dict, source: str | None = None) -> Self:
        """Read back the config a checkpoint stored: a field added later that it lacks takes its ``before`` value.

        Unlike :meth:`from_dict`, which fills a missing field with today's default, this gives what the code did when
        the checkpoint was written.

        Args:
            data: the checkpoint's config (:func:`~efficienttrack.core.settings.plain_form`).
            source: where ``data`` came from, named in error messages (the class name when None).
        """
        return settings_from_dict(cls, data, source or cls.__name__, stored=True)


@dataclass(frozen=True)
class ModelConfig(TrainingSchedule):
    """Size and training settings of the closed-loop dynamics model (the schedule's fields: :class:`TrainingSchedule`)."""

    hidden: int = setting(128, ge=1, le=MAX_HIDDEN)
    """Units per hidden layer (paper 512)."""
    layers: int = setting(3, ge=1, le=MAX_LAYERS)
    """Hidden Linear → LayerNorm → ELU blocks (paper 6)."""
    horizon: int = setting(20, ge=1, le=MAX_HORIZON)
    """h: multi-step training horizon (:attr:`rollout_length`), and the history length unless ``history`` is set
    (paper 20)."""
    history: int | None = setting(5, ge=1, le=MAX_HORIZON)
    """Length of the histories o_H, q^r_H the model sees (:attr:`history_length`); None: h (the paper). Shorter
    generalizes better on the XE75."""
    lr: float = inherit(TrainingSchedule, "lr", 3e-3)
    """Adam learning rate (paper 1e-5). 3e-3 with the warm-up: the preset's 4,000 steps go most of the way to the
    accuracy of 12,000 steps at 1e-3, and the policy through the model tracks better on two plants of three (level on the
    xe75); without the warm-up the first
    steps' huge rollout losses throw it off on some plants (docs/comparison.md, "A model that learns faster")."""
    weight_decay: float = inherit(TrainingSchedule, "weight_decay", 0.003)
    """w: decoupled weight decay (paper 0.003)."""
    steps: int | None = inherit(TrainingSchedule, "steps", 4000)
    """Optimizer steps; None to use ``epochs``."""
    warmup: float = inherit(TrainingSchedule, "warmup", 0.1)
    """Share of the steps over which the learning rate rises to ``lr`` (0: from the first step, the paper's): the
    fresh model's 20-step rollouts drift far (losses of thousands), and a full rate on them diverges."""

    @property
    def history_length(self) -> int:
        """Length of the histories o_H, q^r_H the model sees: ``history``, or ``horizon`` when unset."""
        return self.horizon if self.history is None else self.history

    @property
    def rollout_length(self) -> int:
        """Steps the model is rolled on its own predictions per training window (``horizon``)."""
        return self.horizon

    @property
    def in_dim(self) -> int:
        """Network input features: :func:`~efficienttrack.data.features.feature_width` of the history and one q^r_{t+1}."""
        return feature_width(self.history_length, 1)


MODEL_PRESETS: dict[str, ModelConfig] = {
    "paper": ModelConfig(
        hidden=512, layers=6, horizon=20, history=None, batch_size=2048, lr=1e-5, weight_decay=0.003,
        steps=None, epochs=2000, cosine_decay=False, grad_clip=None, warmup=0.0, save_every=1000,
    ),
    "cpu": ModelConfig(),
    "tiny": ModelConfig(
        hidden=32, layers=2, horizon=4, history=None, batch_size=64, lr=3e-3, warmup=0.0, steps=300, save_every=100
    ),
}  # fmt: skip
"""Named model configs: the paper's (a GPU job), ``cpu`` (minutes on 2 cores), ``tiny`` (tests, seconds; its 4-step
rollouts start from the full rate, which the ramp did not improve)."""


@dataclass(frozen=True)
class PolicyConfig(TrainingSchedule):
    """Size, loss and training settings of the adjustment policy (the schedule's fields: :class:`TrainingSchedule`)."""

    hidden: int = setting(128, ge=1, le=MAX_HIDDEN)
    """Units per hidden layer (paper 512)."""
    layers: int = setting(3, ge=1, le=MAX_LAYERS)
    """Hidden Linear → LayerNorm → ELU blocks (paper 6)."""
    steps: int | None = inherit(TrainingSchedule, "steps", 3000)
    """Optimizer steps; None to use ``epochs``. The policy's training, not the model, limits the tracking: 3,000 steps
    tracked better than 1,500 (the preset until 2026-11-29) in nine of nine runs on three plants (docs/comparison.md,
    "Twice the policy's steps")."""
    lr: float = inherit(TrainingSchedule, "lr", 3e-3)
    """Adam learning rate (paper 1e-5). 3e-3 with the warm-up, the model's rate: it tracked better than 1e-3 (the rate
    until 2026-12-07) in nine of nine runs on three plants (docs/comparison.md, "The policy at the model's rate")."""
    warmup: float = inherit(TrainingSchedule, "warmup", 0.1)
    """Share of the steps over which the learning rate rises to ``lr`` (0: from the first step, the paper's)."""
    horizon: int = setting(20, ge=2, le=MAX_HORIZON)
    """h: the paper's one length of the policy, read as :attr:`history_length`, :attr:`future_length` and
    :attr:`rollout_length` (paper 20); at least 2, for the smoothness term needs two actions."""
    gamma: float = setting(0.98, gt=0, le=1)
    """γ: discount of the tracking loss over the rollout (paper 0.98)."""
    k_smooth: float = setting(1.0, ge=0)
    """k_smooth: weight of the action-smoothness regularizer (paper 1.0)."""
    max_adjust: tuple[float, ...] = setting(XE75_MAX_ADJUST, gt=0, length=4)
    """(4,) rad, bound of |a| per joint (boom, arm, bucket, swing)."""
    burn_in: int = setting(0, ge=0, le=MAX_HORIZON, before=0)
    """B: steps the policy drives the frozen model from each training start, without gradient, before the loss's h
    steps, so that the histories the loss sees hold the policy's own adjustments, as when deployed (0: the paper's,
    the histories are the recorded ones)."""
    burn_in_share: float = setting(1.0, gt=0, le=1, before=1.0)
    """With ``burn_in``: the share of each batch's windows that get the burn-in; the others start from the recorded
    histories, at any step of an episode, its first B included (1: all windows are burned in)."""
    k_path: float = setting(0.0, ge=0, before=0.0)
    """Weight of the predicted path's roughness, (1/(H−2)) Σ ‖wrap(Δ²q̂)‖², the term the 2nd-order oSMT measures on
    the executed path (0: the paper's loss, which smooths only the adjustment)."""
    imagined_share: float = setting(0.5, ge=0, le=1, before=0.0)
    """Share of each batch whose rows go on through an imagined deployment, h steps per optimizer step: each row
    continues from where the frozen model, driven by the policy, left it at the previous step (gradients truncated
    there), and restarts at a random episode's start after its end. The loss then sees the policy's own closed loop as
    deployed, over whole episodes (0: every window starts from recorded histories, the paper's; 0.5 by default since
    it tracked better on every plant, docs/comparison.md)."""

    truncate: int = setting(0, ge=0, le=MAX_HORIZON, before=0)
    """K: cut the gradient through the model's predicted states every K steps of the rollout (truncated
    backpropagation), so that an action is credited with what it causes over the next K steps at most; the loss itself
    still runs over all h steps (0: never, the paper's). Through a model trained ten times longer the whole rollout's
    gradient explodes (norms 10–100 times the preset model's, spikes to 50) and the policy tracked worse; cut every 5
    steps it tracked 30 % better than through the preset's model, on the paper's simulator. Not the default: through
    the xe75's preset model, K = 5 tracked more than twice as badly; ``row_cap`` does not (docs/comparison.md,
    "Exploding gradients through a better model")."""

    row_cap: float = setting(10.0, ge=0, before=0.0)
    """τ: at every step of the rollout, cut each window's gradient through the predicted state and the reference that
    later steps see to at most τ times the batch's median window (0: never, the paper's). Through a model trained
    longer the gradient's mass sits in a few windows (under the preset's policy, the top 1 % carry 55 % of it,
    ``benchmarks/policy_gradients.py --policy``) and, uncut, the better model gave the worse policy; the cap tames those
    windows and leaves the others their whole horizon, where ``truncate`` cuts every window's. 10 by default since
    2026-11-29: on the paper's simulator the policy then improves with the model's length (validation MAE 0.195°,
    0.157°, 0.133° through models of 4,000, 12,000 and 40,000 steps, against 0.518° uncut at 40,000), and through the
    preset's models it tracked as well or a little better on three plants (docs/comparison.md, "Exploding gradients
    through a better model")."""

    def __post_init__(self) -> None:
        """Check the fields, then a horizon that ``k_path`` can use and at most one of ``burn_in`` and ``imagined_share``."""
        super().__post_init__()
        if self.k_path and self.horizon < 3:
            raise EfficientTrackError(f"PolicyConfig: k_path needs a horizon of at least 3 steps, got {self.horizon}")
        if self.burn_in and self.imagined_share:
            raise EfficientTrackError(
                f"PolicyConfig: burn_in ({self.burn_in}) and imagined_share ({self.imagined_share:g}) are two ways of "
                "one thing; set one of them (for a burn-in: imagined_share=0)"
            )

    @property
    def history_length(self) -> int:
        """Length of the histories o_H, q^r_H the policy sees (``horizon``)."""
        return self.horizon

    @property
    def future_length(self) -> int:
        """F: future desired positions q*_F the policy sees (``horizon``)."""
        return self.horizon

    @property
    def rollout_length(self) -> int:
        """Steps the model is rolled under the policy per training window (``horizon``)."""
        return self.horizon

    @property
    def in_dim(self) -> int:
        """Network input features: :func:`~efficienttrack.data.features.feature_width` of the history and the F targets."""
        return feature_width(self.history_length, self.future_length)


POLICY_PRESETS: dict[str, PolicyConfig] = {
    "paper": PolicyConfig(
        hidden=512, layers=6, horizon=20, batch_size=2048, lr=1e-5, warmup=0.0,
        steps=None, epochs=2000, cosine_decay=False, grad_clip=None, save_every=1000,
    ),
    "cpu": PolicyConfig(),
    "tiny": PolicyConfig(hidden=32, layers=2, horizon=4, batch_size=64, lr=3e-3, warmup=0.0, steps=200, save_every=100),
}  # fmt: skip
"""Named policy configs: the paper's (a GPU job), ``cpu`` (minutes on 2 cores), ``tiny`` (tests, seconds)."""
