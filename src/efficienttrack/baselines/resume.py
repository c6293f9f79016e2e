"""What the resumable baselines share: the state file, how often it is saved, and how a saved state is checked.

A baseline saves its training state (tensors and plain values, no pickle) to :data:`STATE_FILE` in its folder; the
same run started again (:func:`run_identity`) reads it back with :func:`read_state`, which refuses the state of
another run, and restores from it inside :func:`restoring`, which turns any problem with its contents into an error
that names the file.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from efficienttrack.baselines.curve import TrainingRun
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.references import Reference
from efficienttrack.learn.checkpoints import CHECKPOINT_READ_ERRORS, load_tensors

STATE_FILE = "training_state.pt"
"""A resumable baseline's training state in its output folder while it trains; removed once the run has finished."""
SAVE_EVERY_SECONDS = 300.0
"""Default wall seconds between saves of a training state: an interruption loses at most about this much training."""


def references_digest(*sets: Sequence[Reference]) -> str:
    """SHA-256 of reference sets (names and positions, in order): a saved training state is resumed only with them.

    Args:
        *sets: lists of references, e.g. the training and the test references.

    Returns:
        The hex digest.
    """
    digest = hashlib.sha256()
    for refs in sets:
        digest.update(b"set")
        for ref in refs:
            digest.update(ref.name.encode() + b"\0")
            digest.update(np.ascontiguousarray(ref.q, dtype=np.float64).tobytes())
    return digest.hexdigest()


def run_identity(header: dict[str, Any], run: TrainingRun) -> str:
    """What a run is, as saved with its state: its header (method, loop, seed, budget, system, settings), references.

    Args:
        header: the run's ``curve.json`` header.
        run: the run (its training, test and validation references: :attr:`TrainingRun.reference_sets
            <efficienttrack.baselines.curve.TrainingRun.reference_sets>`).

    Returns:
        JSON text; equal for the same run.
    """
    return json.dumps({**header, "references": references_digest(*run.reference_sets)}, sort_keys=True)


def _fix(path: Path) -> str:
    return f"delete {path} (or use another folder) to start this run afresh"


def read_state(path: Path, run: str) -> dict[str, Any]:
    """The training state saved at ``path``, when it is this run's.

    Args:
        path: the state file.
        run: what this run is (its header and references, as JSON), as saved with the state.

    Raises:
        EfficientTrackError: an unreadable file, or the state of another run; naming the file and what to do.
    """
    state = load_tensors(path)
    if state.get("run") != run:
        raise EfficientTrackError(
            f"{path}: the training state of another run (method, loop, seed, budget, system, settings or references "
            f"differ); {_fix(path)}"
        )
    return state


@contextmanager
def restoring(path: Path) -> Iterator[None]:
    """Restore from the state at ``path`` inside this block, with errors that name the file.

    A missing entry or a tensor that does not fit the run becomes an EfficientTrackError saying what to do.

    Args:
        path: the state file.
    """
    try:
        yield
    except (*CHECKPOINT_READ_ERRORS, AttributeError) as exc:
        raise EfficientTrackError(f"{path}: a damaged training state ({type(exc).__name__}: {exc}); {_fix(path)}") from exc
