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

    Training runs on the training references (one episode per reference, picked by each environment's seeded
    generator) with ``settings.n_envs`` environments stepping one batched system. With ``settings.inputs ==
    "relative"`` the policy sees the standardized relative features of
    :func:`~efficienttrack.envs.features.pd_pipeline` (statistics from a PD pass over the training references), in
    training and evaluation alike; the untrained policy is the PD controller (its action mean starts at zero).
    When the interaction count first reaches a point of ``run.points``, the deterministic policy (the mean action,
    clipped to [−1, 1]) runs every test reference once (:func:`efficienttrack.envs.evaluate`) and
    :func:`efficienttrack.data.metrics.compute_metrics` scores it; then every validation reference, when the run has
    them. ``folder/curve.json`` (``{"method", "loop", "seed", "budget", "system", "settings", "curve": [point, ...]}``)
    is rewritten atomically after each point. Between rollouts, every ``save_every_seconds``, the training state goes
    to ``folder/training_state.pt`` (:mod:`.sb3_state`: no pickle); the same run started again in the folder resumes
    from it, keeping the points measured up to it, with fresh episodes (so not bit-identical to an uninterrupted
    run). The state is removed once the run has finished; the final model goes to ``folder/model.zip`` (SB3's
    format, for the user; nothing here loads it). The same seed and settings give the same curve (wall times aside)
    on one machine when the run is not interrupted.

    Args:
        method: ``"ppo"`` or ``"sac"``.
        run: the run (:func:`~efficienttrack.baselines.curve.training_run`): ``loop`` ``"closed"`` (the policy adjusts
            the PD reference) or ``"open"`` (the policy sends PWM / 1000 to the plant under ``system``); ``budget``,
            the steps of all parallel environments summed (with N environments training stops at the first multiple
            of N that reaches it); ``seed`` (≤ ``MAX_SB3_SEED``) seeds SB3 (Python, numpy, torch, the action space)
            and the environments (environment i: seed + i); ``folder`` gets ``curve.json`` and ``model.zip`` (created;
            other files in it are left alone).
        preset: ``"paper"``, ``"cpu"``, ``"tiny"`` (:data:`~efficienttrack.baselines.settings.PRESETS`) or the method's
            settings.
        progress: a display to show the training steps and the last MAE on, or None for no progress.
        save_every_seconds: wall seconds between saves of the training state (0: at every rollout's start).

    Returns:
        One point per measurement, in order: ``{"interaction_steps": int (the count when measured: the first
        multiple of N at or after the requested point), "wall_seconds": float (training wall time so far, building
        the model included, evaluations excluded), "metrics": dict (compute_metrics of the test episodes)}``, and
        ``"validation"`` (compute_metrics of the validation episodes) when the run has validation references.

    Raises:
        EfficientTrackError: an unknown method or preset, a run that is no TrainingRun, a seed beyond
            ``MAX_SB3_SEED``, an output folder that cannot be written or is being written by another process, a
            training state in the folder from another run, or a problem the environments report (a system spec, a
            reference outside the limits).
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
