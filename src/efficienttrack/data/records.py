"""Episode records: what one run of a machine along one reference produced, and their file formats.

Time alignment (as in the XE75 logs): at step t the controller reads ``q[t]``, ``qd[t]``,
sends ``q_ref[t]`` (the target for step t+1) and applies ``u[t]``; the machine reaches
``q[t+1]`` one step later. ``q_des[t]`` is the desired position for step t+1, so the tracking
error of step t is ``wrap(q[t+1] − q_des[t])``.

Formats read by :func:`load_records` (all validated on load):

- ``.npz`` (ours and the XE75 logs): real floating-point arrays ``q, qd, q_ref, q_des, u, t`` (+ ``meta_json``,
  a JSON object whose ``name``, when given, must be a plain file name), no pickle.
- ``.csv`` (ours): an optional ``# meta: {json}`` line, then the header ``t, q_boom … q_swing,
  qd_*, q_ref_*, q_des_*, u_*`` (``u_*`` absent when there is no PWM), one row per step.
- ``.npy`` (the original research repository): a 0-d object array holding a pickled dict
  ``js → q, jv → qd, target → q_ref, real_target → q_des, action → u, time → t``. Its pickle
  is read by an unpickler that only builds numpy arrays and refuses every other global.

Binary formats are read by :mod:`efficienttrack.core.npyfile`: no file may expand beyond
:data:`~efficienttrack.core.npyfile.MAX_EXPANDED_BYTES`, checked before anything is allocated.
- ``.csv`` (the original research repository): header ``target,real_target,js,jv,time,action``,
  vectors printed by numpy as ``"[a b c d]"``.
"""

from __future__ import annotations

import csv
import json
import warnings
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, check_file_name, finite_json
from efficienttrack.core.joints import JOINT_NAMES, MAX_ABS_ANGLE, MAX_ABS_VELOCITY
from efficienttrack.core.npyfile import MAX_EXPANDED_BYTES, read_npz, read_pickled_npy

JOINT_FIELDS = ("q", "qd", "q_ref", "q_des", "u")
ANGLE_FIELDS = ("q", "q_ref", "q_des")
JITTER_RANGE = (0.1, 2.0)
"""Time steps outside this range, in median steps, are reported as jitter (the XE75 logs stay within 0.28…1.72)."""
RECORD_SUFFIXES = (".npz", ".npy", ".csv")
"""Episode file formats, in order of preference when one folder holds the same episode twice."""

UPSTREAM_KEYS = {"js": "q", "jv": "qd", "target": "q_ref", "real_target": "q_des", "action": "u", "time": "t"}
"""Keys of the original repository's episode dict → our field names."""
CSV_COLUMNS = ("t", *(f"{name}_{joint}" for name in JOINT_FIELDS for joint in JOINT_NAMES))
MAX_RECORD_STEPS = MAX_EXPANDED_BYTES // (8 * (len(JOINT_FIELDS) * 4 + 1))
"""Most steps one record may hold: what its float64 arrays (five (T, 4) and ``t``) fit into the read cap
(:data:`~efficienttrack.core.npyfile.MAX_EXPANDED_BYTES`, 128 MiB): 798,915 steps, 11 h at 20 Hz. Importers refuse a
longer log before building it, so that nothing is written that the loaders would refuse."""
"""Header of our CSV format (the ``u_*`` columns are left out when u is None)."""


class RecordWarning(UserWarning):
    """A record is usable but odd (time not increasing, jittery sampling)."""


@dataclass
class EpisodeRecord:
    """One episode, T control steps at 20 Hz.

    Attributes:
        q: (T, 4) rad, joint positions measured at step t.
        qd: (T, 4) rad/s, joint velocities measured at step t.
        q_ref: (T, 4) rad, reference sent to the position controller at step t (target of t+1).
        q_des: (T, 4) rad, desired position for step t+1.
        u: (T, 4) PWM applied at step t, or None when the system does not expose it.
        t: (T,) s since the start of the run (informational).
        meta: JSON-serializable facts about the run (reference name, noise σ, fallbacks, ...).
    """

    q: np.ndarray
    qd: np.ndarray
    q_ref: np.ndarray
    q_des: np.ndarray
    u: np.ndarray | None
    t: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        """Number of steps T."""
        return len(self.q)

    @property
    def obs(self) -> np.ndarray:
        """(T, 8) observations [q rad, qd rad/s]."""
        return np.concatenate([self.q, self.qd], axis=1)

    def validate(self, source: str = "record") -> EpisodeRecord:
        """Check fields, shapes, finiteness and units; raise EfficientTrackError naming ``source`` and the field.

        Time is informational: a non-increasing or jittery ``t`` only gives a :class:`RecordWarning`.

        Args:
            source: what to call the record in messages (usually its file).

        Returns:
            self, with every array as float64.
        """
        for name in (*JOINT_FIELDS, "t"):
            value = getattr(self, name)
            if value is None:
                if name == "u":
                    continue
                raise EfficientTrackError(f"{source}: field '{name}' is missing")
            setattr(self, name, real_array(value, f"{source}: field '{name}'"))
        steps = len(self.q) if self.q.ndim else 0
        if steps < 2:
            raise EfficientTrackError(f"{source}: field 'q' needs at least 2 steps, has {steps}")
        for name in JOINT_FIELDS:
            arr = getattr(self, name)
            if arr is None:
                continue
            if arr.shape != (steps, 4):
                raise EfficientTrackError(
                    f"{source}: field '{name}' has shape {arr.shape}, expected ({steps}, 4) (T = {steps} steps from 'q')"
                )
            bad = ~np.isfinite(arr)
            if bad.any():
                step, joint = np.argwhere(bad)[0]
                raise EfficientTrackError(
                    f"{source}: field '{name}' has NaN/inf values (first at step {step}, joint {JOINT_NAMES[joint]})"
                )
        if self.t.shape != (steps,):
            raise EfficientTrackError(f"{source}: field 't' has shape {self.t.shape}, expected ({steps},)")
        if not np.all(np.isfinite(self.t)):
            raise EfficientTrackError(f"{source}: field 't' has NaN/inf values")
        for name in ANGLE_FIELDS:
            peak = float(np.max(np.abs(getattr(self, name))))
            if peak > MAX_ABS_ANGLE:
                raise EfficientTrackError(
                    f"{source}: field '{name}' reaches {peak:.1f}, beyond ±2π rad: angles look like degrees (use radians)"
                )
        fastest = np.abs(self.qd).max(axis=0)
        if np.any(fastest > MAX_ABS_VELOCITY):
            joint = int(np.argmax(fastest))
            raise EfficientTrackError(
                f"{source}: field 'qd' reaches {fastest[joint]:.3g} rad/s at the {JOINT_NAMES[joint]}, beyond the "
                f"±{MAX_ABS_VELOCITY:g} rad/s of any excavator joint: a corrupted file, or not rad/s?"
            )
        _check_time(self.t, source)
        return self

    def save(self, path: str | Path) -> Path:
        """Write the record to ``path`` (.npz, no pickle) atomically; return the path."""
        path = Path(path)
        arrays = {name: getattr(self, name) for name in (*JOINT_FIELDS, "t") if getattr(self, name) is not None}
        arrays["meta_json"] = np.array(json.dumps(finite_json(self.meta, f"{path}: meta"), allow_nan=False))
        atomic_write(path, lambda f: np.savez(f, **arrays))
        return path

    @classmethod
    def load(cls, path: str | Path) -> EpisodeRecord:
        """Read and validate a record saved by :meth:`save` or one of the XE75 ``.npz`` logs.

        Args:
            path: the ``.npz`` file (read with ``allow_pickle=False``).
        """
        path = Path(path)
        arrays = read_npz(path, kinds={"meta_json": "U"})
        missing = [name for name in ("q", "qd", "q_ref", "q_des", "t") if name not in arrays]
        if missing:
            raise EfficientTrackError(f"{path}: missing field(s) {', '.join(repr(name) for name in missing)}")
        meta_json = arrays.get("meta_json", np.array("{}"))
        if meta_json.shape != ():
            raise EfficientTrackError(f"{path}: field 'meta_json' has shape {meta_json.shape}, expected one string")
        meta = parse_meta(str(meta_json), f"{path}: field 'meta_json'", path.stem)
        record = cls(
            q=arrays["q"],
            qd=arrays["qd"],
            q_ref=arrays["q_ref"],
            q_des=arrays["q_des"],
            u=arrays.get("u"),
            t=arrays["t"],
            meta=meta,
        )
        return record.validate(str(path))


def real_array(value: object, source: str) -> np.ndarray:
    """``value`` as a float64 array when it holds real numbers; bool, complex, strings and objects are refused.

    Args:
        value: an array or nested sequence of numbers.
        source: file and field, for messages.

    Returns:
        A float64 array (``value`` itself when it already is one).
    """
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise EfficientTrackError(f"{source} is not a numeric array ({exc})") from exc
    if arr.dtype.kind not in "fiu":
        raise EfficientTrackError(f"{source} has dtype {arr.dtype}, expected real numbers")
    return arr.astype(np.float64, copy=False)


def parse_meta(text: str, source: str, default_name: str) -> dict[str, Any]:
    """A record's meta from its JSON text: an object whose ``name``, when given, is a plain file name.

    The name becomes a file name when the record is saved (``convert``), so one that could lead outside a folder
    is refused here, naming the file it was read from (:func:`efficienttrack.core.fileio.check_file_name`).

    Args:
        text: the JSON text.
        source: file and field, for messages.
        default_name: the name when the meta gives none (the file's stem).

    Returns:
        The meta dict, with ``name`` set.
    """
    try:
        meta = json.loads(text)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, an integer of over 4,300 digits, nested too deeply
        raise EfficientTrackError(f"{source} is not valid JSON ({type(exc).__name__}: {exc})") from exc
    if not isinstance(meta, dict):
        raise EfficientTrackError(f"{source} holds a JSON {type(meta).__name__}, expected an object")
    if "name" in meta:
        check_file_name(meta["name"], f"{source} key 'name'")
    else:
        meta["name"] = default_name
    return meta


def _check_time(t: np.ndarray, source: str) -> None:
    """Warn (never fail) when the timestamps ``t`` (T,) s are not increasing or the sampling is jittery."""
    dt = np.diff(t)
    if np.any(dt <= 0):
        warnings.warn(
            f"{source}: timestamps are not increasing at {int(np.sum(dt <= 0))} step(s) (time is informational only)",
            RecordWarning,
            stacklevel=3,
        )
        return
    median = float(np.median(dt))
    odd = (dt < JITTER_RANGE[0] * median) | (dt > JITTER_RANGE[1] * median)
    if odd.any():
        warnings.warn(
            f"{source}: jittery sampling, {int(odd.sum())} step(s) far from the median dt {median:.4f} s "
            f"(longest {dt.max():.4f} s, shortest {dt.min():.4f} s)",
            RecordWarning,
            stacklevel=3,
        )


# ---------------------------------------------------------------------------------------------- CSV (ours)


def save_csv(record: EpisodeRecord, path: str | Path) -> Path:
    """Write ``record`` as our CSV (one row per step, full float64 precision) atomically.

    Args:
        record: the episode; its ``meta`` goes to a leading ``# meta: {json}`` line.
        path: destination ``.csv``.

    Returns:
        The path written.
    """
    names = [name for name in JOINT_FIELDS if getattr(record, name) is not None]
    columns = ["t", *(f"{name}_{joint}" for name in names for joint in JOINT_NAMES)]
    table = np.column_stack([record.t, *(getattr(record, name) for name in names)])

    def write(f: IO[str]) -> None:
        f.write(f"# meta: {json.dumps(record.meta)}\n")
        f.write(",".join(columns) + "\n")
        np.savetxt(f, table, delimiter=",", fmt="%.17g")

    return atomic_write(path, write, mode="w")


def _load_csv_ours(path: Path, lines: list[str]) -> EpisodeRecord:
    """Parse our CSV from its ``lines`` (comment lines included); see :func:`save_csv`."""
    meta: dict[str, Any] = {}
    body = [line for line in lines if not line.startswith("#")]
    for line in lines:
        if line.startswith("# meta:"):
            meta = parse_meta(line[len("# meta:") :], f"{path}: field 'meta'", path.stem)
    header = [name.strip() for name in body[0].split(",")]
    unknown = [name for name in header if name not in CSV_COLUMNS]
    if unknown:
        raise EfficientTrackError(f"{path}: unknown column(s) {', '.join(unknown)}; expected {', '.join(CSV_COLUMNS)}")
    try:
        table = np.loadtxt(body[1:], delimiter=",", ndmin=2, dtype=np.float64)
    except ValueError as exc:
        raise EfficientTrackError(f"{path}: not a numeric table ({exc})") from exc
    if table.shape[1] != len(header):
        raise EfficientTrackError(f"{path}: rows have {table.shape[1]} values, the header names {len(header)} columns")
    column = {name: table[:, i] for i, name in enumerate(header)}
    fields: dict[str, np.ndarray | None] = {"t": column.get("t")}
    for name in JOINT_FIELDS:
        present = [f"{name}_{joint}" in column for joint in JOINT_NAMES]
        if any(present) and not all(present):
            missing = [f"{name}_{joint}" for joint, ok in zip(JOINT_NAMES, present, strict=True) if not ok]
            raise EfficientTrackError(f"{path}: field '{name}' lacks column(s) {', '.join(missing)}")
        fields[name] = np.column_stack([column[f"{name}_{joint}"] for joint in JOINT_NAMES]) if all(present) else None
    meta.setdefault("name", path.stem)
    return EpisodeRecord(meta=meta, **fields).validate(str(path))  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ original repository formats


UPSTREAM_NPY = (
    "an upstream episode (a 0-d object array with a dict of js, jv, target, real_target, action, time); "
    "a reference trajectory?"
)
"""What an upstream episode ``.npy`` holds, for the message when a file holds something else."""


def _upstream_fields(path: Path, columns: dict[str, Any]) -> EpisodeRecord:
    """Map the upstream keys of ``columns`` to an EpisodeRecord and validate it."""
    missing = [key for key in UPSTREAM_KEYS if key not in columns]
    if missing:
        raise EfficientTrackError(
            f"{path}: missing field(s) {', '.join(repr(key) for key in missing)} (upstream keys {', '.join(UPSTREAM_KEYS)})"
        )
    fields: dict[str, np.ndarray] = {}
    for key, name in UPSTREAM_KEYS.items():
        fields[name] = real_array(columns[key], f"{path}: field '{key}' ({name})")
    return EpisodeRecord(meta={"name": path.stem, "format": "upstream"}, **fields).validate(f"{path}")


def load_upstream_npy(path: str | Path) -> EpisodeRecord:
    """Read an episode ``.npy`` of the original research repository (restricted unpickling, never ``np.load``).

    Args:
        path: the ``.npy`` file (0-d object array holding a dict of per-step lists).

    Returns:
        The validated record (q, qd, q_ref, q_des, u: (T, 4); t: (T,) s).

    Raises:
        EfficientTrackError: unreadable file, a global other than numpy's array reconstruction in the
            pickle, missing keys or invalid values.
    """
    path = Path(path)
    episode = read_pickled_npy(path, UPSTREAM_NPY)
    if not isinstance(episode, dict):
        raise EfficientTrackError(f"{path}: the pickled object is a {type(episode).__name__}, not an episode dict")
    return _upstream_fields(path, episode)


def _load_upstream_csv(path: Path, lines: list[str]) -> EpisodeRecord:
    """Parse the original repository's CSV ``lines`` (vectors printed as ``"[a b c d]"``)."""
    try:
        rows = list(csv.reader(lines))
    except csv.Error as exc:  # a stray quote makes the rest of the file one field, beyond csv's field size limit
        raise EfficientTrackError(f"{path}: not a readable CSV ({exc})") from exc
    header, rows = rows[0], rows[1:]
    if any(len(row) != len(header) for row in rows):
        raise EfficientTrackError(f"{path}: rows do not all have the {len(header)} columns of the header")
    columns: dict[str, Any] = {}
    for i, key in enumerate(header):
        text = " ".join(row[i] for row in rows).replace("[", " ").replace("]", " ")
        try:
            values = np.array(text.split(), dtype=np.float64)
        except ValueError as exc:
            raise EfficientTrackError(f"{path}: field '{key}' holds non-numeric text ({exc})") from exc
        if key == "time":
            columns[key] = values
        elif values.size != 4 * len(rows):
            raise EfficientTrackError(f"{path}: field '{key}' does not hold 4 values per row")
        else:
            columns[key] = values.reshape(len(rows), 4)
    return _upstream_fields(path, columns)


def load_csv(path: str | Path) -> EpisodeRecord:
    """Read an episode CSV, ours (:func:`save_csv`) or the original repository's, told apart by the header.

    Args:
        path: the ``.csv`` file.

    Returns:
        The validated record.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise EfficientTrackError(f"{path}: not a readable CSV file ({exc})") from exc
    body = [line for line in lines if line.strip() and not line.startswith("#")]
    if not body:
        raise EfficientTrackError(f"{path}: empty CSV, no header")
    kind = csv_kind(body[0])
    if kind == "upstream":
        return _load_upstream_csv(path, body)
    if kind == "ours":
        return _load_csv_ours(path, [line for line in lines if line.strip()])
    raise EfficientTrackError(
        f"{path}: unknown CSV header '{body[0][:80]}'; expected ours (t, q_boom, ...) or the upstream "
        f"'{','.join(UPSTREAM_KEYS)}'"
    )


# ------------------------------------------------------------------------------------------- many records


def load_record(path: str | Path) -> EpisodeRecord:
    """Read one episode file, its format told by the suffix (``.npz``, ``.npy`` upstream, ``.csv`` either).

    Args:
        path: the episode file.

    Returns:
        The validated record; ``meta["name"]`` is the file's stem unless the file says otherwise.
    """
    path = Path(path)
    if not path.is_file():
        raise EfficientTrackError(f"{path}: no such file")
    if path.suffix == ".npz":
        return EpisodeRecord.load(path)
    if path.suffix == ".npy":
        return load_upstream_npy(path)
    if path.suffix == ".csv":
        return load_csv(path)
    raise EfficientTrackError(f"{path}: unknown episode format '{path.suffix}' (expected {', '.join(RECORD_SUFFIXES)})")


def find_record_files(folder: Path, recursive: bool = False) -> list[Path]:
    """Episode files in ``folder`` (sorted); one file per (folder, stem), the best format first.

    The same episode in several formats side by side (e.g. upstream ``.npy`` and ``.csv``) is
    read once, from the first of :data:`RECORD_SUFFIXES` present.

    Args:
        folder: the folder to search.
        recursive: also search its subfolders, at any depth (else only the files directly in it).

    Returns:
        Sorted paths.
    """
    chosen: dict[tuple[Path, str], Path] = {}
    candidates = folder.rglob("*") if recursive else folder.iterdir()
    for path in sorted(p for p in candidates if p.suffix in RECORD_SUFFIXES and p.is_file()):
        key = (path.parent, path.stem)
        if key not in chosen or RECORD_SUFFIXES.index(path.suffix) < RECORD_SUFFIXES.index(chosen[key].suffix):
            chosen[key] = path
    return sorted(chosen.values())


def csv_kind(header: str) -> str | None:
    """Which episode CSV a header line starts: ``"ours"``, ``"upstream"`` (the research repository's), or None.

    Args:
        header: the first line that is not a comment.
    """
    names = {name.strip() for name in header.split(",")}
    if names == set(UPSTREAM_KEYS):
        return "upstream"
    return "ours" if {"t", "q_boom"} <= names else None


HEAD_BYTES = 4096
"""What :func:`looks_like_episode` reads of a file: enough for a ``.npy`` header or a CSV header line."""


def looks_like_episode(path: Path) -> bool:
    """Whether a file, by its first bytes, is an episode rather than another ``.npy``/``.csv`` in a run folder.

    A ``.npz`` is; a ``.npy`` is when it holds a pickled object (the research repository's episodes; a reference is a
    float array); a ``.csv`` when its header is ours (``t``, ``q_boom``, …) or the repository's. Used to count the
    episodes of subfolders in a hint, never to refuse a file that is loaded.

    Args:
        path: a file with one of :data:`RECORD_SUFFIXES`.
    """
    if path.suffix == ".npz":
        return True
    try:
        with open(path, "rb") as f:
            head = f.read(HEAD_BYTES)
    except OSError:
        return False
    if path.suffix == ".npy":
        return b"'descr': '|O'" in head
    lines = [line for line in head.decode("utf-8", "replace").splitlines() if line.strip() and not line.startswith("#")]
    return bool(lines) and csv_kind(lines[0]) is not None


def record_files(path: str | Path, recursive: bool = False) -> list[Path]:
    """The episode files ``path`` stands for: itself when a file, else the folder's (:func:`find_record_files`).

    Args:
        path: an episode file or a folder.
        recursive: for a folder, search its subfolders too.

    Returns:
        Sorted paths, at least one.

    Raises:
        EfficientTrackError: no such path, or a folder without episode files; when only its subfolders hold
            some, the message names them and says how to include them.
    """
    path = Path(path)
    if not path.is_dir():
        if not path.exists():
            raise EfficientTrackError(f"{path}: no such file or folder")
        return [path]
    files = find_record_files(path, recursive)
    if files:
        return files
    nested = [] if recursive else [file for file in find_record_files(path, recursive=True) if looks_like_episode(file)]
    if nested:
        subfolders = sorted({str(file.parent.relative_to(path)) for file in nested})
        shown = ", ".join(f"{name}/" for name in subfolders[:3]) + (", ..." if len(subfolders) > 3 else "")
        raise EfficientTrackError(
            f"{path}: no episode files directly in this folder, but {len(nested)} in {len(subfolders)} subfolder(s) "
            f"({shown}); include subfolders with --recursive (recursive=True), or name the subfolders"
        )
    raise EfficientTrackError(f"{path}: folder holds no episode files ({', '.join(RECORD_SUFFIXES)})")


def load_records(paths: str | Path | Iterable[str | Path], recursive: bool = False) -> list[EpisodeRecord]:
    """Read every episode in ``paths``: files, or the episode files of folders (see :func:`record_files`).

    Args:
        paths: one path or several; files are read whatever their stem, folders in sorted order.
        recursive: read the subfolders of folders too (else a folder means the episodes directly in it).

    Returns:
        The validated records, in the order of ``paths`` (folders sorted).

    Raises:
        EfficientTrackError: a path does not exist, a folder holds no episode (naming subfolders that do
            when ``recursive`` is off), or a file is invalid.
    """
    if isinstance(paths, str | Path):
        paths = [paths]
    records = [load_record(file) for path in paths for file in record_files(path, recursive)]
    if not records:
        raise EfficientTrackError("no episode files given")
    return records


def load_named_records(folder: str | Path, names: Sequence[str]) -> list[EpisodeRecord]:
    """The episodes of ``folder`` named ``names``, in that order (resuming runs read their outputs back this way).

    Args:
        folder: a folder of records written by :func:`save_records`.
        names: the episode names (``meta["name"]``) expected there.

    Returns:
        One record per name.

    Raises:
        EfficientTrackError: an expected episode is not in the folder.
    """
    by_name = {record.meta["name"]: record for record in load_records(folder)}
    missing = [name for name in names if name not in by_name]
    if missing:
        raise EfficientTrackError(
            f"{folder}: episode(s) {', '.join(missing[:5])} missing from a finished stage; delete the folder to redo it"
        )
    return [by_name[name] for name in names]


def save_records(records: Sequence[EpisodeRecord], folder: str | Path, fmt: str = "npz") -> list[Path]:
    """Write each record to ``folder/<meta name>.<fmt>`` atomically.

    A name that could lead outside ``folder`` (path separators, a leading dot, NUL...) is refused before anything is
    written (:func:`efficienttrack.core.fileio.check_file_name`).

    Args:
        records: the episodes; unnamed ones are called ``episode_0000``, ``episode_0001``, ...
        folder: destination folder (created).
        fmt: ``"npz"`` or ``"csv"`` (our formats).

    Returns:
        The paths written, in the order of ``records``.

    Raises:
        EfficientTrackError: an unknown format, a name that is not a plain file name, or two records with one name.
    """
    if fmt not in ("npz", "csv"):
        raise EfficientTrackError(f"--format '{fmt}': expected npz or csv")
    folder = Path(folder)
    names = [
        check_file_name(record.meta.get("name") or f"episode_{i:04d}", f"{folder}: record {i} meta 'name'")
        for i, record in enumerate(records)
    ]
    duplicates = sorted(name for name, count in Counter(names).items() if count > 1)
    if duplicates:
        raise EfficientTrackError(f"{folder}: several records are named {', '.join(duplicates[:5])}; names must be unique")
    writer = EpisodeRecord.save if fmt == "npz" else save_csv
    return [writer(record, folder / f"{name}.{fmt}") for record, name in zip(records, names, strict=True)]
