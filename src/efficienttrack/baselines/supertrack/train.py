"""SuperTrack (Fussell et al. 2021): a world model learnt online, a policy trained by backpropagation through it.

One iteration of :func:`train_supertrack`:

1. **collect**: the current policy plus exploration noise (AR(1), seeded) runs whole episodes on training
   references drawn at random until ``steps_per_iteration`` interaction steps are spent, through the environments'
   episode loop (:func:`efficienttrack.envs.evaluate`); the episodes go into the replay buffer (the most recent
   ``buffer_steps``). In the first iteration the policy is a = 0 (closed loop: the PD controller; open loop: u = 0,
   so the noise alone moves the machine).
2. **world model**: ``model.steps`` multi-step optimizer steps on buffer windows
   (:func:`efficienttrack.learn.dynamics.train_model`, warm-started from the last iteration's model): in the closed
   loop g_θ of the PD loop driven by the references sent, in the open loop g_θ of the plant driven by the PWM
   (:class:`~efficienttrack.learn.dynamics.PlantModel`).
3. **policy**: ``policy.steps`` optimizer steps through the frozen world model from buffer windows on the discounted
   tracking loss plus the smoothness term (:func:`efficienttrack.learn.policy.train_policy`, warm-started).
4. **evaluate** the noiseless policy on the held-out references when the interaction count first reaches an
   evaluation point (:class:`~efficienttrack.baselines.curve.CurveRecorder`).

What is SuperTrack's and what is ours: SuperTrack's loop (collect with the policy and noise, train the world model,
train the policy through it, repeat), its world-model window 8, its learning rates; ours: the networks and losses of
EfficientTrack (:mod:`efficienttrack.learn.dynamics`, :mod:`efficienttrack.learn.policy`: SuperTrack's character-specific
losses on rigid-body positions and rotations become the joint tracking error of an excavator), the policy window 20
(the environments show 20 desired positions; SuperTrack's is 32), and the noise.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, replace
from typing import Any

import numpy as np

from efficienttrack.baselines.agent import Noise, policy_act
from efficienttrack.baselines.curve import CURVE_FILE, CurveRecorder, TrainingRun, check_training_run
from efficienttrack.baselines.resume import SAVE_EVERY_SECONDS, STATE_FILE, run_identity
from efficienttrack.baselines.supertrack.settings import SuperTrackSettings, supertrack_settings
from efficienttrack.baselines.supertrack.state import Progress, restore_state, save_state
from efficienttrack.core.fileio import output_lock
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.data.records import EpisodeRecord
from efficienttrack.data.references import Reference
from efficienttrack.envs.core import open_system
from efficienttrack.envs.evaluation import evaluate
from efficienttrack.learn.dynamics import ClosedLoopModel, PlantModel, train_model
from efficienttrack.learn.policy import AdjustmentPolicy, PWMPolicy, train_policy


def draw_references(refs: Sequence[Reference], steps: int, rng: np.random.Generator) -> list[Reference]:
    """References drawn at random (with repeats) until their episodes hold at least ``steps`` interaction steps.

    Args:
        refs: the training references.
        steps: interaction steps wanted, ≥ 1.
        rng: the generator.

    Returns:
        The drawn references, in the order drawn.
    """
    drawn, total = [], 0
    while total < steps:
        ref = refs[int(rng.integers(len(refs)))]
        drawn.append(ref)
        total += ref.steps
    return drawn


def keep_recent(buffer: list[EpisodeRecord], capacity: int) -> list[EpisodeRecord]:
    """The most recent episodes whose steps fit ``capacity`` (at least the newest one).

    Args:
        buffer: episodes, oldest first.
        capacity: the most steps to keep.
    """
    sizes = np.cumsum([len(r) for r in reversed(buffer)])
    keep = max(1, int(np.searchsorted(sizes, capacity, side="right")))
    return buffer[-keep:]


def train_supertrack(
    run: TrainingRun,
    preset: str | SuperTrackSettings = "cpu",
    progress: ProgressDisplay | None = None,
    save_every_seconds: float = SAVE_EVERY_SECONDS,
) -> list[dict[str, Any]]:
    """Train SuperTrack for ``run.budget`` interaction steps (module docstring); the curve of its test metrics.

    The last iteration collects only what is left of the budget (whole episodes, so it may end up to one episode
    past it). A point is measured after the first iteration whose count reaches it (points reached together once), on
    the test references and then, when the run has them, the validation references. ``folder/curve.json`` is rewritten
    after each point. After an iteration, every ``save_every_seconds``, the state goes to ``folder/training_state.pt``
    (:mod:`.state`: no pickle); the same run started again in the folder resumes from it and continues as the
    uninterrupted run would. The state is removed once the run has finished.

    Args:
        run: the run (:func:`~efficienttrack.baselines.curve.training_run`): ``loop`` ``"closed"`` (the policy adjusts
            the PD reference) or ``"open"`` (the policy sends PWM / 1000 to the plant under ``system``); ``seed`` seeds
            the reference draws, the noise and the trainings; ``folder`` gets ``curve.json``.
        preset: ``"cpu"``, ``"tiny"`` (:data:`~.settings.SUPERTRACK_PRESETS`) or a :class:`SuperTrackSettings`.
        progress: a display for the interaction count and the last MAE, or None.
        save_every_seconds: wall seconds between saves of the state (0: after every iteration).

    Returns:
        One point per measurement: ``{"interaction_steps", "wall_seconds" (training so far, evaluations excluded),
        "metrics": compute_metrics of the test episodes, "iterations"}``, and ``"validation"`` (compute_metrics of the
        validation episodes) when the run has validation references.

    Raises:
        EfficientTrackError: an unknown preset, a run that is no TrainingRun, a folder being written by another
            process, or a training state in the folder from another run.
    """
    settings = supertrack_settings(preset)
    run = check_training_run(run)
    loop, system, seed = run.loop, run.system, run.seed
    stepped = open_system(loop, system)
    closed = loop == "closed"
    world, actor = (ClosedLoopModel, AdjustmentPolicy) if closed else (PlantModel, PWMPolicy)
    bound = tuple(float(b) for b in stepped.limits.max_adjust)
    policy_cfg = replace(settings.policy, max_adjust=bound) if closed else settings.policy
    header = {"method": "supertrack", "loop": loop, "seed": seed, "budget": run.budget, "system": system.to_dict(),
              "settings": asdict(settings)}  # fmt: skip
    per_iteration = (  # windows of an iteration's two trainings; an epoch schedule's follow the buffer: not counted
        None if settings.model.steps is None or policy_cfg.steps is None
        else settings.model.steps * settings.model.batch_size + policy_cfg.steps * policy_cfg.batch_size
    )  # fmt: skip
    rng = np.random.default_rng([seed, 0x5E7])
    noise = Noise(settings.noise(loop), settings.noise_rho, rng)
    buffer: list[EpisodeRecord] = []
    model, policy = None, None
    count, iteration = 0, 0
    run_id = run_identity(header, run)
    state_file, saved = run.folder / STATE_FILE, time.perf_counter()
    with output_lock(run.folder / CURVE_FILE, "folder", folder=False):
        recorder = CurveRecorder(run, header, stepped, progress)
        try:
            if state_file.exists():
                model, policy = world(settings.model), actor(policy_cfg)
                count, iteration, buffer, curve, wall = restore_state(state_file, run_id, model, policy, rng, noise)
                recorder.resume(curve, wall, count)
            points = [p for p in run.points if p > count]
            while count < run.budget:
                # collect: the policy plus noise on references drawn at random
                drawn = draw_references(run.train_refs, min(settings.steps_per_iteration, run.budget - count), rng)
                buffer = keep_recent(buffer + evaluate(policy_act(policy, loop, noise), drawn, loop, stepped),
                                     settings.buffer_steps)  # fmt: skip
                count += sum(ref.steps for ref in drawn)
                # world model, then the policy through it, both warm-started from the last iteration
                train_seed = seed + iteration
                model = train_model(settings.model, buffer, settings.device, train_seed, progress=False, init=model,
                                    network=world).model  # fmt: skip
                policy = train_policy(policy_cfg, model, buffer, settings.device, train_seed, progress=False,
                                      init=policy, network=actor).policy.cpu()  # fmt: skip
                iteration += 1
                # evaluate at the points reached
                if points and count >= points[0]:
                    points = [p for p in points if p > count]
                    samples = iteration * per_iteration if per_iteration is not None else None
                    recorder.measure(policy_act(policy, loop), count,
                                     extra={"iterations": iteration, "gradient_samples": samples})  # fmt: skip
                recorder.show(count)
                if time.perf_counter() - saved >= save_every_seconds and count < run.budget:
                    done = Progress(count, iteration, buffer, recorder.curve, recorder.wall_seconds)
                    save_state(state_file, run_id, done, model, policy, rng, noise)
                    saved = time.perf_counter()
            state_file.unlink(missing_ok=True)
        finally:
            recorder.close()
    return recorder.curve
