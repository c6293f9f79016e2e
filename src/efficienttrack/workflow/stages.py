"""The resumable stages of a run: finished-stage markers, the console log, a training stage and an evaluation stage.

A run folder (``run``, and each later round of it) is built stage by stage; a stage writes its marker
``<folder>/stages/<name>.json`` last, so a rerun skips what finished and resumes what did not.
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import torch
from rich.console import Console

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, write_json
from efficienttrack.core.provenance import provenance
from efficienttrack.data.records import EpisodeRecord, find_record_files, load_named_records, load_record, save_records
from efficienttrack.data.references import Reference
from efficienttrack.deploy.runtime import track
from efficienttrack.systems.protocol import BatchedSystem

LOGS = "logs"
"""Folder of the training logs in a run folder: ``logs/model``, ``logs/policy``."""
LOG_WIDTH = 160
"""Characters per line of ``OUT/run.log`` (wide enough for the results table)."""

NetworkT = TypeVar("NetworkT", bound=torch.nn.Module)
"""The network a training stage trains, saves and loads (g_θ or π_φ)."""


class Stages:
    """Finished-stage markers in ``OUT/stages``: a stage is done when its marker exists.

    Args:
        out: the run (or round) folder.
    """

    def __init__(self, out: Path) -> None:
        self.folder = out / "stages"
        self.skipped: list[str] = []

    def done(self, name: str, keys: tuple[str, ...] = ()) -> dict[str, Any] | None:
        """The facts of finished stage ``name`` (noted as skipped), or None when it has not finished.

        Args:
            name: the stage.
            keys: facts the caller reads; a marker without them is refused like a truncated one.

        Raises:
            EfficientTrackError: the marker is unreadable, truncated or lacks ``keys``, naming the file and the fix.
        """
        path = self.folder / f"{name}.json"
        if not path.exists():
            return None
        try:
            facts = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise _broken_marker(path, name, f"unreadable ({exc})") from exc
        if not isinstance(facts, dict):
            raise _broken_marker(path, name, "not a mapping of facts")
        missing = [key for key in keys if key not in facts]
        if missing:
            raise _broken_marker(path, name, f"missing {', '.join(missing)}")
        self.skipped.append(name)
        return facts

    def finish(self, name: str, facts: dict[str, Any]) -> dict[str, Any]:
        """Mark stage ``name`` finished with its ``facts`` (JSON-serializable); returns the facts."""
        write_json(self.folder / f"{name}.json", facts)
        return facts


def _broken_marker(path: Path, name: str, problem: str) -> EfficientTrackError:
    """The error for a stage marker that cannot be used: what is wrong, and how to recover."""
    return EfficientTrackError(
        f"{path}: the marker of finished stage '{name}' is {problem}, truncated or corrupted; delete that file to redo "
        "the stage on the next run, or start afresh with --force"
    )


class RunLog:
    """What a command prints: to the console, and appended as plain text to ``OUT/run.log`` (rewritten atomically).

    Args:
        out: the run folder.
        console: where to print (a fresh rich console when None).
    """

    def __init__(self, out: Path, console: Console | None) -> None:
        self.console = console or Console()
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
    stages: Stages, name: str, out: Path, system: BatchedSystem, pi: torch.nn.Module | None, refs: Sequence[Reference], device
) -> list[EpisodeRecord]:
    """Track ``refs`` with ``pi`` (PD alone when None) as stage ``evaluate_<name>``, or read back its records when done.

    Args:
        stages: the folder's finished-stage markers.
        name: the records' folder ``<out>/records/<name>`` and the stage's name.
        out: the run (or round) folder.
        system: the closed-loop system.
        pi: the adjustment policy, or None for the PD controller alone.
        refs: the references, one episode each.
        device: where the policy runs.

    Returns:
        One record per reference, in the order of ``refs``.
    """
    if stages.done(f"evaluate_{name}") is not None:
        return load_named_records(out / "records" / name, [ref.name for ref in refs])
    records = track_and_save(name, out, system, pi, refs, device)
    stages.finish(f"evaluate_{name}", {"episodes": len(records), "fallbacks": sum(r.meta["fallbacks"] for r in records)})
    return records


def train_stage(
    stages: Stages,
    name: str,
    out: Path,
    log: RunLog,
    train: Callable[..., Any],
    save: Callable[[NetworkT, Path, str], Path],
    load: Callable[[Path], NetworkT],
    device: torch.device,
) -> tuple[NetworkT, dict[str, Any]]:
    """One resumable training stage: train (from ``OUT/checkpoints/<name>.ckpt``), save ``OUT/<name>.pt``, load it back.

    Args:
        stages: the run's finished-stage markers; a finished stage is loaded, not trained again.
        name: ``model`` or ``policy``: the checkpoint, log folder (``OUT/logs/<name>``) and stage are named after it.
        out: the run folder.
        log: where to note that the stage is done.
        train: the trainer with everything but ``checkpoint`` and ``log_dir`` bound; returns a result whose first
            field is the network and which has ``seconds`` and ``fingerprint``.
        save: writes the network to a path, with the fingerprint of what it was trained from.
        load: reads it back.
        device: where the loaded network goes.

    Returns:
        The trained network (eval mode, on ``device``) and the stage's facts (``seconds``, ``log``).
    """
    facts = stages.done(name, ("seconds", "log"))
    if facts is None:
        result = train(checkpoint=out / "checkpoints" / f"{name}.ckpt", log_dir=out / LOGS / name)
        save(result[0], out / f"{name}.pt", result.fingerprint)
        facts = stages.finish(name, {"seconds": result.seconds, "log": f"{LOGS}/{name}"})
    log.print(f"{name} trained ({facts['seconds']:.0f} s{', earlier run' if name in stages.skipped else ''})")
    return load(out / f"{name}.pt").to(device), facts
