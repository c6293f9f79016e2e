"""Episode records from anyone's tables: a CSV or Parquet log with a time column, resampled onto the 20 Hz grid.

One table becomes one :class:`~efficienttrack.data.records.EpisodeRecord`. The table holds one row per sample with a
time column and one column per channel; other columns are ignored.

Columns: a channel is ``FIELD.JOINT``, FIELD one of ``q`` (positions), ``qd`` (velocities), ``q_ref`` (the
reference sent to the position controller), ``q_des`` (the desired positions), ``u`` (PWM commands) and JOINT one of
boom, arm, bucket, swing. Each channel is read from the column ``FIELD_JOINT`` by default (``q_boom``, ``qd_arm``...,
the header of our own CSV export, so our files round-trip) and the time from ``t``. A column map renames them: a
channel to a column (``{"q.boom": "BoomAngle"}``, ``--column q.boom=BoomAngle``) or a whole field to four columns in
joint order (``{"q": ["Boom", "Arm", "Bucket", "Swing"]}``, ``--column q=Boom,Arm,Bucket,Swing``); the time column is
named on its own (``time_column``, ``--time-column``). Needed: ``q`` and one of ``q_ref``/``q_des`` (the other is
taken equal to it, as a log of the controller alone has it); ``qd`` is estimated from ``q`` when the table has none;
``u`` is optional. A field named in the map must be in the table; a field left to its default names is absent when
none of its columns is there, and refused when only some are.

Units: time in seconds, or ``time_unit`` ms/us/ns (a Parquet timestamp or duration column carries its own unit); angles
in radians, or ``angle_unit="deg"`` for degrees (``q``, ``q_ref``, ``q_des`` in °, ``qd`` in °/s); ``u`` as logged.

Empty cells: a field's samples are the rows where its four columns all hold a number; an empty (or NaN) cell leaves that
row out of that field only, so a log merged from sources logged at different rates reads as it is.

Resampling, the rosbag import's (:mod:`efficienttrack.data.rosbag`) with the same functions: the grid is
``t_k = t_0 + k·dt`` (dt = 0.05 s) over the time every field covers. Positions and logged velocities are interpolated
linearly at ``t_k`` (:func:`interpolate`; the swing through its wrap at ±π). References, desired positions and
commands are held, not interpolated (:func:`hold`): a table stamps a row's command with the time its state was read,
so ``q_ref[k]`` is the value of the last row at or before ``t_k + dt/2``, which for rows on a jittery 20 Hz clock
(jitter under dt/2) is row k itself and for a faster command log the command in force halfway through step k → k+1.
(A bag stamps a reference when it is published, after the reading, so the rosbag import holds the last one before
``t_{k+1}``.) The swing is wrapped to (−π, π].

Velocities, when the table has none: a Savitzky–Golay derivative of the resampled positions (:func:`estimate_velocity`:
``scipy.signal.savgol_filter`` with a window of 5 samples = 0.25 s, a quadratic fit, ``deriv=1``, ``mode="interp"``
at the ends; zero-phase, no delay), on the unwrapped swing. Against the XE75's sensor rates this is off by about
0.015 rad/s RMS on the boom and arm, 0.08 on the bucket and 0.007 on the swing; docs/your-logs.md has the figures.

Refused with the file and the column named: missing columns, unknown channels in the map, cells that are not numbers,
times that are not finite or do not increase, gaps between two samples of a field longer than ``max_gap``, angles
beyond ±2π rad (degrees given as radians), fields that do not overlap in time.

Parquet tables are read with pyarrow, imported when one is read (``pip install 'efficienttrack[parquet]'``).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_file_name
from efficienttrack.core.joints import DT, JOINT_NAMES, MAX_ABS_ANGLE, N_JOINTS, SWING
from efficienttrack.data.records import (
    ANGLE_FIELDS,
    CSV_COLUMNS,
    JOINT_FIELDS,
    MAX_RECORD_STEPS,
    UPSTREAM_KEYS,
    EpisodeRecord,
    parse_meta,
)

MAX_GAP = 0.25
"""Longest gap between two samples accepted by default, s (5 control periods); a longer one is a dropout that
interpolation would paper over."""
TABLE_SUFFIXES = (".csv", ".parquet")
"""File formats a table is read from."""
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
"""Units of a numeric time column → seconds."""
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
"""Units of the angles (and of ``qd`` per second) → radians."""
HELD_FIELDS = ("q_ref", "q_des", "u")
"""Commands: held between samples (:func:`hold`); ``q`` and ``qd`` are interpolated (:func:`interpolate`)."""
SAVGOL_WINDOW = 5
"""Samples of the Savitzky–Golay window that estimates velocities (0.25 s at 20 Hz)."""
SAVGOL_ORDER = 2
"""Degree of the polynomial fitted in each window."""
VELOCITY_METHOD = (
    f"Savitzky-Golay derivative of the resampled q (scipy.signal.savgol_filter, window {SAVGOL_WINDOW} samples, "
    f"order {SAVGOL_ORDER}, mode interp)"
)
"""How estimated velocities were made, as the record's meta says it."""
RESAMPLING = (
    "20 Hz grid from the first time all fields cover; q, qd interpolated linearly (swing unwrapped); q_ref, q_des, u "
    "held: the last row at or before t_k + dt/2"
)
"""How the table was put on the grid, as the record's meta says it."""
PARQUET_HINT = "install pyarrow to read Parquet tables: pip install 'efficienttrack[parquet]'"


# ----------------------------------------------------------------------------- resampling (also the rosbag import's)


def check_max_gap(max_gap: float) -> float:
    """``max_gap`` when it is a number of seconds of at least one control period.

    Args:
        max_gap: the longest gap between two samples, s.

    Returns:
        ``max_gap`` as a float.

    Raises:
        EfficientTrackError: naming ``--max-gap`` for NaN, inf or a value under :data:`DT`.
    """
    if not (math.isfinite(max_gap) and max_gap >= DT):
        raise EfficientTrackError(f"--max-gap {max_gap}: expected a number of seconds ≥ one control period ({DT})")
    return float(max_gap)


def control_grid(start: float, end: float, source: str) -> np.ndarray:
    """The 20 Hz grid ``t_k = start + k·dt`` over ``[start, end]`` (1e-9 s of slack at the end).

    Args:
        start: the first grid time, s.
        end: the last time the samples cover, s.
        source: the log, named in the error.

    Returns:
        (T,) s; empty when ``end < start``.

    Raises:
        EfficientTrackError: the grid would hold more than :data:`~efficienttrack.data.records.MAX_RECORD_STEPS` steps
            (checked before it is built).
    """
    steps = math.floor((end - start) / DT + 1e-9) + 1 if end >= start else 0
    if steps > MAX_RECORD_STEPS:
        raise EfficientTrackError(
            f"{source}: the log spans {end - start:.0f} s, {steps:,} control steps, more than one record holds "
            f"({MAX_RECORD_STEPS:,} steps, {MAX_RECORD_STEPS * DT / 3600:.1f} h at 20 Hz); split it into shorter logs"
        )
    return start + DT * np.arange(steps)


def interpolate(stamps: np.ndarray, values: np.ndarray, times: np.ndarray, unwrap_swing: bool) -> np.ndarray:
    """Linear interpolation of samples at ``times``, the swing unwrapped first when the values are angles.

    Args:
        stamps: (M,) s, increasing.
        values: (M, 4) in joint order (rad or rad/s).
        times: (T,) s within ``[stamps[0], stamps[-1]]``.
        unwrap_swing: unwrap the swing column (angles that wrap at ±π) before interpolating; the result keeps it
            unwrapped (wrap it afterwards with :func:`efficienttrack.core.angles.wrap`).

    Returns:
        (T, 4) the values at ``times``.
    """
    values = values.copy()
    if unwrap_swing:
        values[:, SWING] = np.unwrap(values[:, SWING])
    return np.stack([np.interp(times, stamps, values[:, j]) for j in range(values.shape[1])], axis=1)


def hold(stamps: np.ndarray, values: np.ndarray, times: np.ndarray, strict: bool = False) -> np.ndarray:
    """Previous-value hold: at each time the value of the last sample at (or, with ``strict``, strictly before) it.

    Args:
        stamps: (M,) s, increasing.
        values: (M, C) the samples.
        times: (T,) s, none before ``stamps[0]`` (strictly after it with ``strict``).
        strict: take the last sample strictly before each time (else at or before it).

    Returns:
        (T, C) a copy of the samples held at ``times``.
    """
    index = np.searchsorted(stamps, times, side="left" if strict else "right") - 1
    return values[index].copy()


def estimate_velocity(q: np.ndarray, window: int = SAVGOL_WINDOW, polyorder: int = SAVGOL_ORDER) -> np.ndarray:
    """Joint velocities from positions on the 20 Hz grid: a Savitzky–Golay derivative (zero-phase, no delay).

    Each window of ``window`` samples is fitted by a polynomial of degree ``polyorder`` and its slope taken at the
    window's centre (``scipy.signal.savgol_filter(..., deriv=1, delta=dt)``; the first and last ``window // 2``
    samples take the slope of the fit to the first or last window). With window 5 and degree 2 this is the
    least-squares slope over ±2 samples, ``(−2q[k−2] − q[k−1] + q[k+1] + 2q[k+2]) / (10·dt)``. Records shorter than the
    window take a central difference (one-sided at the ends, ``np.gradient``).

    Args:
        q: (T, 4) rad on the grid, the swing unwrapped (a jump of 2π would read as a huge speed).
        window: samples per window, odd, greater than ``polyorder``.
        polyorder: degree of the fitted polynomial.

    Returns:
        (T, 4) rad/s.
    """
    from scipy.signal import savgol_filter  # here, not at the top: scipy.signal costs ~0.3 s at start-up

    if len(q) < window:
        return np.gradient(q, DT, axis=0) if len(q) > 1 else np.zeros_like(q)
    return np.asarray(savgol_filter(q, window, polyorder, deriv=1, delta=DT, axis=0, mode="interp"))


# ------------------------------------------------------------------------------------------------ column map


def column_map(
    columns: Mapping[str, str | Sequence[str]] | Sequence[str] | None = None,
) -> tuple[dict[str, tuple[str, ...]], frozenset[str]]:
    """The table's column of every channel: the defaults (``q_boom``, ...) amended by the user's map.

    Args:
        columns: ``{"q.boom": "BoomAngle", "q": ["B", "A", "K", "S"], ...}``, or ``["q.boom=BoomAngle",
            "q=B,A,K,S"]`` (``--column`` on the command line: a whole field's four columns separated by commas, in
            joint order); None for the defaults alone.

    Returns:
        ``({field: (column of boom, arm, bucket, swing)} for q, qd, q_ref, q_des, u, the fields the map names)``.

    Raises:
        EfficientTrackError: an unknown channel or field, a pair without ``=``, an empty column name, or a field given
            other than four columns; the message names the key.
    """
    names = {name: [f"{name}_{joint}" for joint in JOINT_NAMES] for name in JOINT_FIELDS}
    given: set[str] = set()
    if columns is None:
        pairs: list[tuple[str, str | Sequence[str]]] = []
    elif isinstance(columns, Mapping):
        pairs = list(columns.items())
    else:
        pairs = []
        for pair in columns:
            channel, sep, text = pair.partition("=")
            if not sep:
                raise EfficientTrackError(f"--column '{pair}': expected CHANNEL=COLUMN, e.g. q.boom=BoomAngle")
            pairs.append((channel.strip(), text))
    for key, value in pairs:
        name, _, joint = key.partition(".")
        if name not in names or (joint and joint not in JOINT_NAMES):
            hint = "; name the time column with --time-column" if key in ("t", "time") else ""
            raise EfficientTrackError(
                f"--column '{key}': unknown channel; expected FIELD.JOINT or FIELD, FIELD one of {', '.join(JOINT_FIELDS)} "
                f"and JOINT one of {', '.join(JOINT_NAMES)}{hint}"
            )
        if joint:
            values = [str(value).strip()]
        else:
            values = [str(v).strip() for v in (value.split(",") if isinstance(value, str) else value)]
        if not joint and len(values) != N_JOINTS:
            raise EfficientTrackError(
                f"--column '{key}': {len(values)} column(s) given; expected {N_JOINTS}, for {', '.join(JOINT_NAMES)}"
            )
        if not all(values):
            raise EfficientTrackError(f"--column '{key}': empty column name")
        if joint:
            names[name][JOINT_NAMES.index(joint)] = values[0]
        else:
            names[name] = values
        given.add(name)
    for name in sorted(given):
        twice = next((column for column in names[name] if names[name].count(column) > 1), None)
        if twice is not None:
            joints = [JOINT_NAMES[j] for j, column in enumerate(names[name]) if column == twice]
            raise EfficientTrackError(
                f"--column: column '{twice}' is mapped to {' and '.join(f'{name}.{joint}' for joint in joints)}; each "
                f"joint of '{name}' needs its own column (map the other joint with --column {name}.JOINT=COLUMN)"
            )
    return {name: tuple(cols) for name, cols in names.items()}, frozenset(given)


def check_options(
    columns: Mapping[str, str | Sequence[str]] | Sequence[str] | None = None,
    time_unit: str = "s",
    angle_unit: str = "rad",
    max_gap: float = MAX_GAP,
) -> tuple[dict[str, tuple[str, ...]], frozenset[str]]:
    """Check :func:`read_table`'s options before any file is read (``convert`` checks them even with no table to read).

    Args:
        columns: the column map (:func:`column_map`).
        time_unit: one of :data:`TIME_UNITS`.
        angle_unit: one of :data:`ANGLE_UNITS`.
        max_gap: the longest gap between two samples, s (:func:`check_max_gap`).

    Returns:
        :func:`column_map`'s ``(columns per field, the fields the map names)``.

    Raises:
        EfficientTrackError: naming the option and the bad value.
    """
    if time_unit not in TIME_UNITS:
        raise EfficientTrackError(f"--time-unit '{time_unit}': expected one of {', '.join(TIME_UNITS)}")
    if angle_unit not in ANGLE_UNITS:
        raise EfficientTrackError(f"--angle-unit '{angle_unit}': expected one of {', '.join(ANGLE_UNITS)}")
    check_max_gap(max_gap)
    return column_map(columns)


def _channel(name: str, column: str, names: dict[str, tuple[str, ...]]) -> str:
    """``'BoomAngle' (q.boom)``: a column and its channel, for messages."""
    return f"'{column}' ({name}.{JOINT_NAMES[names[name].index(column)]})"


# ---------------------------------------------------------------------------------------------------- reading


def needs_import(path: str | Path) -> bool:
    """Whether a file is a table for :func:`read_table` rather than one of our record formats.

    Args:
        path: an input file.

    Returns:
        True for a ``.parquet`` file, and for a ``.csv`` whose header is neither the original repository's nor ours
        with every field a record needs (t, q, qd, q_ref, q_des); such CSVs are read as before by
        :func:`efficienttrack.data.records.load_record`.
    """
    path = Path(path)
    if path.suffix == ".parquet":
        return True
    if path.suffix != ".csv":
        return False
    try:
        with path.open(newline="") as f:
            line = next((line for line in f if line.strip() and not line.startswith("#")), "")
    except (OSError, UnicodeDecodeError):
        return False  # the records' reader names the problem
    header = {name.strip() for name in line.strip().split(",")}
    needed = {"t", *(f"{name}_{joint}" for name in ("q", "qd", "q_ref", "q_des") for joint in JOINT_NAMES)}
    return header != set(UPSTREAM_KEYS) and not (needed <= header <= set(CSV_COLUMNS))


def _read_csv(path: Path, wanted: list[str]) -> tuple[dict[str, np.ndarray], list[str], dict[str, Any]]:
    """The ``wanted`` columns of a CSV that are in its header, as float64 (empty cells NaN); its header; its meta line."""
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()  # -sig: a spreadsheet's byte-order mark is no name
    except (OSError, UnicodeDecodeError) as exc:
        raise EfficientTrackError(f"{path}: not a readable CSV file ({exc})") from exc
    meta: dict[str, Any] = {}
    for line in lines:
        if line.startswith("# meta:"):
            meta = parse_meta(line[len("# meta:") :], f"{path}: line '# meta:'", path.stem)
    body = [line for line in lines if line.strip() and not line.startswith("#")]
    if not body:
        raise EfficientTrackError(f"{path}: empty CSV, no header")
    rows = list(csv.reader(body))
    header = [name.strip() for name in rows[0]]
    lengths = np.array([len(row) for row in rows[1:]], dtype=np.int64)
    if np.any(lengths != len(header)):
        row = int(np.argmax(lengths != len(header)))
        raise EfficientTrackError(
            f"{path}: data row {row + 1} has {lengths[row]} values, the header names {len(header)} columns"
        )
    cells = list(zip(*rows[1:], strict=True)) if len(rows) > 1 else [() for _ in header]
    found: dict[str, np.ndarray] = {}
    for column in dict.fromkeys(wanted):
        if column not in header:
            continue
        text = np.char.strip(np.asarray(cells[header.index(column)], dtype=str))
        text[np.isin(text, ("", "nan", "NaN", "NA"))] = "nan"
        try:
            found[column] = text.astype(np.float64)
        except ValueError:
            bad = next(i for i, cell in enumerate(text) if not _is_number(cell))
            raise EfficientTrackError(
                f"{path}: column '{column}' holds '{text[bad][:40]}' at data row {bad + 1}, not a number"
            ) from None
    return found, header, meta


def _is_number(text: str) -> bool:
    """Whether ``float(text)`` works."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def _read_parquet(path: Path, wanted: list[str], time_column: str) -> tuple[dict[str, np.ndarray], list[str], float | None]:
    """The ``wanted`` columns of a Parquet table as float64 (nulls NaN), its names, a time type's scale to s or None."""
    try:
        import pyarrow as pa
        import pyarrow.compute as pc
        import pyarrow.parquet as pq
    except ImportError as exc:
        raise EfficientTrackError(f"{path}: {PARQUET_HINT} ({exc})") from exc
    try:
        header = list(pq.read_schema(path).names)
        present = [column for column in dict.fromkeys(wanted) if column in header]
        table = pq.read_table(path, columns=present)
    except (pa.ArrowException, OSError, ValueError) as exc:
        raise EfficientTrackError(f"{path}: not a readable Parquet file ({exc})") from exc
    found: dict[str, np.ndarray] = {}
    time_scale = None
    for column in present:
        data = table.column(column)
        kind = data.type
        try:
            if column == time_column and (pa.types.is_timestamp(kind) or pa.types.is_duration(kind)):
                time_scale = TIME_UNITS[kind.unit]  # int64 counts of its unit, to float64 here: pyarrow refuses > 2^53
                found[column] = np.asarray(data.cast(pa.int64()).to_numpy(zero_copy_only=False), dtype=np.float64)
            else:
                found[column] = np.asarray(pc.cast(data, pa.float64()).to_numpy(zero_copy_only=False), dtype=np.float64)
        except (pa.ArrowException, ValueError) as exc:
            raise EfficientTrackError(f"{path}: column '{column}' has type {kind}, not numbers ({exc})") from None
    return found, header, time_scale


def read_table(
    path: str | Path,
    columns: Mapping[str, str | Sequence[str]] | Sequence[str] | None = None,
    time_column: str = "t",
    time_unit: str = "s",
    angle_unit: str = "rad",
    max_gap: float = MAX_GAP,
) -> EpisodeRecord:
    """Read one CSV or Parquet table into an episode on the 20 Hz grid (module docstring: columns, resampling).

    Args:
        path: the ``.csv`` (comma-separated, one header line; lines starting with ``#`` are skipped, a ``# meta:
            {json}`` line is kept in the record's meta) or ``.parquet`` file.
        columns: the column map (:func:`column_map`); None for our CSV's names.
        time_column: the column of the sample times.
        time_unit: the time column's unit, one of ``s``, ``ms``, ``us``, ``ns``.
        angle_unit: ``rad`` or ``deg`` for the angles (and ``qd`` per second).
        max_gap: the longest gap between two samples of a field, s.

    Returns:
        The validated record: q, qd, q_ref, q_des (T, 4) rad and rad/s, u (T, 4) PWM or None, t (T,) s from the grid's
        start; ``meta["imported"]`` names the file, its columns, units, the resampling and the velocities' origin.
        Its name is the ``# meta:`` line's, else the file's stem.

    Raises:
        EfficientTrackError: naming the file, and the column and row where one is at fault.
    """
    path = Path(path)
    names, given = check_options(columns, time_unit, angle_unit, max_gap)
    if path.suffix not in TABLE_SUFFIXES:
        raise EfficientTrackError(f"{path}: unknown table format '{path.suffix}' (expected {', '.join(TABLE_SUFFIXES)})")
    if not path.is_file():
        raise EfficientTrackError(f"{path}: no such file")
    wanted = [time_column, *(column for cols in names.values() for column in cols)]
    meta: dict[str, Any] = {}
    if path.suffix == ".csv":
        found, header, meta = _read_csv(path, wanted)
        time_scale = None
    else:
        found, header, time_scale = _read_parquet(path, wanted, time_column)
    shown = ", ".join(header[:12]) + (", ..." if len(header) > 12 else "")
    if time_column not in found:
        raise EfficientTrackError(f"{path}: no time column '{time_column}' (columns: {shown}); name it with --time-column")
    fields = [name for name in JOINT_FIELDS if name in given or any(column in found for column in names[name])]
    for name in ("q", *fields):
        missing = [column for column in names[name] if column not in found]
        if missing:
            channels = ", ".join(_channel(name, column, names) for column in missing)
            raise EfficientTrackError(
                f"{path}: no column(s) {channels} (columns: {shown}); map them with --column {name}.JOINT=COLUMN"
            )
    if "q_ref" not in fields and "q_des" not in fields:
        raise EfficientTrackError(
            f"{path}: no reference: neither q_ref ({', '.join(names['q_ref'])}) nor q_des ({', '.join(names['q_des'])}) "
            "columns; map one with --column q_ref=COLUMNS"
        )
    raw_time = found[time_column]
    seconds = time_scale if time_scale is not None else TIME_UNITS[time_unit]
    time = _check_time(path, time_column, raw_time, seconds, max_gap)
    samples = {name: _field(path, name, names, found, time, max_gap, ANGLE_UNITS[angle_unit]) for name in fields}

    start = max(float(stamps[0]) for stamps, _ in samples.values())
    end = min(float(stamps[-1]) for stamps, _ in samples.values())
    grid = control_grid(start, end, str(path))
    if len(grid) < 2:
        spans = ", ".join(f"{name} {stamps[0]:.3f}…{stamps[-1]:.3f} s" for name, (stamps, _) in samples.items())
        raise EfficientTrackError(f"{path}: the fields overlap for fewer than 2 control steps of {DT} s ({spans})")
    q = interpolate(*samples["q"], grid, unwrap_swing=True)
    if "qd" in samples:
        qd = interpolate(*samples["qd"], grid, unwrap_swing=False)
        velocity = f"logged: columns {', '.join(names['qd'])}, interpolated linearly"
    else:
        qd = estimate_velocity(q)
        velocity = f"estimated: {VELOCITY_METHOD}"
    held = {name: hold(*samples[name], grid + DT / 2) for name in HELD_FIELDS if name in samples}
    q_ref = held["q_ref"] if "q_ref" in held else held["q_des"].copy()
    q_des = held["q_des"] if "q_des" in held else q_ref.copy()
    for angles in (q, q_ref, q_des):
        angles[:, SWING] = wrap(angles[:, SWING])

    name = check_file_name(meta.get("name", path.stem), f"{path}: the episode's name")
    meta = {**meta, "name": name}
    meta["imported"] = {
        "file": str(path),
        "format": path.suffix[1:],
        "rows": len(raw_time),
        "time_column": time_column,
        "time_unit": "from the Parquet type" if time_scale is not None else time_unit,
        "angle_unit": angle_unit,
        "columns": {field: list(names[field]) for field in fields},
        "copied": "q_des = q_ref" if "q_des" not in samples else "q_ref = q_des" if "q_ref" not in samples else None,
        "start_s": start,
        "resampling": RESAMPLING,
        "velocity": velocity,
        "max_gap_s": max_gap,
    }
    record = EpisodeRecord(q=q, qd=qd, q_ref=q_ref, q_des=q_des, u=held.get("u"), t=grid - start, meta=meta)
    return record.validate(f"{path} (table)")


def _check_time(path: Path, column: str, raw: np.ndarray, seconds: float, max_gap: float) -> np.ndarray:
    """(N,) s since the first row: finite, increasing, without a gap longer than ``max_gap`` (else refused)."""
    if len(raw) < 2:
        raise EfficientTrackError(f"{path}: column '{column}' has {len(raw)} row(s); at least 2 are needed")
    bad = ~np.isfinite(raw)
    if bad.any():
        row = int(np.argmax(bad)) + 1
        raise EfficientTrackError(f"{path}: column '{column}' has no time (empty, NaN or inf) at data row {row}")
    time = (raw - raw[0]) * seconds
    steps = np.diff(time)
    if np.any(steps <= 0):
        row = int(np.argmax(steps <= 0)) + 1
        raise EfficientTrackError(
            f"{path}: column '{column}' does not increase at data row {row + 1} ({raw[row - 1]:.9g}, then {raw[row]:.9g}); "
            "sort the rows by time and drop repeated ones"
        )
    _check_gaps(path, f"column '{column}'", time, max_gap)
    return time


def _check_gaps(path: Path, what: str, stamps: np.ndarray, max_gap: float) -> None:
    """Refuse a jump longer than ``max_gap`` s between two of ``stamps`` (N,) s, naming where it is."""
    steps = np.diff(stamps)
    if np.any(steps > max_gap):
        k = int(np.argmax(steps > max_gap))
        raise EfficientTrackError(
            f"{path}: {what} jumps by {steps[k]:.3f} s at {stamps[k]:.3f} s into the log (to {stamps[k + 1]:.3f} s), a gap "
            f"longer than --max-gap {max_gap} s; split the log there or allow a longer gap"
        )


def _field(
    path: Path,
    name: str,
    names: dict[str, tuple[str, ...]],
    found: dict[str, np.ndarray],
    time: np.ndarray,
    max_gap: float,
    radians: float,
) -> tuple[np.ndarray, np.ndarray]:
    """One field's samples: (M,) s and (M, 4) in rad, rad/s or PWM, from the rows where its 4 columns hold numbers."""
    values = np.column_stack([found[column] for column in names[name]])
    inf = np.isinf(values)
    if inf.any():
        row, joint = np.argwhere(inf)[0]
        column = names[name][joint]
        raise EfficientTrackError(f"{path}: column {_channel(name, column, names)} holds inf at data row {row + 1}")
    rows = np.all(np.isfinite(values), axis=1)
    if rows.sum() < 2:
        raise EfficientTrackError(
            f"{path}: field '{name}' (columns {', '.join(names[name])}) has {int(rows.sum())} row(s) with all four values; "
            "at least 2 are needed"
        )
    stamps, values = time[rows], values[rows]
    if not rows.all():
        _check_gaps(path, f"field '{name}' (columns {', '.join(names[name])}, empty cells left out)", stamps, max_gap)
    if name == "u":
        return stamps, values
    if name == "q" and radians != 1.0 and np.abs(values).max() <= MAX_ABS_ANGLE:
        raise EfficientTrackError(
            f"{path}: field 'q' (columns {', '.join(names[name])}) stays within ±{MAX_ABS_ANGLE:.2f} over the whole log, "
            f"{np.abs(values).max() * radians:.4f} rad at most as degrees: radians read as degrees? (--angle-unit deg is "
            "given; leave it out for radians)"
        )
    values = values * radians
    if name in ANGLE_FIELDS:
        peak = np.abs(values).max(axis=0)
        if np.any(peak > MAX_ABS_ANGLE):
            joint = int(np.argmax(peak > MAX_ABS_ANGLE))
            column = names[name][joint]
            raise EfficientTrackError(
                f"{path}: column {_channel(name, column, names)} reaches {peak[joint]:.4g} rad, beyond ±2π: degrees? "
                "(give --angle-unit deg; a swing past a full turn must be wrapped to ±π)"
            )
    return stamps, values
