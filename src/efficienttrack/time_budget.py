"""Fit a run into a wall-clock budget (``--time-budget MINUTES``) by training fewer optimizer steps.

Almost all of a run's time is training, and a training step's cost depends on the machine (it varied by 30 %
between days on one 2-core machine). So the run measures it: after the collection and the PD evaluation it times
short trainings of each network on the collected data (:func:`step_seconds`; their setup cancels out), estimates
what every round's trainings and the rest of the run will take, and scales the optimizer steps of every training,
all rounds, by one factor ≤ 1 (:func:`budget_scale`). The factor is kept in ``OUT/stages/time_budget.json``, so a
resumed run trains the same steps. The budget is a target, not a guarantee: work beside the run slows its steps.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch

from efficienttrack import dynamics, policy
from efficienttrack.config import RunConfig
from efficienttrack.errors import EfficientTrackError
from efficienttrack.records import EpisodeRecord
from efficienttrack.stages import RunLog, Stages
from efficienttrack.training import TrainingSchedule

PROBE_STEPS = (1, 4, 24)
"""Optimizer steps of the short trainings of each network: a warm-up (the process's first steps are slow), then two
timed ones; the step time is the difference of those two over their 20 steps."""
MIN_SCALE = 0.05
"""Smallest share of the configured steps worth training; a budget that leaves less is refused."""
RESERVE = 0.03
"""Share of the budget kept for what the estimate leaves out (model errors, saving, plots)."""
STAGE = "time_budget"
"""The stage that keeps the factor: ``OUT/stages/time_budget.json``."""


class StepTimes(NamedTuple):
    """Seconds per optimizer step of each training on this machine, and the training windows (for epoch schedules).

    Attributes:
        model: s per step of g_θ's training.
        policy: s per step of π_φ's training.
        windows: training windows of the collected data.
    """

    model: float
    policy: float
    windows: int


def step_seconds(train: Callable[[TrainingSchedule], Any], cfg: TrainingSchedule) -> tuple[float, Any]:
    """Seconds per optimizer step of a training: after a warm-up, two short runs of it, their setup cancelling out.

    Args:
        train: runs the training with a schedule and returns its result (``seconds``, ``windows``, the network first).
        cfg: the training's config; the probes train :data:`PROBE_STEPS` steps of it.

    Returns:
        The seconds per step (> 0) and the longer probe's result.
    """
    _, short, long = (
        train(dataclasses.replace(cfg, steps=steps, epochs=None, save_every=steps, eval_every=None)) for steps in PROBE_STEPS
    )
    per_step = (long.seconds - short.seconds) / (PROBE_STEPS[2] - PROBE_STEPS[1])
    return max(per_step, long.seconds / PROBE_STEPS[2] / 10, 1e-6), long


def measure_step_times(cfg: RunConfig, records: Sequence[EpisodeRecord], device: torch.device) -> StepTimes:
    """Time both trainings of ``cfg`` on ``records`` (:data:`PROBE_STEPS`: 29 steps of each network; nothing is saved).

    Args:
        cfg: the run's config (sizes, batches, horizons).
        records: the collected episodes.
        device: the training device.

    Returns:
        The step times and the window count.
    """
    common = {"device": device, "seed": cfg.seed, "progress": False}
    model_s, probe = step_seconds(lambda c: dynamics.train_model(c, records, **common), cfg.model)
    policy_s, _ = step_seconds(lambda c: policy.train_policy(c, probe.model, records, **common), cfg.policy)
    return StepTimes(model_s, policy_s, probe.windows)


def budget_scale(cfg: RunConfig, times: StepTimes, seconds_left: float, other_seconds: float) -> tuple[float, float]:
    """The factor on every training's steps that fits the rest of the run into ``seconds_left``.

    Args:
        cfg: the run's config: round 1's steps, ``rounds`` and ``warm_budget`` (a later round's share of them).
        times: the step times.
        seconds_left: the budget's seconds not spent yet.
        other_seconds: what the rest of the run takes besides training (deployments, evaluations).

    Returns:
        The factor (≤ 1: the configured steps are the most trained) and the training seconds they would take unscaled.

    Raises:
        EfficientTrackError: the budget leaves less than :data:`MIN_SCALE` of the configured training.
    """
    round_1 = cfg.model.total_steps(times.windows) * times.model + cfg.policy.total_steps(times.windows) * times.policy
    training = round_1 * (1 + (cfg.rounds - 1) * cfg.warm_budget)
    available = seconds_left * (1 - RESERVE) - other_seconds
    scale = min(1.0, available / training)
    if scale < MIN_SCALE:
        raise EfficientTrackError(
            f"--time-budget {cfg.time_budget:g} min: {max(available, 0) / 60:.1f} min would be left for training, less than "
            f"{MIN_SCALE:.0%} of the {training / 60:.1f} min its steps take on this machine; give more minutes or fewer steps"
        )
    return scale, training


def fit_to_budget(
    cfg: RunConfig,
    stages: Stages,
    log: RunLog,
    records: Sequence[EpisodeRecord],
    device: torch.device,
    started: float,
    pass_seconds: float,
    evaluation_seconds: float,
) -> RunConfig:
    """``cfg`` with every training's steps scaled to fit ``cfg.time_budget`` (unchanged without one).

    The factor is decided once per run folder and kept as the stage :data:`STAGE`; a rerun reads it back.

    Args:
        cfg: the run's config.
        stages: the run's finished-stage markers.
        log: where to say what was decided.
        records: the collected episodes (the probes train on them).
        device: the training device.
        started: ``time.perf_counter()`` when this invocation of the run began; the budget counts from there.
        pass_seconds: what one collection pass took here (a later round deploys one pass).
        evaluation_seconds: what one evaluation on the test references took here.

    Returns:
        The config to train with.
    """
    if cfg.time_budget is None:
        return cfg
    facts = stages.done(STAGE, ("scale",))
    if facts is None:
        times = measure_step_times(cfg, records, device)
        other = cfg.rounds * evaluation_seconds + (cfg.rounds - 1) * pass_seconds
        left = cfg.time_budget * 60 - (time.perf_counter() - started)
        scale, training = budget_scale(cfg, times, left, other)
        facts = stages.finish(
            STAGE,
            {"scale": scale, "model_step_seconds": times.model, "policy_step_seconds": times.policy,
             "unscaled_training_seconds": training, "seconds_left": left, "other_seconds": other},
        )  # fmt: skip
        log.print(
            f"time budget {cfg.time_budget:g} min: {times.model * 1e3:.0f} ms per model step, {times.policy * 1e3:.0f} ms "
            f"per policy step; the configured training takes {training / 60:.1f} min, "
            + ("it fits" if scale >= 1 else f"so every training gets {scale:.0%} of its steps")
        )
    if facts["scale"] >= 1:
        return cfg
    return dataclasses.replace(cfg, model=cfg.model.scaled(facts["scale"]), policy=cfg.policy.scaled(facts["scale"]))
