"""Atomic file writing: nothing the user recorded or trained is left half-written by a crash.

Files get the permissions a plain ``open()`` would give them (``0o666`` less the umask, so
``-rw-r--r--`` under the usual umask 022), not the private ``0o600`` of the temporary file.
"""

from __future__ import annotations

import csv
import fnmatch
import json
import math
import os
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import IO, Any

from efficienttrack.errors import EfficientTrackError


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


MAX_NAME_BYTES = 200
"""Longest name (UTF-8 bytes) :func:`check_file_name` accepts: a suffix and :func:`atomic_write`'s temporary
``.<name>.<random>.tmp`` must still fit the usual 255-byte limit of a file name."""


def check_file_name(name: object, source: str) -> str:
    r"""Return ``name`` when it can name a file inside any folder; else raise EfficientTrackError naming ``source``.

    Names read from file contents (an episode's ``meta.name``, a reference's name) become output file names, so a
    name must not lead outside the folder it is joined to. Refused: non-strings, empty names, names starting with a
    dot (``.``, ``..``, hidden files), path separators (``/``, ``\\``), NUL and other control characters, and names
    longer than :data:`MAX_NAME_BYTES`.

    Args:
        name: the candidate name, without suffix.
        source: where the name comes from, for the message, e.g. ``"a.npz: field 'meta_json' key 'name'"``.

    Returns:
        ``name``, unchanged.
    """
    if not isinstance(name, str):
        problem = f"is a {type(name).__name__}, not a string"
    elif not name:
        problem = "is empty"
    elif "/" in name or "\\" in name:
        problem = "holds a path separator"
    elif name.startswith("."):
        problem = "starts with a dot"
    elif any(ord(char) < 0x20 or ord(char) == 0x7F for char in name):
        problem = "holds a NUL or control character"
    elif len(name.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES:
        problem = f"is longer than {MAX_NAME_BYTES} bytes"
    else:
        return name
    shown = repr(name) if len(repr(name)) <= 80 else repr(name)[:77] + "..."
    raise EfficientTrackError(f"{source} = {shown} cannot be a file name: it {problem} (names must stay inside the folder)")


def finite_json(data: Any, where: str) -> Any:
    """``data`` with every NaN/±inf float replaced by None (JSON ``null``), with a warning naming them.

    JSON has no NaN or Infinity (Python's ``json`` writes them, other readers refuse the file); a figure that is
    not finite is written as ``null`` and noted.

    Args:
        data: JSON-serializable data (dicts, lists, tuples, numbers, strings, None).
        where: the file or output, named in the warning.

    Returns:
        The data with lists for tuples and None for non-finite floats.
    """
    replaced: list[str] = []

    def clean(value: Any, key: str) -> Any:
        if isinstance(value, float) and not math.isfinite(value):
            replaced.append(key or "(top level)")
            return None
        if isinstance(value, dict):
            return {k: clean(v, f"{key}.{k}" if key else str(k)) for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [clean(v, f"{key}[{i}]") for i, v in enumerate(value)]
        return value

    cleaned = clean(data, "")
    if replaced:
        more = f" and {len(replaced) - 5} more" if len(replaced) > 5 else ""
        warnings.warn(f"{where}: not finite, written as null: {', '.join(replaced[:5])}{more}", stacklevel=2)
    return cleaned


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON atomically; NaN/inf figures become ``null`` with a warning (:func:`finite_json`).

    Args:
        path: destination; parent folders are created.
        data: a JSON-serializable object.

    Returns:
        The destination path.
    """
    cleaned = finite_json(data, str(path))
    return atomic_write(path, lambda f: json.dump(cleaned, f, indent=2, sort_keys=False, allow_nan=False), mode="w")


def write_csv(path: str | Path, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> Path:
    """Write a table as CSV atomically: the header line, then one line per row (None written as an empty cell).

    Args:
        path: destination; parent folders are created.
        header: the column names.
        rows: the rows, each with one value per column.

    Returns:
        The destination path.
    """
    lines = [list(header), *([("" if value is None else value) for value in row] for row in rows)]
    return atomic_write(path, lambda f: csv.writer(f, lineterminator="\n").writerows(lines), mode="w")


def prepare_output_folder(folder: str | Path, owned: Sequence[str], force: bool = False, option: str = "--out") -> list[Path]:
    """Make ``folder`` ready for a command's fresh output: refuse a non-empty one, or with ``force`` clear the old output.

    A command writing a folder names the entries it writes there (``owned``, glob patterns matched
    against the names directly in ``folder``). Without ``force`` any entry at all is refused, so that
    no stale file of an earlier run is mixed with the new ones. With ``force`` the entries matching
    ``owned`` are removed (a matching folder with everything in it; a symbolic link as the link
    itself, never its target) and every other entry is left alone: nothing outside ``folder`` and
    nothing the command would not have written is deleted.

    Args:
        folder: the output folder (created when missing).
        owned: glob patterns of the names the command writes, e.g. ``("*.npy",)`` or ``("records", "metrics.json")``.
        force: clear the old output instead of refusing a non-empty folder.
        option: the command-line option naming the folder, for messages.

    Returns:
        The entries removed (empty without ``force``).

    Raises:
        EfficientTrackError: ``folder`` is a file, or is not empty and ``force`` is off.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise EfficientTrackError(f"{option} {folder}: is a file, expected a folder")
    entries = sorted(folder.iterdir()) if folder.is_dir() else []
    if entries and not force:
        names = ", ".join(entry.name for entry in entries[:5]) + (", ..." if len(entries) > 5 else "")
        raise EfficientTrackError(
            f"{option} {folder}: folder is not empty ({len(entries)} entries: {names}); use another folder, "
            "or --force to replace the earlier output"
        )
    removed = [entry for entry in entries if any(fnmatch.fnmatchcase(entry.name, pattern) for pattern in owned)]
    for entry in removed:
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()
    folder.mkdir(parents=True, exist_ok=True)
    return removed
