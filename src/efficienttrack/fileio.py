"""Atomic file writing: nothing the user recorded or trained is left half-written by a crash.

Files get the permissions a plain ``open()`` would give them (``0o666`` less the umask, so
``-rw-r--r--`` under the usual umask 022), not the private ``0o600`` of the temporary file.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any


def current_umask() -> int:
    """The process's file-creation mask, e.g. ``0o022``.

    Read from ``/proc/self/status`` (Linux ≥ 4.7) without touching it; elsewhere it is read by
    setting and restoring it (``os.umask`` has no read-only form), which a thread creating files at
    that instant could notice.

    Returns:
        The umask bits.
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o077)
    os.umask(mask)
    return mask


def atomic_write(path: str | Path, write: Callable[[IO[Any]], object], mode: str = "wb") -> Path:
    """Write a file through ``write(fileobj)`` into a temporary sibling, then rename it into place.

    The file gets mode ``0o666 & ~umask``, as with ``open()``.

    Args:
        path: destination; parent folders are created.
        write: callable that writes the content to the open file object.
        mode: ``"wb"`` or ``"w"``.

    Returns:
        The destination path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.chmod(fd, 0o666 & ~current_umask())  # mkstemp creates 0o600; give what open() would
        with os.fdopen(fd, mode) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON atomically.

    Args:
        path: destination; parent folders are created.
        data: a JSON-serializable object.

    Returns:
        The destination path.
    """
    return atomic_write(path, lambda f: json.dump(data, f, indent=2, sort_keys=False), mode="w")
