"""A baseline's curve measured on a study's validation references too, point by point, through its own evaluation.

A baseline (:mod:`efficienttrack.baselines`) measures each point of its curve with
:meth:`CurveRecorder.measure <efficienttrack.baselines.curve.CurveRecorder.measure>`: its deterministic agent on the
test references (:func:`efficienttrack.envs.evaluate`), scored by :func:`~efficienttrack.data.metrics.compute_metrics`.
While a study's job runs a baseline, :func:`measuring_validation` has it record with a :class:`ValidatedRecorder`,
which runs the same agent on the validation references right after, on the same system, and adds their metrics to
the point as ``"validation"``. :func:`require_validation` then checks that every point has them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from functools import partial
from types import FunctionType
from typing import Any

import numpy as np

from efficienttrack.baselines.curve import CurveRecorder
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json
from efficienttrack.data.metrics import compute_metrics
from efficienttrack.data.references import Reference
from efficienttrack.envs.evaluation import evaluate
from efficienttrack.study.jobs import Point

RECORDER = "CurveRecorder"
"""The name a baseline's module builds its recorder by (``from efficienttrack.baselines.curve import CurveRecorder``)."""


class ValidatedRecorder(CurveRecorder):
    """A :class:`~efficienttrack.baselines.curve.CurveRecorder` that measures each point on the validation references too.

    Args:
        *args: :class:`~efficienttrack.baselines.curve.CurveRecorder`'s (header, path, system, test_refs, progress,
            budget).
        validation: the study's validation references.
        **kwargs: the same, by name.
    """

    def __init__(self, *args: Any, validation: Sequence[Reference], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.validation = list(validation)

    def measure(
        self,
        act: Callable[[np.ndarray], np.ndarray],
        count: int,
        wall_seconds: float | None = None,
        extra: dict[str, Any] | None = None,
    ) -> None:
        """Measure the point on the test references, then the same agent on the validation references.

        The test references come first, so that an agent with a state (TD-MPC's planner and its generator) meets them
        as it would without validation. The validation's time is left out of the wall time, as the test's is.

        Args:
            act: observations (N, 332) float32 → actions (N, 4) in [−1, 1].
            count: the interaction steps trained so far.
            wall_seconds: as :meth:`CurveRecorder.measure <efficienttrack.baselines.curve.CurveRecorder.measure>`.
            extra: further facts of the point.
        """
        super().measure(act, count, wall_seconds, extra)
        began = time.perf_counter()
        records = evaluate(act, self.validation, loop=self.header["loop"], system=self.system)
        self.curve[-1] = {**self.curve[-1], "validation": compute_metrics(records)}
        write_json(self.path, {**self.header, "curve": self.curve})
        self.evaluating += time.perf_counter() - began


@contextmanager
def measuring_validation(train: Callable[..., Any], validation: Sequence[Reference]) -> Iterator[None]:
    """While the block runs, the recorder that the baseline ``train`` builds is a :class:`ValidatedRecorder`.

    ``train`` builds its recorder by the name :data:`RECORDER` in its own module; the name is bound to a
    :class:`ValidatedRecorder` of ``validation`` there for the block, and to the plain recorder again after it. No
    other job sees it: every executor runs one job at a time in a process.

    Args:
        train: a baseline's ``train_*`` function.
        validation: the study's validation references.

    Raises:
        EfficientTrackError: ``train``'s module builds no :data:`RECORDER` (its points could not be validated).
    """
    namespace = train.__globals__ if isinstance(train, FunctionType) else {}
    if namespace.get(RECORDER) is not CurveRecorder:
        name = getattr(train, "__qualname__", repr(train))
        raise EfficientTrackError(f"{name}: records its curve without {RECORDER}, so its points cannot be validated")
    namespace[RECORDER] = partial(ValidatedRecorder, validation=validation)
    try:
        yield
    finally:
        namespace[RECORDER] = CurveRecorder


def require_validation(curve: list[Point], method: str) -> list[Point]:
    """The curve, once every point is found measured on the validation references.

    Args:
        curve: a method's points.
        method: its name, for the error.

    Returns:
        ``curve``.

    Raises:
        EfficientTrackError: a point has no ``"validation"`` metrics (saying how many).
    """
    missing = sum("validation" not in p for p in curve)
    if missing:
        raise EfficientTrackError(
            f"{method}: {missing} of its {len(curve)} curve points were not measured on the validation references"
        )
    return curve
