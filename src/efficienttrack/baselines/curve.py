"""What every baseline shares: its run, the evaluation points, the held-out measurement, and ``curve.json``.

A baseline's ``train_<method>(run, settings)`` takes one checked :class:`TrainingRun` (:func:`training_run`): the loop,
the system, the training, test and validation references, the budget, the seed, the output folder and the evaluation
points. It trains for the budget of interaction steps and, when its count first reaches each evaluation point, runs its
deterministic policy on the held-out references (:func:`efficienttrack.envs.evaluate`) and scores it with
:func:`efficienttrack.data.metrics.compute_metrics`: the same episodes and metrics as EfficientTrack's evaluation; with
validation references, the same policy on them right after. :class:`CurveRecorder` keeps those points and rewrites
``curve.json`` after each, so a long run loses nothing.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from efficienttrack.core.configfile import check_seed
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_output_folder, write_json
from efficienttrack.core.progress import ProgressDisplay
from efficienttrack.data.metrics import MIN_STEPS, compute_metrics
from efficienttrack.data.references import Reference
from efficienttrack.envs.core import check_loop
from efficienttrack.envs.evaluation import evaluate
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.systems.spec import SystemSpec

CURVE_FILE = "curve.json"
"""The curve's file in the output folder, rewritten atomically after every evaluation point."""


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


class CurveRecorder:
    """The curve of one training run: measures points, writes ``folder/curve.json``, shows progress.

    Args:
        run: the run (its loop, test and validation references, folder and budget).
        header: what the run is (``method``, ``loop``, ``seed``, ``budget``, ``system``, ``settings``), written with
            the curve.
        system: the checked system the references run on (the closed loop, or the plant for the open loop).
        progress: a display to show the interaction count and the last MAE on, or None.
        total: the progress bar's total in interaction steps; None: the run's budget.
    """

    def __init__(
        self,
        run: TrainingRun,
        header: dict[str, Any],
        system: BatchedSystem,
        progress: ProgressDisplay | None,
        total: int | None = None,
    ) -> None:
        self.run, self.header, self.system, self.progress = run, header, system, progress
        self.path = run.folder / CURVE_FILE
        self.curve: list[dict[str, Any]] = []
        self.start = time.perf_counter()
        self.evaluating = 0.0
        """Seconds spent evaluating, left out of the wall time."""
        label = f"{header['method']} {run.loop} (steps)"
        self.task = None if progress is None else progress.add_task(label, total=run.budget if total is None else total)
        write_json(self.path, {**header, "curve": self.curve})

    @property
    def wall_seconds(self) -> float:
        """The training wall time so far, evaluations excluded."""
        return time.perf_counter() - self.start - self.evaluating

    def resume(self, curve: list[dict[str, Any]], wall_seconds: float, count: int) -> None:
        """Continue a run from its saved state: the points it measured, its wall time and its interaction steps.

        Args:
            curve: the points measured before the state was saved (later ones are measured again).
            wall_seconds: the training wall time at the state; the wall times of new points continue from it.
            count: interaction steps of the state; the progress display's time left counts only the steps from here.
        """
        self.curve = list(curve)
        self.start, self.evaluating = time.perf_counter() - wall_seconds, 0.0
        write_json(self.path, {**self.header, "curve": self.curve})
        if self.progress is not None and self.task is not None:
            self.progress.resume(self.task, completed=count)

    def measure(
        self,
        act: Callable[[np.ndarray], np.ndarray],
        count: int,
        wall_seconds: float | None = None,
        extra: dict[str, Any] | None = None,
    ) -> None:
        """Run the deterministic policy ``act`` on the test and validation references; append the point, write the file.

        The validation references (when the run has them) come after the test references, so that an agent with a
        state (TD-MPC's planner and its generator) meets the test references as it would without validation. Both
        evaluations are left out of the wall time.

        Args:
            act: observations (N, 332) float32 → actions (N, 4) in [−1, 1] (:func:`efficienttrack.envs.evaluate`).
            count: the interaction steps trained so far.
            wall_seconds: the wall time the point took, for a method whose points are separate runs (open-loop
                EfficientTrack: one run per pass count); None: the recorder's time so far, evaluations excluded.
            extra: further facts of the point (e.g. ``{"passes": 2}``), added to it.
        """
        wall = self.wall_seconds if wall_seconds is None else wall_seconds
        began = time.perf_counter()
        metrics = self._score(act, self.run.test_refs)
        if self.run.validation_refs:
            extra = {**(extra or {}), "validation": self._score(act, self.run.validation_refs)}
        self.add(count, wall, metrics, extra)
        self.evaluating += time.perf_counter() - began

    def _score(self, act: Callable[[np.ndarray], np.ndarray], refs: Sequence[Reference]) -> dict[str, Any]:
        """:func:`~efficienttrack.data.metrics.compute_metrics` of ``act`` run on every reference of ``refs`` once."""
        return compute_metrics(evaluate(act, refs, loop=self.run.loop, system=self.system))

    def add(self, count: int, wall_seconds: float, metrics: dict[str, Any], extra: dict[str, Any] | None = None) -> None:
        """Append a point measured by the caller and write the file (what :meth:`measure` does after evaluating).

        For a method whose "policy" is no function of the observation (the ILC oracle's stored corrections, which has
        no validation references).

        Args:
            count: the interaction steps trained so far.
            wall_seconds: the training wall time so far (evaluations excluded).
            metrics: :func:`~efficienttrack.data.metrics.compute_metrics` of the test episodes.
            extra: further facts of the point (e.g. ``{"passes": 2}``; :meth:`measure` puts ``"validation"`` here),
                added to it.
        """
        point = {"interaction_steps": int(count), "wall_seconds": float(wall_seconds), "metrics": metrics}
        self.curve.append({**point, **(extra or {})})
        write_json(self.path, {**self.header, "curve": self.curve})
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


def earlier_points(path: Path, header: dict[str, Any]) -> list[dict[str, Any]]:
    """The points an earlier run with the same ``header`` wrote to ``path``; none for another run or no readable file.

    For a method whose points are separate trainings (open-loop EfficientTrack: one per pass count), which resumes by
    keeping the points already measured.

    Args:
        path: the run's ``curve.json``.
        header: this run's header (method, loop, seed, budget, system, settings, references).

    Returns:
        The earlier run's points, in order.
    """
    try:
        earlier = json.loads(path.read_text())
    except (OSError, ValueError):
        return []
    same = isinstance(earlier, dict) and all(
        earlier.get(key) == json.loads(json.dumps(value)) for key, value in header.items()
    )
    points = earlier.get("curve") if same else None
    return points if isinstance(points, list) and all(isinstance(p, dict) for p in points) else []


def check_refs(refs: Sequence[Reference], name: str, min_steps: int = 2) -> list[Reference]:
    """The references as a list, each a :class:`Reference` of at least ``min_steps`` steps.

    Args:
        refs: the references given.
        name: the argument's name, for errors.
        min_steps: fewest positions a reference may have.

    Returns:
        The references.

    Raises:
        EfficientTrackError: none given, something else than a Reference, or a reference that is too short.
    """
    refs = list(refs)
    if not refs:
        raise EfficientTrackError(f"{name}: no references given")
    for ref in refs:
        if not isinstance(ref, Reference):
            raise EfficientTrackError(
                f"{name}: expected References (efficienttrack.data.references), got {type(ref).__name__}"
            )
        if len(ref) < min_steps:
            raise EfficientTrackError(f"{name}: reference '{ref.name}' has {len(ref)} steps, needs at least {min_steps}")
    return refs


class TrainingRun(NamedTuple):
    """One training run of a baseline, checked (build it with :func:`training_run`, which checks every field).

    Every ``train_<method>(run, ...)`` of :mod:`efficienttrack.baselines` takes one. References are
    :class:`~efficienttrack.data.references.Reference`: desired joint positions ``.q`` (T, 4) rad (boom, arm, bucket,
    swing) at the system's control rate (20 Hz); an episode of a reference of T positions is T − 1 interaction steps.

    Attributes:
        loop: ``"closed"`` (the policy adjusts the PD reference) or ``"open"`` (the policy sends PWM / 1000 to the
            PWM-level plant under ``system``).
        system: the system spec training and evaluation run on.
        train_refs: the training references, each ≥ 3 positions.
        test_refs: the held-out references every point is measured on, each ≥ ``metrics.MIN_STEPS`` positions.
        budget: interaction steps to train for, ≥ 1 (the paper's I.S.).
        seed: the seed, an integer ≥ 0.
        folder: the output folder (checked writable; created by the method when it writes).
        eval_at: the interaction counts asked for, each in ``[1, budget]``, increasing without repeats; None: the
            method's own default (:attr:`points` for most).
        validation_refs: references every point is measured on too, right after the test references (each ≥
            ``metrics.MIN_STEPS`` positions), added to the point as ``"validation"``; empty: none.
    """

    loop: str
    system: SystemSpec
    train_refs: tuple[Reference, ...]
    test_refs: tuple[Reference, ...]
    budget: int
    seed: int
    folder: Path
    eval_at: tuple[int, ...] | None
    validation_refs: tuple[Reference, ...]

    @property
    def points(self) -> list[int]:
        """The evaluation points: ``eval_at``, or :func:`default_eval_points` of the budget when None."""
        return default_eval_points(self.budget) if self.eval_at is None else list(self.eval_at)

    @property
    def reference_sets(self) -> tuple[tuple[Reference, ...], ...]:
        """The reference sets that make the run what it is: training, test and, when there are any, validation."""
        sets = (self.train_refs, self.test_refs)
        return (*sets, self.validation_refs) if self.validation_refs else sets


def training_run(
    loop: str,
    system: SystemSpec,
    train_refs: Sequence[Reference],
    test_refs: Sequence[Reference],
    budget: int,
    seed: int,
    folder: str | Path,
    eval_at: Sequence[int] | None = None,
    validation_refs: Sequence[Reference] = (),
) -> TrainingRun:
    """The checked run every ``train_<method>`` of :mod:`efficienttrack.baselines` takes, checked before any work.

    Args:
        loop: ``"closed"`` or ``"open"``; the open loop needs a PWM-level plant under ``system``
            (``SystemSpec(plant="xe75")`` or a built-in system that has one).
        system: the system spec.
        train_refs: the training references (``.q`` (T, 4) rad, each ≥ 3 positions).
        test_refs: the held-out references every point is measured on (each ≥ ``metrics.MIN_STEPS`` positions).
        budget: interaction steps, an integer ≥ 1.
        seed: the seed, an integer ≥ 0.
        folder: the output folder (not created here).
        eval_at: interaction counts to evaluate at, each in ``[1, budget]``, or None for the method's default.
        validation_refs: references to measure every point on too (each ≥ ``metrics.MIN_STEPS`` positions); empty:
            none.

    Returns:
        The run.

    Raises:
        EfficientTrackError: naming the argument and the problem.
    """
    check_loop(loop)
    if not isinstance(budget, int | np.integer) or isinstance(budget, bool) or budget < 1:
        raise EfficientTrackError(f"budget: must be an integer ≥ 1 interaction step, got {budget!r}")
    points = None if eval_at is None else tuple(check_eval_points(eval_at, int(budget)))
    seed = check_seed(seed, "seed")
    if not isinstance(system, SystemSpec):
        raise EfficientTrackError(f"system: expected a SystemSpec (efficienttrack.systems.spec), got {type(system).__name__}")
    if loop == "open" and system.open_plant() is None:
        raise EfficientTrackError(
            f"system '{system.system_name}': the open loop needs a PWM-level plant under it; give SystemSpec(plant=...)"
        )
    train, test = check_refs(train_refs, "train_refs", 3), check_refs(test_refs, "test_refs", MIN_STEPS)
    validation = list(validation_refs)
    validation = check_refs(validation, "validation_refs", MIN_STEPS) if validation else []
    return TrainingRun(loop, system, tuple(train), tuple(test), int(budget), seed, check_output_folder(folder, "folder"),
                       points, tuple(validation))  # fmt: skip


def check_training_run(run: object) -> TrainingRun:
    """``run``, once found to be a :class:`TrainingRun` (what every ``train_<method>`` checks first).

    Args:
        run: what a ``train_<method>`` was given as its run.

    Returns:
        The run.

    Raises:
        EfficientTrackError: something else than a TrainingRun.
    """
    if not isinstance(run, TrainingRun):
        raise EfficientTrackError(
            f"run: expected a TrainingRun (efficienttrack.baselines.curve.training_run), got {type(run).__name__}"
        )
    return run
