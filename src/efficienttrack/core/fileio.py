"""Atomic file writing: nothing the user recorded or trained is left half-written by a crash.

Files get the permissions a plain ``open()`` would give them (``0o666`` less the umask, so
``-rw-r--r--`` under the usual umask 022), not the private ``0o600`` of the temporary file.

Outputs are also guarded before the work that fills them: :func:`check_output_file` and
:func:`check_output_folder` find an output that cannot be written (a file where a folder is needed or the
reverse, a read-only or full disk) before any work is done, and :func:`output_lock` keeps a second
process from writing the same folder or checkpoint at the same time.
"""

from __future__ import annotations

import contextlib
import csv
import fnmatch
import json
import math
import os
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

from efficienttrack.core.errors import EfficientTrackError

try:
    import fcntl
except ImportError:  # Windows: no flock
    fcntl = None  # type: ignore[assignment]  # the module or None, checked before each use


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
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise _naming(exc, path) from exc
    try:
        os.chmod(fd, 0o666 & ~current_umask())  # mkstemp creates 0o600; give what open() would
        with os.fdopen(fd, mode) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise _naming(exc, path) from exc
        raise
    return path


def _naming(exc: OSError, path: Path) -> OSError:
    """``exc`` naming the destination ``path`` (not a temporary file, or no file at all as from ``fsync``)."""
    return exc if exc.errno is None else type(exc)(exc.errno, exc.strerror, str(path))


def os_error_text(exc: OSError) -> str:
    """An OSError as one line naming its file, e.g. ``"/data/m.pt: No space left on device"``.

    Args:
        exc: the error (its ``filename`` when set, its ``strerror``).

    Returns:
        The message.
    """
    reason = exc.strerror or str(exc)
    if exc.filename is None:
        return reason
    other = f" → {exc.filename2}" if exc.filename2 is not None else ""
    return f"{exc.filename}{other}: {reason}"


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


def _writable_folder(folder: Path, path: Path, option: str) -> None:
    """Check that files can be written where ``folder`` (or its nearest existing ancestor) is: a probe file is written."""
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise EfficientTrackError(f"{option} {path}: {existing} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(dir=existing, prefix=".efficienttrack-probe-")
    except OSError as exc:
        raise EfficientTrackError(f"{option} {path}: cannot write in {existing} ({exc.strerror})") from exc
    try:
        os.write(fd, b"\0")  # a byte, so that a full disk refuses it
        os.fsync(fd)
    except OSError as exc:
        raise EfficientTrackError(f"{option} {path}: cannot write in {existing} ({exc.strerror})") from exc
    finally:
        os.close(fd)
        os.unlink(probe)


def check_output_file(path: str | Path, option: str = "--out") -> Path:
    """Check before any work that the file ``path`` can be written: not a folder, its parent a folder (or creatable), writable.

    A probe file is written and removed in the parent (or its nearest existing ancestor); no folder is created.

    Args:
        path: the output file.
        option: the command-line option naming it, for messages.

    Returns:
        ``path`` as a Path.

    Raises:
        EfficientTrackError: ``path`` is a folder, a parent is a file, or nothing can be written there (read-only, full).
    """
    path = Path(path)
    if path.is_dir():
        raise EfficientTrackError(f"{option} {path}: is a folder, expected a file")
    _writable_folder(path.parent, path, option)
    return path


def check_output_folder(path: str | Path, option: str = "--out") -> Path:
    """Check before any work that the folder ``path`` can be written: not a file, none of its parents a file, writable.

    A probe file is written and removed in the folder (or its nearest existing ancestor); no folder is created.

    Args:
        path: the output folder.
        option: the command-line option naming it, for messages.

    Returns:
        ``path`` as a Path.

    Raises:
        EfficientTrackError: ``path`` or a parent is a file, or nothing can be written there (read-only, full).
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise EfficientTrackError(f"{option} {path}: is a file, expected a folder")
    _writable_folder(path, path, option)
    return path


def lock_path(path: str | Path) -> Path:
    """The lock file of output file ``path`` (a checkpoint): ``.<name>.lock`` beside it, after resolving links.

    Args:
        path: the output file.

    Returns:
        The lock file's path.
    """
    path = Path(path).resolve()
    return path.parent / f".{path.name}.lock"


def _refuse_second_writer(path: Path, option: str, holder: str = "") -> EfficientTrackError:
    pid = f" (pid {holder})" if holder.isdigit() else ""
    return EfficientTrackError(
        f"{option} {path}: another efficienttrack process{pid} is writing it; wait for it to finish, or use another {option}"
    )


@contextlib.contextmanager
def output_lock(path: str | Path, option: str = "--out", folder: bool = True) -> Iterator[None]:
    """Hold an exclusive lock on output ``path``, a run folder or a checkpoint file, while the block runs.

    A folder is locked itself (``flock`` on the folder, created when missing): nothing is written for
    the lock, so its listing and its parent are left alone. A file, which is replaced whole when it is
    written, is locked through :func:`lock_path` (created holding the process id, removed on release).
    The kernel releases a lock when its process ends, however it ends, so a killed run leaves no stale
    lock. Locks hold between processes and between two holders in one process. Platforms without
    ``fcntl`` (Windows) take no lock.

    Args:
        path: the output folder or file.
        option: the command-line option naming it, for messages.
        folder: ``path`` is a folder (else a file).

    Yields:
        Nothing: the lock is held inside the block.

    Raises:
        EfficientTrackError: another process (or holder) has the lock.
    """
    path = Path(path)
    if fcntl is None:
        yield
        return
    if folder:
        path.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise _refuse_second_writer(path, option) from None
        try:
            yield
        finally:
            os.close(fd)
        return
    lock = lock_path(path)
    lock.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip()
            os.close(fd)
            raise _refuse_second_writer(path, option, holder) from None
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:  # else the holder removed the file while we opened it: take the new one
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        lock.unlink(missing_ok=True)  # while still holding it, so that no one locks the removed file
        os.close(fd)
