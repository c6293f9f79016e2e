"""The stages of a run: their names, the console log, an evaluation stage and a training stage.

Each stage runs through the run's :class:`~efficienttrack.workflow.ledger.Ledger`, which skips it when it finished and
notes what it took.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

import torch
from rich.console import Console

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write
from efficienttrack.core.provenance import provenance
from efficienttrack.data.records import EpisodeRecord, find_record_files, load_named_records, load_record, save_records
from efficienttrack.data.references import Reference
from efficienttrack.deploy.runtime import track
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.workflow.ledger import Ledger

COLLECT = "collect"
"""Round 1's collection (facts: ``interaction_steps``)."""
PARTS = ("model", "policy")
"""A round's training stages, in order: g_θ, then π_φ through it."""
INTERACTIONS = "interactions"
"""Round k ≥ 2's tally of the training interactions up to it (``interaction_steps``), read by ``evaluate``."""
PROBE = "time_budget"
"""The step times a time budget measured (:mod:`efficienttrack.workflow.time_budget`)."""

LOGS = "logs"
"""Folder of the training logs in a run folder: ``logs/model``, ``logs/policy``."""
LOG_WIDTH = 160
"""Characters per line of ``OUT/run.log`` (wide enough for the results table)."""


def evaluation(name: str) -> str:
    """The stage that tracks references into ``records/<name>``."""
    return f"evaluate_{name}"


def plan(part: str) -> str:
    """The stage that keeps the time budget's factor on a round's training ``part`` (one of :data:`PARTS`)."""
    return f"{PROBE}_{part}"


NetworkT = TypeVar("NetworkT", bound=torch.nn.Module)
"""The network a training stage trains, saves and loads (g_θ or π_φ)."""


class RunLog:
    """What a command prints: to the console, and appended as plain text to ``OUT/run.log`` (rewritten atomically).

    Args:
        out: the run folder.
        console: where to print (when None, a fresh rich console, :data:`LOG_WIDTH` wide when not on a terminal).
    """

    def __init__(self, out: Path, console: Console | None) -> None:
        if console is None:  # off a terminal (a script's output, a pipe), as wide as the log: no column cut to "…"
            console = Console()
            console = console if console.is_terminal or console.is_jupyter else Console(width=LOG_WIDTH)
        self.console = console
        self.path = out / "run.log"

    def header(self, command: str) -> None:
        """Start an invocation's part of the log (not shown on the console).

        Args:
            command: the command named in the header line (``run``, ``demo``, ``evaluate``).
        """
        facts = provenance()
        commit = facts["git_commit"] or "unknown"
        self._append(f"=== {facts['created']} efficienttrack {facts['version']} {command} (commit {commit}) ===")

    def print(self, renderable: Any) -> None:
        """Show ``renderable`` (a string or a rich renderable) on the console and append it to the log."""
        self.console.print(renderable)
        self._append(renderable)

    def _append(self, renderable: Any) -> None:
        text = io.StringIO()
        Console(file=text, width=LOG_WIDTH, color_system=None, highlight=False, soft_wrap=False).print(renderable)
        lines = "".join(line.rstrip() + "\n" for line in text.getvalue().splitlines())
        before = self.path.read_text() if self.path.exists() else ""
        atomic_write(self.path, lambda f: f.write(before + lines), mode="w")


def track_and_save(
    name: str, out: Path, system: BatchedSystem, pi: torch.nn.Module | None, refs: Sequence[Reference], device
) -> list[EpisodeRecord]:
    """Track ``refs`` with ``pi`` (PD alone when None) and save the records to ``OUT/records/<name>``.

    Every group of episodes is written to ``OUT/records/.<name>.partial/`` as soon as it has run, and the
    folder becomes ``OUT/records/<name>`` when every reference is done, as collection does: when the system
    fails or the run is interrupted, the finished episodes are kept and a rerun tracks only the others. A
    complete ``OUT/records/<name>`` is read back instead of tracked again.

    Args:
        name: the records' folder under ``<out>/records``.
        out: the run (or round) folder.
        system: the closed-loop system.
        pi: the adjustment policy, or None for the PD controller alone.
        refs: the references, one episode each.
        device: where the policy runs.

    Returns:
        One record per reference, in the order of ``refs``.

    Raises:
        EfficientTrackError: the system or the policy failed; the message names the episode, the error and
            where the finished episodes are kept.
    """
    folder = out / "records" / name
    names = [ref.name for ref in refs]
    if folder.is_dir():
        return load_named_records(folder, names)
    partial = folder.with_name(f".{name}.partial")
    partial.mkdir(parents=True, exist_ok=True)
    finished = {record.meta.get("name"): record for record in map(load_record, find_record_files(partial))}
    todo = [ref for ref in refs if ref.name not in finished]
    flushed: list[EpisodeRecord] = []

    def flush(records: list[EpisodeRecord]) -> None:
        save_records(records, partial)
        flushed.extend(records)

    try:
        new = track(system, pi, todo, device=device, description=f"evaluating {name}", on_done=flush)
    except EfficientTrackError as exc:
        kept = len(refs) - len(todo) + len(flushed)
        raise EfficientTrackError(
            f"{exc}; {kept} of {len(refs)} episode(s) are recorded in {partial}, rerun the same command to go on from there"
        ) from exc
    os.replace(partial, folder)
    by_name = {**finished, **{record.meta["name"]: record for record in new}}
    return [by_name[ref_name] for ref_name in names]


def evaluate_stage(
    ledger: Ledger, k: int, name: str, system: BatchedSystem, pi: torch.nn.Module | None, refs: Sequence[Reference], device
) -> list[EpisodeRecord]:
    """Round k's stage ``evaluate_<name>``: track ``refs`` with ``pi`` (PD alone when None) into ``records/<name>``.

    Args:
        ledger: the run's ledger.
        k: the round.
        name: the records' folder.
        system: the closed-loop system.
        pi: the adjustment policy, or None.
        refs: the references, one episode each.
        device: where the policy runs.

    Returns:
        One record per reference, in the order of ``refs`` (read back when the stage finished earlier).
    """
    folder = ledger.folder(k)

    def work() -> tuple[list[EpisodeRecord], dict[str, Any]]:
        records = track_and_save(name, folder, system, pi, refs, device)
        return records, {"episodes": len(records), "fallbacks": sum(r.meta["fallbacks"] for r in records)}

    load = partial(load_named_records, folder / "records" / name, [ref.name for ref in refs])
    return ledger.run(evaluation(name), work, load, k)[0]


def train_stage(
    ledger: Ledger,
    k: int,
    name: str,
    log: RunLog,
    train: Callable[..., Any],
    save: Callable[[NetworkT, Path, str], Path],
    load: Callable[[Path], NetworkT],
    device: torch.device,
) -> tuple[NetworkT, dict[str, Any]]:
    """Round k's training stage ``name`` (``model`` or ``policy``): train from ``checkpoints/<name>.ckpt``, save ``<name>.pt``.

    Args:
        ledger: the run's ledger.
        k: the round.
        name: the stage, its checkpoint, network file and log folder (``logs/<name>``).
        log: where to note that the stage is done.
        train: the trainer with everything but ``checkpoint`` and ``log_dir`` bound; returns a result whose first
            field is the network and which has ``fingerprint``.
        save: writes the network to a path, with the fingerprint of what it was trained from.
        load: reads it back.
        device: where the loaded network goes.

    Returns:
        The trained network (eval mode, on ``device``, as read back) and the stage's facts (``seconds``, ``log``, and
        ``steps``, the optimizer steps trained; absent in a folder made before it was kept).
    """
    folder = ledger.folder(k)

    def work() -> tuple[None, dict[str, Any]]:
        result = train(checkpoint=folder / "checkpoints" / f"{name}.ckpt", log_dir=folder / LOGS / name)
        save(result[0], folder / f"{name}.pt", result.fingerprint)
        return None, {"log": f"{LOGS}/{name}", "steps": result.steps}

    _, facts = ledger.run(name, work, lambda: None, k, ("seconds", "log"))
    skipped = ", earlier run" if ledger.key(name, k) in ledger.skipped else ""
    log.print(f"{name} trained ({facts['seconds']:.0f} s{skipped})")
    return load(folder / f"{name}.pt").to(device), facts
