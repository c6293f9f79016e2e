"""Reference trajectories: the desired joint path a machine should follow, and reading, checking and writing them.

A reference is the desired joint path q*_0 … q*_{T−1}, a (T, 4) array in rad sampled at
20 Hz (dt = 0.05 s), joints in the order boom, arm, bucket, swing. The loading-cycle generator
lives in :mod:`efficienttrack.data.cycles`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, check_file_name
from efficienttrack.core.joints import DT, JOINT_NAMES, MAX_ABS_ANGLE
from efficienttrack.core.npyfile import read_npy

MIN_STEPS = 2
"""Fewest samples a reference may have."""
MAX_STEP = 0.5
"""Largest joint change in one 50 ms step (rad, i.e. 10 rad/s); more is physically impossible."""
SUFFIXES = (".npy", ".csv")
"""File types :func:`load_references` reads."""


@dataclass(frozen=True, eq=False)
class Reference:
    """One reference trajectory.

    Attributes:
        name: identifier, the file stem when loaded (e.g. ``ref_01``).
        q: (T, 4) float64 rad, desired positions q*_0 … q*_{T−1} at 20 Hz, joints boom, arm,
            bucket, swing. Checked by :func:`check_reference` on construction.
    """

    name: str
    q: np.ndarray

    def __post_init__(self) -> None:
        """Check ``q`` and store it as a read-only float64 array."""
        q = check_reference(self.q, self.name)
        q.setflags(write=False)
        object.__setattr__(self, "q", q)

    def __len__(self) -> int:
        """Number of samples T."""
        return len(self.q)

    @property
    def t(self) -> np.ndarray:
        """(T,) s, time of each sample from 0."""
        return np.arange(len(self.q)) * DT

    @property
    def steps(self) -> int:
        """Control steps of one episode tracking it, T − 1: step t sends the target q*_{t+1}."""
        return len(self.q) - 1

    @property
    def duration(self) -> float:
        """Time from the first to the last sample, (T − 1)·dt (s)."""
        return self.steps * DT


def references_sha256(refs: Iterable[Reference]) -> str:
    """SHA-256 of references' names and positions, in order: what a resumed run or study checks it is given again.

    Args:
        refs: the references, each q (L_i, 4) rad.

    Returns:
        The hex digest.
    """
    digest = hashlib.sha256()
    for ref in refs:
        digest.update(ref.name.encode() + b"\0" + np.ascontiguousarray(ref.q).tobytes())
    return digest.hexdigest()


def check_reference(q: object, source: str) -> np.ndarray:
    """Validate a reference array and return it as float64.

    Args:
        q: candidate (T, 4) array of joint angles in rad.
        source: file or name used in error messages.

    Returns:
        (T, 4) float64 rad, a copy.

    Raises:
        EfficientTrackError: wrong shape or dtype, fewer than ``MIN_STEPS`` samples, NaN/inf,
            angles beyond ±2π (likely degrees), or a step larger than ``MAX_STEP`` rad.
    """
    arr = np.asarray(q)
    if arr.dtype.kind not in "iuf":
        raise EfficientTrackError(f"{source}: reference must be a real numeric array, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise EfficientTrackError(f"{source}: reference must have shape (T, 4) [boom, arm, bucket, swing], got {arr.shape}")
    if arr.shape[0] < MIN_STEPS:
        raise EfficientTrackError(f"{source}: reference needs at least {MIN_STEPS} samples, has {arr.shape[0]}")
    arr = np.array(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        row = int(np.flatnonzero(~np.isfinite(arr).all(axis=1))[0])
        raise EfficientTrackError(f"{source}: reference has NaN or inf (first at sample {row})")
    peak = float(np.abs(arr).max())
    if peak > MAX_ABS_ANGLE:
        raise EfficientTrackError(f"{source}: |angle| reaches {peak:.3g} > 2π; looks like degrees, references are in rad")
    steps = np.abs(wrap(np.diff(arr, axis=0)))
    if steps.size and steps.max() > MAX_STEP:
        sample, joint = np.unravel_index(int(steps.argmax()), steps.shape)
        raise EfficientTrackError(
            f"{source}: {JOINT_NAMES[joint]} jumps {steps[sample, joint]:.3g} rad between samples "
            f"{sample} and {sample + 1} (limit {MAX_STEP} rad per {DT * 1000:.0f} ms step); physically impossible"
        )
    return arr


def _read_array(path: Path) -> np.ndarray:
    """Read one reference file as a raw array; errors name the file."""
    if path.suffix == ".npy":
        return read_npy(path)
    try:
        lines = [line for line in path.read_text().splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        raise EfficientTrackError(f"{path}: cannot read as text ({exc})") from exc
    if lines:
        try:
            [float(x) for x in lines[0].split(",")]
        except ValueError:
            lines = lines[1:]  # a header row
    if not lines:
        raise EfficientTrackError(f"{path}: {'empty file' if path.stat().st_size == 0 else 'no rows'}, no reference samples")
    try:
        return np.loadtxt(lines, delimiter=",", ndmin=2, dtype=np.float64)
    except ValueError as exc:
        raise EfficientTrackError(f"{path}: expected plain numeric CSV with 4 columns ({exc})") from exc


def load_references(source: str | Path | Iterable[str | Path]) -> list[Reference]:
    """Read references from a folder or from files, checked, sorted by name.

    ``.npy`` files must hold a plain floating-point array (no pickle, at most
    :data:`~efficienttrack.core.npyfile.MAX_EXPANDED_BYTES`, see :func:`efficienttrack.core.npyfile.read_npy`); ``.csv`` files
    are plain numbers, four comma-separated columns (boom, arm, bucket, swing, rad), with an optional header row. From a
    folder, every ``*.npy`` and ``*.csv`` file directly inside it is read.

    Args:
        source: a folder, one file, or an iterable of files.

    Returns:
        References sorted by name (the file stem), each q (T, 4) rad at 20 Hz.

    Raises:
        EfficientTrackError: missing path, no reference files, unsupported suffix, two files with
            the same stem, or a file whose content fails :func:`check_reference`.
    """
    if isinstance(source, str | Path):
        root = Path(source)
        if not root.exists():
            raise EfficientTrackError(f"{root}: no such file or folder")
        paths = sorted(p for p in root.iterdir() if p.suffix in SUFFIXES) if root.is_dir() else [root]
        if not paths:
            raise EfficientTrackError(f"{root}: no reference files (*.npy, *.csv)")
    else:
        paths = [Path(p) for p in source]
        if not paths:
            raise EfficientTrackError("no reference files given")
    refs: dict[str, Reference] = {}
    for path in paths:
        if path.suffix not in SUFFIXES:
            raise EfficientTrackError(f"{path}: unsupported reference file type (use .npy or .csv)")
        if not path.is_file():
            raise EfficientTrackError(f"{path}: no such file")
        if path.stem in refs:
            raise EfficientTrackError(f"{path}: a reference named '{path.stem}' was already read from another file")
        refs[path.stem] = Reference(path.stem, check_reference(_read_array(path), str(path)))
    return [refs[name] for name in sorted(refs)]


def save_references(refs: Iterable[Reference], folder: str | Path) -> list[Path]:
    """Write each reference to ``folder/<name>.npy`` atomically (float64 (T, 4) rad, no pickle).

    Args:
        refs: references to write.
        folder: destination folder, created if missing.

    Returns:
        The paths written, in the order of ``refs``.

    Raises:
        EfficientTrackError: a name that is not a plain file name, or two references with one name.
    """
    folder = Path(folder)
    paths: list[Path] = []
    for ref in refs:
        path = folder / f"{check_file_name(ref.name, f'{folder}: reference name')}.npy"
        if path in paths:
            raise EfficientTrackError(f"two references are named '{ref.name}'")

        def write(f: IO[Any], q: np.ndarray = ref.q) -> None:
            np.save(f, q, allow_pickle=False)

        paths.append(atomic_write(path, write))
    return paths
