"""The Stable-Baselines3 baselines: PPO and SAC trained on the tracking environments, scored like EfficientTrack.

:func:`train_baseline` trains one method with SB3 (not rewritten here) on the training references, on
N environments that step one batched system (:class:`~efficienttrack.baselines.vec_env.SB3VecEnv` over
:class:`efficienttrack.envs.TrackingVectorEnv`), and at chosen interaction counts evaluates the deterministic policy
on the held-out references with :func:`efficienttrack.envs.evaluate` and :func:`efficienttrack.metrics.compute_metrics`:
the same episodes and the same metrics as EfficientTrack's evaluation. The curve goes to ``curve.json`` point by point.

An interaction step is one environment step of one machine (20 Hz): N parallel environments stepping once are N
interaction steps, which is how the paper counts I.S. and what SB3's ``num_timesteps`` counts.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback

from efficienttrack.baselines.settings import PPOSettings, SACSettings, method_settings
from efficienttrack.baselines.vec_env import SB3VecEnv
from efficienttrack.configfile import check_seed
from efficienttrack.envs.core import open_system
from efficienttrack.envs.evaluation import evaluate
from efficienttrack.envs.vector import TrackingVectorEnv
from efficienttrack.errors import EfficientTrackError
from efficienttrack.fileio import atomic_write, check_output_folder, output_lock, write_json
from efficienttrack.metrics import MIN_STEPS, compute_metrics
from efficienttrack.progress import ProgressDisplay
from efficienttrack.references import Reference
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import SystemSpec

LOOPS = ("closed", "open")
"""The two settings a baseline trains in: adjusting the PD reference (closed) or sending PWM (open)."""

MAX_SB3_SEED = 2**32 - 1025
"""Largest seed: SB3 seeds numpy's legacy generator (< 2^32) and gives environment i the seed + i."""

CURVE_FILE = "curve.json"
"""The curve's file in the output folder, rewritten atomically after every evaluation point."""

MODEL_FILE = "model.zip"
"""The final model, saved with SB3's ``save`` for the user's own use; efficienttrack never loads it."""


def default_eval_points(budget: int) -> list[int]:
    """The interaction counts 1, 2, 5 × 10^k up to ``budget``, and ``budget`` itself.

    Args:
        budget: the training budget in interaction steps (≥ 1).

    Returns:
        Increasing counts, e.g. ``[1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 1500]`` for 1500.
    """
    points = {m * 10**k for k in range(len(str(budget))) for m in (1, 2, 5)}
    return sorted(p for p in points | {budget} if p <= budget)


def check_eval_points(eval_at: Sequence[int] | None, budget: int) -> list[int]:
    """The evaluation points, checked, sorted and without repeats (:func:`default_eval_points` when None).

    Args:
        eval_at: interaction counts at which to evaluate, each in ``[1, budget]``, or None.
        budget: the training budget in interaction steps.

    Returns:
        The increasing counts.

    Raises:
        EfficientTrackError: a count that is not an integer, < 1, or beyond the budget, or none at all.
    """
    if eval_at is None:
        return default_eval_points(budget)
    points = list(eval_at)
    if not points:
        raise EfficientTrackError("eval_at: no evaluation point given")
    for point in points:
        if not isinstance(point, int | np.integer) or isinstance(point, bool) or not 1 <= point <= budget:
            raise EfficientTrackError(f"eval_at: each point must be an integer in [1, budget = {budget}], got {point!r}")
    return sorted({int(p) for p in points})


class _Recorder:
    """The curve of one training run: measures points, writes ``curve.json``, shows progress."""

    def __init__(
        self,
        header: dict[str, Any],
        path: Path,
        system: BatchedSystem,
        test_refs: list[Reference],
        progress: ProgressDisplay | None,
        budget: int,
    ) -> None:
        self.header, self.path, self.system, self.test_refs, self.progress = header, path, system, test_refs, progress
        self.curve: list[dict[str, Any]] = []
        self.start = time.perf_counter()
        self.evaluating = 0.0
        """Seconds spent evaluating, left out of the wall time."""
        label = f"{header['method']} {header['loop']} (steps)"
        self.task = None if progress is None else progress.add_task(label, total=budget)
        write_json(path, {**header, "curve": self.curve})

    def measure(self, model: BaseAlgorithm, count: int) -> None:
        """Evaluate ``model``'s deterministic policy on the test references; append the point and write the file."""
        began = time.perf_counter()
        act = lambda obs: model.predict(obs, deterministic=True)[0]  # noqa: E731
        records = evaluate(act, self.test_refs, loop=self.header["loop"], system=self.system)
        metrics = compute_metrics(records)
        self.curve.append(
            {"interaction_steps": count, "wall_seconds": began - self.start - self.evaluating, "metrics": metrics}
        )
        write_json(self.path, {**self.header, "curve": self.curve})
        self.evaluating += time.perf_counter() - began
        if self.progress is not None and self.task is not None:
            self.progress.update(self.task, mae_deg=metrics["mae_deg"])

    def show(self, count: int) -> None:
        """Show the interaction count on the progress display."""
        if self.progress is not None and self.task is not None:
            self.progress.update(self.task, completed=count)

    def close(self) -> None:
        """Stop showing the task."""
        if self.progress is not None and self.task is not None:
            self.progress.remove_task(self.task)


class _Curve(BaseCallback):
    """SB3 callback: evaluate at the requested interaction counts, stop at the budget.

    A point is measured at the first step whose count ``num_timesteps`` reaches it; with N environments the count
    moves in steps of N, so points reached in the same step are measured once, at that step's count.
    """

    def __init__(self, points: list[int], budget: int, recorder: _Recorder) -> None:
        super().__init__()
        self.points, self.budget, self.recorder = list(points), budget, recorder

    def _on_step(self) -> bool:
        count = self.num_timesteps
        if self.points and count >= self.points[0]:
            self.points = [p for p in self.points if p > count]
            self.recorder.measure(self.model, count)
        self.recorder.show(count)
        return count < self.budget


def _check_refs(refs: Sequence[Reference], name: str, min_steps: int = 2) -> list[Reference]:
    refs = list(refs)
    if not refs:
        raise EfficientTrackError(f"{name}: no references given")
    for ref in refs:
        if not isinstance(ref, Reference):
            raise EfficientTrackError(f"{name}: expected References (efficienttrack.references), got {type(ref).__name__}")
        if len(ref) < min_steps:
            raise EfficientTrackError(f"{name}: reference '{ref.name}' has {len(ref)} steps, needs at least {min_steps}")
    return refs


def train_baseline(
    method: str,
    loop: str,
    system: SystemSpec,
    train_refs: Sequence[Reference],
    test_refs: Sequence[Reference],
    budget: int,
    seed: int,
    folder: str | Path,
    preset: str | PPOSettings | SACSettings = "full",
    eval_at: Sequence[int] | None = None,
    progress: ProgressDisplay | None = None,
) -> list[dict[str, Any]]:
    """Train PPO or SAC with Stable-Baselines3 for ``budget`` interaction steps; evaluate it along the way.

    Training runs on the training references (one episode per reference, picked by each environment's seeded
    generator) with ``settings.n_envs`` environments stepping one batched system. When the interaction count first
    reaches a point of ``eval_at``, the deterministic policy (the mean action, clipped to [−1, 1]) runs every test
    reference once (:func:`efficienttrack.envs.evaluate`) and :func:`efficienttrack.metrics.compute_metrics` scores it.
    ``folder/curve.json`` (``{"method", "loop", "seed", "budget", "system", "settings", "curve": [point, ...]}``) is
    rewritten atomically after each point, so an interrupted run keeps every point it measured; a new run in the
    folder starts over (same seed, same points). The final model goes to ``folder/model.zip`` (SB3's format, for the
    user; nothing here loads it). The same seed and settings give the same curve (wall times aside) on one machine.

    Args:
        method: ``"ppo"`` or ``"sac"``.
        loop: ``"closed"`` (the policy adjusts the PD reference) or ``"open"`` (the policy sends PWM / 1000 to the
            plant: ``system`` must name a PWM-level plant, e.g. ``SystemSpec(plant="xe75")`` or the built-in system).
        system: the system spec both training and evaluation run on.
        train_refs: the training references (``.q`` (T, 4) rad).
        test_refs: the held-out references the curve is measured on (each ≥ 4 steps).
        budget: interaction steps to train for (≥ 1): steps of all parallel environments summed, the paper's I.S.
            With N environments training stops at the first multiple of N that reaches it.
        seed: seed of SB3 (Python, numpy, torch, the action space) and of the environments (environment i: seed + i).
        folder: output folder for ``curve.json`` and ``model.zip`` (created; other files in it are left alone).
        preset: ``"full"``, ``"quick"`` (:data:`~efficienttrack.baselines.settings.PRESETS`) or the method's settings.
        eval_at: interaction counts to evaluate at, each in ``[1, budget]``; None for :func:`default_eval_points`.
        progress: a display to show the training steps and the last MAE on, or None for no progress.

    Returns:
        One point per measurement, in order: ``{"interaction_steps": int (the count when measured: the first
        multiple of N at or after the requested point), "wall_seconds": float (training wall time so far, building
        the model included, evaluations excluded), "metrics": dict (compute_metrics of the test episodes)}``.

    Raises:
        EfficientTrackError: an unknown method, loop or preset, a budget < 1, an evaluation point outside
            ``[1, budget]``, a bad seed, a system that is no SystemSpec, no references or a test reference shorter
            than 4 steps, an output folder that cannot be written or is being written by
            another process, or a problem the environments report (a system spec, a reference outside the limits).
    """
    settings = method_settings(method, preset)
    if loop not in LOOPS:
        raise EfficientTrackError(f"loop '{loop}': unknown (known: {', '.join(LOOPS)})")
    if not isinstance(budget, int | np.integer) or isinstance(budget, bool) or budget < 1:
        raise EfficientTrackError(f"budget: must be an integer ≥ 1 interaction step, got {budget!r}")
    budget = int(budget)
    points = check_eval_points(eval_at, budget)
    if check_seed(seed, "seed") > MAX_SB3_SEED:
        raise EfficientTrackError(f"seed: SB3 needs a seed in [0, {MAX_SB3_SEED}], got {seed}")
    if not isinstance(system, SystemSpec):
        raise EfficientTrackError(f"system: expected a SystemSpec (efficienttrack.systems.spec), got {type(system).__name__}")
    train_refs, test_refs = _check_refs(train_refs, "train_refs"), _check_refs(test_refs, "test_refs", MIN_STEPS)
    folder = check_output_folder(folder, "folder")
    header = {
        "method": method,
        "loop": loop,
        "seed": seed,
        "budget": budget,
        "system": system.to_dict(),
        "settings": asdict(settings),
    }
    with output_lock(folder / CURVE_FILE, "folder", folder=False):
        recorder = _Recorder(header, folder / CURVE_FILE, open_system(loop, system), test_refs, progress, budget)
        env = SB3VecEnv(TrackingVectorEnv(settings.n_envs, loop=loop, system=system, refs=train_refs))
        try:
            model = settings.build(env, seed)
            model.learn(total_timesteps=budget, callback=_Curve(points, budget, recorder))
            atomic_write(folder / MODEL_FILE, model.save)
        finally:
            env.close()
            recorder.close()
    return recorder.curve
