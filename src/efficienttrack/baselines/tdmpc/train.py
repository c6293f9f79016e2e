"""TD-MPC on the tracking environments: interact, store, update, plan; the held-out curve at chosen step counts.

One machine (:class:`efficienttrack.envs.TrackingEnv`) tracks the training references, one episode per reference
(drawn by the environment's seeded generator). The first ``seed_steps`` interaction steps take uniformly random
actions; from then on every action is planned (:func:`~.planner.plan`) with exploration noise. When the seeding ends,
``seed_steps`` updates run at once, then one update per interaction step (the public TD-MPC code's schedule).
An interaction step is one environment step of the machine (20 Hz), the paper's I.S.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from efficienttrack.baselines.curve import CURVE_FILE, CurveRecorder, TrainingRun, check_training_run
from efficienttrack.baselines.resume import SAVE_EVERY_SECONDS, STATE_FILE, run_identity
from efficienttrack.baselines.tdmpc.buffer import PrioritizedBuffer
from efficienttrack.baselines.tdmpc.learner import Learner
from efficienttrack.baselines.tdmpc.networks import TOLD
from efficienttrack.baselines.tdmpc.planner import PlannerConfig, plan
from efficienttrack.baselines.tdmpc.settings import TDMPCSettings, tdmpc_settings
from efficienttrack.baselines.tdmpc.state import Generators, restore_state, save_state
from efficienttrack.core.fileio import atomic_write, output_lock
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.envs.core import open_system
from efficienttrack.envs.features import See, learner_input
from efficienttrack.envs.single import TrackingEnv
from efficienttrack.learn.nets import resolve_device

METHOD = "tdmpc"
"""The method's name in ``curve.json`` and the study."""

MODEL_FILE = "model.pt"
"""The final TOLD model's ``state_dict`` (``torch.load(..., weights_only=True)`` reads it)."""


def planner_config(settings: TDMPCSettings, step: int, action_dim: int) -> PlannerConfig:
    """The planner's knobs at interaction step ``step`` (the horizon and min-std schedules applied).

    Args:
        settings: the settings.
        step: interaction steps so far.
        action_dim: A.

    Returns:
        The planner's config.
    """
    horizon, min_std = settings.schedule(step)
    return PlannerConfig(
        horizon=horizon,
        action_dim=action_dim,
        iterations=settings.iterations,
        num_samples=settings.num_samples,
        num_pi_samples=settings.num_pi_samples,
        num_elites=settings.num_elites,
        temperature=settings.temperature,
        momentum=settings.momentum,
        min_std=min_std,
        pi_std=settings.min_std,
        discount=settings.discount,
    )


def evaluation_agent(
    model: TOLD, settings: TDMPCSettings, step: int, seed: int, see: See = np.asarray
) -> Callable[[np.ndarray], np.ndarray]:
    """The deterministic agent the curve measures: π's mean action, or the planner without exploration noise.

    Args:
        model: the TOLD model.
        settings: ``evaluate_with`` chooses; the planner's knobs as at ``step``.
        step: interaction steps trained so far (the schedules' position).
        seed: with ``step``, seeds the planner's own generator (training's generators are left alone).
        see: flat observations (N, D_obs) → what the networks were trained on (the observation pipeline).

    Returns:
        ``act``: observations (N, D) float32 → actions (N, A) in [−1, 1]; N machines planned for in one batch.
    """
    device = next(model.parameters()).device
    if settings.evaluate_with == "policy":

        @torch.no_grad()
        def act_policy(obs: np.ndarray) -> np.ndarray:
            return model.pi(model.encode(torch.as_tensor(see(obs), device=device))).cpu().numpy()

        return act_policy
    config = planner_config(settings, step, model.action_dim)
    generator = torch.Generator(device=device).manual_seed(int(np.random.SeedSequence([seed, step]).generate_state(1)[0]))
    warm: list[torch.Tensor] = []

    @torch.no_grad()
    def act_plan(obs: np.ndarray) -> np.ndarray:
        z = model.encode(torch.as_tensor(see(obs), device=device))
        previous = warm.pop() if warm and warm[-1].shape[1] == len(z) else None
        result = plan(model, z, config, generator, previous, explore=False)
        warm[:] = [result.mean]
        return result.action.cpu().numpy()

    return act_plan


def train_tdmpc(
    run: TrainingRun,
    preset: str | TDMPCSettings = "cpu",
    progress: ProgressDisplay | None = None,
    save_every_seconds: float = SAVE_EVERY_SECONDS,
) -> list[dict[str, Any]]:
    """Train TD-MPC for ``run.budget`` interaction steps on one machine; evaluate it on the test references along the way.

    At each of ``run.points`` the deterministic agent (``settings.evaluate_with``: π's mean action, or the planner
    without noise) is scored on the test references, then on the validation references (after the test references,
    so that the planner's generator meets those as it would without validation), and ``folder/curve.json`` is
    rewritten. The state is saved between episodes without pickle (:mod:`.state`), and a killed run resumes as the
    uninterrupted run would go on: the same seed and settings give the same curve on one machine, device and thread
    count. The global torch generator is left as it was; the final ``state_dict`` goes to ``folder/model.pt``.

    Args:
        run: the run (:func:`~efficienttrack.baselines.curve.training_run`); its ``seed`` seeds everything random.
        preset: ``"paper"``, ``"cpu"`` (TD-MPC (reduced)), ``"tiny"``
            (:data:`~efficienttrack.baselines.tdmpc.settings.PRESETS`) or a
            :class:`~efficienttrack.baselines.tdmpc.settings.TDMPCSettings`.
        progress: a display to show the training steps and the last MAE on, or None.
        save_every_seconds: wall seconds between saves of the state (0: at every episode's end).

    Returns:
        One point per evaluation: ``{"interaction_steps", "wall_seconds" (training so far, evaluations excluded),
        "metrics"}``, and ``"validation"`` when the run has validation references.

    Raises:
        EfficientTrackError: an unknown preset, a bad run, a device that is not available, a folder in use or holding
            another run's state, or a problem the environment reports.
    """
    settings = tdmpc_settings(preset)
    run = check_training_run(run)
    loop, system, folder, train_refs = run.loop, run.system, run.folder, run.train_refs
    device = resolve_device(settings.device)
    header = {"method": METHOD, "loop": loop, "seed": run.seed, "budget": run.budget, "system": system.to_dict()}
    header["settings"] = asdict(settings)
    run_id = run_identity(header, run)
    with output_lock(folder / CURVE_FILE, "folder", folder=False):
        recorder = CurveRecorder(run, header, open_system(loop, system), progress)
        env = TrackingEnv(loop, system, train_refs)
        see = learner_input(settings.inputs, loop, system, train_refs)
        try:
            resume = Resume(folder / STATE_FILE, run_id, save_every_seconds)
            model = _run(env, see, settings, device, run.budget, run.seed, run.points, recorder, resume)
            atomic_write(folder / MODEL_FILE, lambda f: torch.save(model.state_dict(), f))
            resume.state_file.unlink(missing_ok=True)
        finally:
            env.close()
            recorder.close()
    return recorder.curve


class Resume(NamedTuple):
    """Where and how often a run saves its state, and what the run is (:mod:`.state`)."""

    state_file: Path
    run: str
    every: float


def _run(
    env: TrackingEnv,
    see: See,
    settings: TDMPCSettings,
    device: torch.device,
    budget: int,
    seed: int,
    points: list[int],
    recorder: CurveRecorder,
    resume: Resume,
) -> TOLD:
    # The action space is a Box, whose shape Gymnasium types as optional.
    obs_dim, action_dim = see(env.observation_space.sample()[None]).shape[1], env.action_space.shape[0]  # type: ignore[index]
    rng = np.random.default_rng(seed)
    generator = torch.Generator(device=device).manual_seed(seed)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = TOLD(obs_dim, action_dim, settings).to(device)
    learner = Learner(model, settings, generator)
    buffer = PrioritizedBuffer(
        settings.buffer_size, obs_dim, action_dim, settings.horizon, settings.per_alpha, settings.per_beta
    )
    start, obs = 0, None
    if resume.state_file.exists():
        generators = Generators(rng, generator, env.np_random)
        start, curve, wall = restore_state(resume.state_file, resume.run, learner, buffer, generators)
        recorder.resume(curve, wall, start)
    else:
        obs = see(env.reset(seed=seed)[0][None])[0]
    generators = Generators(rng, generator, env.np_random)  # a seeded reset gives the environment a new generator
    points = [p for p in points if p > start]
    first, warm, saved = True, None, time.perf_counter()
    for count in range(start + 1, budget + 1):
        if obs is None:  # the next episode (after a resumed state, or when the last one ended)
            obs = see(env.reset()[0][None])[0]
        # act: random while seeding, then planned with exploration noise
        if count <= settings.seed_steps:
            action = rng.uniform(-1.0, 1.0, action_dim).astype(np.float32)
        else:
            with torch.no_grad():
                z = model.encode(torch.as_tensor(obs, device=device)[None])
            config = planner_config(settings, count - 1, action_dim)
            result = plan(model, z, config, generator, None if first else warm, explore=True)
            warm, action = result.mean, result.action[0].cpu().numpy()
        raw_next, reward, terminated, truncated, _ = env.step(action)
        next_obs = see(raw_next[None])[0]
        buffer.add(obs, action, reward, next_obs, first)
        first = terminated or truncated
        obs = None if first else next_obs
        # update: seed_steps updates when the seeding ends, then one per interaction step
        if count >= settings.seed_steps and buffer.starts > 0:
            for _ in range(settings.seed_steps if count == settings.seed_steps else 1):
                batch = buffer.sample(settings.batch_size, rng)
                _, priority = learner.update(batch)
                buffer.update(batch.index, priority.numpy())
        # evaluate
        if points and count >= points[0]:
            points = [p for p in points if p > count]
            samples = {"gradient_samples": learner.updates * settings.batch_size}  # sequences of H steps
            recorder.measure(evaluation_agent(model, settings, count, seed, see), count, extra=samples)
        recorder.show(count)
        # save between episodes, when due
        if first and count < budget and time.perf_counter() - saved >= resume.every:
            save_state(resume.state_file, resume.run, count, learner, buffer, generators, recorder.curve,
                       recorder.wall_seconds)  # fmt: skip
            saved = time.perf_counter()
    return model
