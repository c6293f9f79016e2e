"""The Stable-Baselines3 baselines: PPO and SAC trained on the tracking environments, scored like EfficientTrack.

:func:`train_baseline` trains one method with SB3 (not rewritten here) on the training references, on
N environments that step one batched system (:class:`~efficienttrack.baselines.vec_env.SB3VecEnv` over
:class:`efficienttrack.envs.TrackingVectorEnv`), and at chosen interaction counts evaluates the deterministic policy
on the held-out references with :func:`efficienttrack.envs.evaluate` and :func:`efficienttrack.data.metrics.compute_metrics`:
the same episodes and the same metrics as EfficientTrack's evaluation. The curve goes to ``curve.json`` point by point.

An interaction step is one environment step of one machine (20 Hz): N parallel environments stepping once are N
interaction steps, which is how the paper counts I.S. and what SB3's ``num_timesteps`` counts.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import numpy as np
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv

from efficienttrack.baselines.curve import CURVE_FILE, CurveRecorder, TrainingRun, check_training_run
from efficienttrack.baselines.resume import SAVE_EVERY_SECONDS, STATE_FILE, run_identity
from efficienttrack.baselines.sb3_state import restore_state, save_state
from efficienttrack.baselines.settings import PPOSettings, SACSettings, method_settings
from efficienttrack.baselines.vec_env import FeatureVecEnv, SB3VecEnv
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, output_lock
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.envs.core import open_system
from efficienttrack.envs.features import ObservationPipeline, See, learner_input
from efficienttrack.envs.vector import TrackingVectorEnv

MAX_SB3_SEED = 2**32 - 1025
"""Largest seed: SB3 seeds numpy's legacy generator (< 2^32) and gives environment i the seed + i."""

MODEL_FILE = "model.zip"
"""The final model, saved with SB3's ``save`` for the user's own use; efficienttrack never loads it."""


class _Curve(BaseCallback):
    """SB3 callback: evaluate at the requested interaction counts, stop at the budget, save the state between rollouts.

    A point is measured at the first step whose count ``num_timesteps`` reaches it; with N environments the count
    moves in steps of N, so points reached in the same step are measured once, at that step's count. At the start of
    a rollout (the previous update done) the training state is saved when ``every`` seconds have passed since the last.
    ``see`` turns the evaluation's flat observations into what the policy was trained on (the observation pipeline).
    """

    def __init__(
        self,
        points: list[int],
        budget: int,
        recorder: CurveRecorder,
        save: Callable[[], None],
        every: float,
        see: See,
    ) -> None:
        super().__init__()
        self.points, self.budget, self.recorder = list(points), budget, recorder
        self.save, self.every, self.saved = save, every, time.perf_counter()
        self.see = see

    def _on_rollout_start(self) -> None:
        if time.perf_counter() - self.saved >= self.every:
            self.save()
            self.saved = time.perf_counter()

    def _on_step(self) -> bool:
        count = self.num_timesteps
        if self.points and count >= self.points[0]:
            self.points = [p for p in self.points if p > count]
            self.recorder.measure(
                lambda obs: self.model.predict(self.see(obs), deterministic=True)[0], count,
                extra={"gradient_samples": gradient_samples(self.model)},
            )  # fmt: skip
        self.recorder.show(count)
        return count < self.budget


def gradient_samples(model: BaseAlgorithm) -> int:
    """The transitions the model's gradient steps took so far (a curve point's ``gradient_samples``).

    PPO's epochs × its rollout (n_steps × n_envs; an epoch that its KL target cut short counts whole), SAC's gradient
    steps × its batch.
    """
    if isinstance(model, PPO):
        return int(model._n_updates) * model.n_steps * model.n_envs
    assert isinstance(model, SAC), type(model)
    return int(model._n_updates) * model.batch_size


def train_baseline(
    method: str,
    run: TrainingRun,
    preset: str | PPOSettings | SACSettings = "cpu",
    progress: ProgressDisplay | None = None,
    save_every_seconds: float = SAVE_EVERY_SECONDS,
) -> list[dict[str, Any]]:
    """Train PPO or SAC with Stable-Baselines3 for ``run.budget`` interaction steps; evaluate it along the way.

    The learner sees what EfficientTrack's networks see (``settings.inputs``, standardized on a PD pass over the
    training references) and starts as the PD controller. At each of ``run.points`` its deterministic policy is scored
    on the test (and validation) references through the guarded evaluation every method shares, and
    ``folder/curve.json`` is rewritten. The training state is saved between rollouts without pickle (:mod:`.sb3_state`),
    so a killed run resumes, with fresh episodes (not bit-identical to an uninterrupted run); the final model goes to
    ``folder/model.zip`` for the user.

    Args:
        method: ``"ppo"`` or ``"sac"``.
        run: the run (:func:`~efficienttrack.baselines.curve.training_run`); with N environments training stops at the
            first multiple of N that reaches ``budget``; ``seed`` ≤ ``MAX_SB3_SEED``.
        preset: ``"paper"``, ``"cpu"``, ``"tiny"`` (:data:`~efficienttrack.baselines.settings.PRESETS`) or the method's
            settings.
        progress: a display to show the training steps and the last MAE on, or None for no progress.
        save_every_seconds: wall seconds between saves of the training state (0: at every rollout's start).

    Returns:
        One point per measurement: ``{"interaction_steps", "wall_seconds" (training so far, evaluations excluded),
        "metrics"}``, and ``"validation"`` when the run has validation references.

    Raises:
        EfficientTrackError: an unknown method or preset, a bad run or seed, a folder in use or holding another run's
            state, or a problem the environments report.
    """
    settings = method_settings(method, preset)
    run = check_training_run(run)
    if run.seed > MAX_SB3_SEED:
        raise EfficientTrackError(f"seed: SB3 needs a seed in [0, {MAX_SB3_SEED}], got {run.seed}")
    loop, system, seed, folder, train_refs = run.loop, run.system, run.seed, run.folder, run.train_refs
    header = {
        "method": method,
        "loop": loop,
        "seed": seed,
        "budget": run.budget,
        "system": system.to_dict(),
        "settings": asdict(settings),
    }
    run_id = run_identity(header, run)
    state_file = folder / STATE_FILE
    with output_lock(folder / CURVE_FILE, "folder", folder=False):
        recorder = CurveRecorder(run, header, open_system(loop, system), progress)
        env: VecEnv = SB3VecEnv(TrackingVectorEnv(settings.n_envs, loop=loop, system=system, refs=train_refs))
        see = learner_input(settings.inputs, loop, system, train_refs)
        if isinstance(see, ObservationPipeline):  # the input every learner shares, from the training references only
            env = FeatureVecEnv(env, see)
        try:
            model = settings.build(env, seed)
            if state_file.exists():
                curve, wall = restore_state(model, state_file, run_id)
                recorder.resume(curve, wall, model.num_timesteps)
                env.seed(int(np.random.SeedSequence([seed, model.num_timesteps]).generate_state(1)[0]) % MAX_SB3_SEED)
            done = model.num_timesteps
            todo = [p for p in run.points if p > done]

            def save() -> None:
                save_state(model, state_file, run_id, recorder.curve, recorder.wall_seconds)

            callback = _Curve(todo, run.budget, recorder, save, save_every_seconds, see)
            model.learn(total_timesteps=run.budget - done, callback=callback, reset_num_timesteps=done == 0)
            # SB3 annotates a BufferedIOBase: the binary file atomic_write opens is one.
            atomic_write(folder / MODEL_FILE, model.save)  # type: ignore[arg-type]
            state_file.unlink(missing_ok=True)
        finally:
            env.close()
            recorder.close()
    return recorder.curve
