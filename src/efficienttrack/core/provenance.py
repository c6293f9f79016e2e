"""Where a result came from: package, git commit and clean tree, command line, versions, device, date, wall time.

Every file that records settings or results (``config.json``, ``run.json``, ``metrics.json``, the
checkpoint configs ``model.json`` / ``policy.json``) carries a ``"provenance"`` entry built here, so any
figure can be traced to the code and the machine that made it.
"""

from __future__ import annotations

import json
import platform
import shlex
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

import efficienttrack
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import write_json

if TYPE_CHECKING:
    import torch

PACKAGE_DIR = Path(__file__).resolve().parent
"""The package's source folder: its git commit is the one recorded."""
GIT_TIMEOUT_S = 2.0
"""Longest wait for a ``git`` call before the commit is recorded as unknown."""
PROVENANCE_KEYS = (
    "version", "git_commit", "git_dirty", "command", "python", "numpy", "torch", "device", "created", "wall_seconds",
)  # fmt: skip
"""Keys of :func:`provenance`'s dict, in order."""


def _git(folder: Path, *args: str) -> str | None:
    """``git -C folder ARGS``'s output, or None without git, on failure or after :data:`GIT_TIMEOUT_S`."""
    try:
        done = subprocess.run(
            ["git", "-C", str(folder), *args], capture_output=True, text=True, timeout=GIT_TIMEOUT_S, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def git_commit(folder: str | Path | None = None) -> str | None:
    """The commit checked out where ``folder`` lies, when ``folder`` is tracked by that checkout.

    Asks ``git`` (``rev-parse HEAD``, then ``ls-files`` so that a package installed inside some other
    project's checkout, e.g. in its virtual environment, is not credited with that project's commit).

    Args:
        folder: a folder of sources; the package's own (:data:`PACKAGE_DIR`) when None.

    Returns:
        The 40-hex commit, or None outside a git checkout, without a ``git`` binary, or when git fails or hangs.
    """
    folder = Path(PACKAGE_DIR if folder is None else folder)
    if not folder.is_dir():
        return None
    commit = _git(folder, "rev-parse", "HEAD")
    if not commit or not _git(folder, "ls-files", "--", "."):
        return None
    return commit


def git_dirty(folder: str | Path | None = None) -> bool | None:
    """Whether the package's tracked sources differ from the commit :func:`git_commit` records.

    Args:
        folder: a folder of sources; the package's own (:data:`PACKAGE_DIR`) when None.

    Returns:
        True when a tracked file under ``folder`` is modified, staged or deleted; None where the commit is None.
    """
    folder = Path(PACKAGE_DIR if folder is None else folder)
    if git_commit(folder) is None:
        return None
    status = _git(folder, "status", "--porcelain", "--untracked-files=no", "--", ".")
    return None if status is None else bool(status)


def _torch_version() -> str | None:
    """The installed torch's version, or None on the core install, which leaves torch out."""
    try:
        import torch
    except ModuleNotFoundError:
        return None
    return torch.__version__


def describe_device(device: str | torch.device | None) -> str | None:
    """A device as recorded in provenance: ``"cpu"``, or ``"cuda:0 (NVIDIA H100 80GB HBM3)"`` with the GPU's name.

    Args:
        device: a torch device or its name, or None when no device was involved.

    Returns:
        The description, or None for None.
    """
    if device is None:
        return None
    import torch  # here: a device is named only by work in torch, and the core install has none

    device = torch.device(device)
    if device.type == "cuda" and torch.cuda.is_available():
        index = device.index if device.index is not None else torch.cuda.current_device()
        return f"cuda:{index} ({torch.cuda.get_device_name(index)})"
    return str(device)


def provenance(device: str | torch.device | None = None, wall_seconds: float | None = None) -> dict[str, Any]:
    """The provenance entry of a file written now.

    Args:
        device: the torch device the work ran on (None when none was involved or it is not known).
        wall_seconds: wall-clock seconds of the work that produced the file (None when not measured).

    Returns:
        ``{"version": package version, "git_commit": str | None, "git_dirty": bool | None (sources changed since
        that commit), "command": the command line (``sys.argv``), "python", "numpy", "torch": versions
        (torch None where it is not installed), "device": str | None, "created": ISO 8601 UTC time to the second,
        "wall_seconds": float | None}``.
    """
    return {
        "version": efficienttrack.__version__,
        "git_commit": git_commit(),
        "git_dirty": git_dirty(),
        "command": shlex.join(sys.argv),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "torch": _torch_version(),
        "device": describe_device(device),
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "wall_seconds": None if wall_seconds is None else round(float(wall_seconds), 2),
    }


def claim_folder(path: str | Path, identity: dict[str, Any], refusal: str) -> None:
    """Write the identity file of a folder's work, or check that the one there describes the same work.

    Resumable commands (``collect``, ``run``) keep what they are in a JSON file (``collect.json``,
    ``run.json``): a new folder gets ``identity`` plus this invocation's ``provenance``; a folder that holds
    one already must hold the same identity (its provenance is not compared), so that a rerun resumes its own
    work and never mixes in another's.

    Args:
        path: the identity file.
        identity: JSON-serializable facts the work is defined by (settings, system, references).
        refusal: the error message when the folder holds other work (the path is put in front).

    Raises:
        EfficientTrackError: the file describes other work, or is unreadable, truncated or corrupted (saying how to
            recover).
    """
    path = Path(path)
    if not path.exists():
        write_json(path, {**identity, "provenance": provenance()})
        return
    damaged = (
        "; it records what this folder's work is, so nothing is resumed without it: restore it, or start afresh "
        "(--force, or another folder)"
    )
    try:
        found = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise EfficientTrackError(f"{path}: unreadable, truncated or corrupted ({exc}){damaged}") from exc
    if not isinstance(found, dict):
        raise EfficientTrackError(f"{path}: holds a {type(found).__name__}, not a mapping of facts: corrupted{damaged}")
    found = {key: value for key, value in found.items() if key != "provenance"}
    if found != identity:
        changes = differences(found, identity)
        shown = "; ".join(changes[:MAX_SHOWN]) + (f"; and {len(changes) - MAX_SHOWN} more" if len(changes) > MAX_SHOWN else "")
        raise EfficientTrackError(f"{path}: {refusal} ({shown})")


MAX_SHOWN = 4
"""Differing fields a refusal names before it counts the rest."""
_ABSENT = object()
"""Stands for a field one side of :func:`differences` does not have."""


def differences(found: Any, expected: Any, path: str = "") -> list[str]:
    """Where two JSON values differ, as ``"config.model.history: 5 here, 10 now"``, mappings compared field by field.

    Args:
        found: the value in the folder.
        expected: the value of this invocation.
        path: the dotted path of the values (``""`` at the top).

    Returns:
        One line per differing leaf, in the order of ``expected`` (then fields only ``found`` has).
    """
    if isinstance(found, dict) and isinstance(expected, dict):
        keys = [*expected, *(key for key in found if key not in expected)]
        return [
            line
            for key in keys
            for line in differences(found.get(key, _ABSENT), expected.get(key, _ABSENT), f"{path}.{key}" if path else key)
        ]
    if found == expected:
        return []
    return [f"{path or 'the whole file'}: {_short(found)} here, {_short(expected)} now"]


def _short(value: Any) -> str:
    """A JSON value for a message, cut to 60 characters."""
    text = "absent" if value is _ABSENT else json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."
