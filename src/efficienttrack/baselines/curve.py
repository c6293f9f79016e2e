"""What every baseline's curve shares: the evaluation points, the held-out measurement, and ``curve.json``.

A baseline trains for a budget of interaction steps and, when its count first reaches each evaluation point, runs its
deterministic policy on the held-out references (:func:`efficienttrack.envs.evaluate`) and scores it with
:func:`efficienttrack.data.metrics.compute_metrics`: the same episodes and metrics as EfficientTrack's evaluation.
:class:`CurveRecorder` keeps those points and rewrites ``curve.json`` after each, so a long run loses nothing.
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
    """The curve of one training run: measures points, writes ``curve.json``, shows progress.

    Args:
        header: what the run is (``method``, ``loop``, ``seed``, ``budget``, ``system``, ``settings``), written with
            the curve.
        path: the curve's file (``curve.json``), rewritten atomically after every point.
        system: the checked system the test references run on (for the loop in ``header["loop"]``).
        test_refs: the held-out references every point is measured on.
        progress: a display to show the interaction count and the last MAE on, or None.
        budget: the run's budget in interaction steps (the progress bar's total).
    """

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

    @property
    def wall_seconds(self) -> float:
        """The training wall time so far, evaluations excluded."""
        return time.perf_counter() - self.start - self.evaluating

    def resume(self, curve: list[dict[str, Any]], wall_seconds: float) -> None:
        """Continue a run from its saved state: the points it measured, and its wall time up to the state.

        Args:
            curve: the points measured before the state was saved (later ones are measured again).
            wall_seconds: the training wall time at the state; the wall times of new points continue from it.
        """
        self.curve = list(curve)
        self.start, self.evaluating = time.perf_counter() - wall_seconds, 0.0
        write_json(self.path, {**self.header, "curve": self.curve})
        if self.curve and self.progress is not None and self.task is not None:
            self.progress.update(self.task, completed=self.curve[-1]["interaction_steps"])

    def measure(
        self,
        act: Callable[[np.ndarray], np.ndarray],
        count: int,
        wall_seconds: float | None = None,
        extra: dict[str, Any] | None = None,
    ) -> None:
        """Run the deterministic policy ``act`` on the test references; append the point and write the file.

        Args:
            act: observations (N, 332) float32 → actions (N, 4) in [−1, 1] (:func:`efficienttrack.envs.evaluate`).
            count: the interaction steps trained so far.
            wall_seconds: the wall time the point took, for a method whose points are separate runs (open-loop
                EfficientTrack: one run per pass count); None: the recorder's time so far, evaluations excluded.
            extra: further facts of the point (e.g. ``{"passes": 2}``), added to it.
        """
        wall = self.wall_seconds if wall_seconds is None else wall_seconds
        began = time.perf_counter()
        records = evaluate(act, self.test_refs, loop=self.header["loop"], system=self.system)
        self.add(count, wall, compute_metrics(records), extra)
        self.evaluating += time.perf_counter() - began

    def add(self, count: int, wall_seconds: float, metrics: dict[str, Any], extra: dict[str, Any] | None = None) -> None:
        """Append a point measured by the caller and write the file (what :meth:`measure` does after evaluating).

        For a method whose "policy" is no function of the observation (the ILC oracle's stored corrections).

        Args:
            count: the interaction steps trained so far.
            wall_seconds: the training wall time so far (evaluations excluded).
            metrics: :func:`~efficienttrack.data.metrics.compute_metrics` of the test episodes.
            extra: further facts of the point (e.g. ``{"passes": 2}``), added to it.
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


class Run(NamedTuple):
    """The checked arguments of a training run (:func:`check_run`).

    Attributes:
        train_refs: the training references.
        test_refs: the held-out references (each ≥ ``metrics.MIN_STEPS`` steps).
        budget: interaction steps, ≥ 1.
        points: the evaluation points (:func:`~efficienttrack.baselines.curve.check_eval_points`).
        folder: the output folder (created).
    """

    train_refs: list[Reference]
    test_refs: list[Reference]
    budget: int
    points: list[int]
    folder: Path


def check_run(
    loop: str,
    system: SystemSpec,
    train_refs: Sequence[Reference],
    test_refs: Sequence[Reference],
    budget: int,
    seed: int,
    folder: str | Path,
    eval_at: Sequence[int] | None,
) -> Run:
    """Check the arguments every ``train_<method>`` of this family takes, before any work.

    Args:
        loop: ``"closed"`` or ``"open"``; the open loop needs a plant under ``system``.
        system: the system spec.
        train_refs: the training references.
        test_refs: the held-out references.
        budget: interaction steps, an integer ≥ 1.
        seed: the seed.
        folder: the output folder.
        eval_at: interaction counts to evaluate at, or None.

    Returns:
        The checked arguments.

    Raises:
        EfficientTrackError: naming the argument and the problem.
    """
    check_loop(loop)
    if not isinstance(budget, int | np.integer) or isinstance(budget, bool) or budget < 1:
        raise EfficientTrackError(f"budget: must be an integer ≥ 1 interaction step, got {budget!r}")
    points = check_eval_points(eval_at, int(budget))
    check_seed(seed, "seed")
    if not isinstance(system, SystemSpec):
        raise EfficientTrackError(f"system: expected a SystemSpec (efficienttrack.systems.spec), got {type(system).__name__}")
    if loop == "open" and system.open_plant() is None:
        raise EfficientTrackError(
            f"system '{system.system_name}': the open loop needs a PWM-level plant under it; give SystemSpec(plant=...)"
        )
    train, test = check_refs(train_refs, "train_refs", 3), check_refs(test_refs, "test_refs", MIN_STEPS)
    return Run(train, test, int(budget), points, check_output_folder(folder, "folder"))
