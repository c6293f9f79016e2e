"""Tables with a time column → episode records on the 20 Hz grid (efficienttrack.data.tabular and ``convert``)."""

import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.angles import wrap
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.joints import DT, JOINT_NAMES
from efficienttrack.data.records import EpisodeRecord, load_record, load_records, save_csv
from efficienttrack.data.tabular import column_map, estimate_velocity, needs_import, read_table

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
PD_CLEAN = DATA / "xe75" / "pd_clean_train"
OURS = [f"{name}_{joint}" for name in ("q", "qd", "q_ref", "q_des", "u") for joint in JOINT_NAMES]

W = 2 * math.pi * np.array([0.3, 0.2, 0.4, 0.25])
"""Angular frequencies of the test positions, rad/s."""
A = np.array([0.4, 0.5, 0.6, 0.8])
"""Their amplitudes, rad; the swing is centred on 3.0 rad, so it crosses +π and is logged wrapped."""
LINEAR_ERROR = A * W**2 * 0.09**2 / 8
"""Bound of linear interpolation's error between samples ≤ 0.09 s apart, max|q''|·h²/8, rad per joint (≤ 3.8e-3)."""
CENTRE = np.array([0.0, -0.3, 0.8, 3.0])


def positions(t):
    """(N, 4) rad: the known smooth function, the swing wrapped as a driver logs it."""
    q = CENTRE + A * np.sin(W * np.asarray(t)[:, None])
    q[:, 3] = wrap(q[:, 3])
    return q


def velocities(t):
    return A * W * np.cos(W * np.asarray(t)[:, None])


def write_csv(path, header, table, comment=None):
    """A comma-separated table (float64 printed in full; NaN cells written empty)."""
    lines = [comment] if comment else []
    lines.append(",".join(header))
    for row in np.asarray(table, dtype=float):
        lines.append(",".join("" if np.isnan(v) else repr(float(v)) for v in row))
    path.write_text("\n".join(lines) + "\n")
    return path


def irregular_times(n=300, seed=0, low=0.01, high=0.09):
    """(n,) s from 0, steps drawn uniformly in [low, high] s (mean 20 Hz)."""
    return np.concatenate([[0.0], np.cumsum(np.random.default_rng(seed).uniform(low, high, n - 1))])


def table_of(t, q, q_ref, u=None, qd=None, extra=()):
    """Columns t, q_*, [qd_*], q_ref_*, [u_*] in our CSV's names."""
    header = ["t", *OURS[0:4], *(OURS[4:8] if qd is not None else []), *OURS[8:12], *(OURS[16:20] if u is not None else [])]
    parts = [t[:, None], q, *([qd] if qd is not None else []), q_ref, *([u] if u is not None else [])]
    return header, np.hstack(parts)


# ------------------------------------------------------------------------------------------ known answers


def test_irregular_samples_of_a_known_function_land_on_the_grid_within_the_interpolation_error(tmp_path):
    t = irregular_times()
    q = positions(t)
    header, table = table_of(t, q, q_ref=q + 0.01)
    record = read_table(write_csv(tmp_path / "irregular.csv", header, table))
    grid = np.arange(len(record)) * DT
    np.testing.assert_allclose(record.t, grid, rtol=0, atol=1e-12)
    assert record.t[-1] <= t[-1] < record.t[-1] + DT  # the grid covers the table
    assert np.all(np.abs(wrap(record.q - positions(grid))).max(axis=0) <= LINEAR_ERROR)
    assert np.abs(record.q[:, 3]).max() <= math.pi and record.q[:, 3].min() < -3.0  # the swing crossed +π, wrapped
    # velocities estimated (the table has none): interpolation error and the estimator's own, 4 % of the peak speed
    assert np.all(np.abs(record.qd - velocities(grid)).max(axis=0) < 0.04 * A * W)
    assert record.u is None
    np.testing.assert_array_equal(record.q_des, record.q_ref)
    imported = record.meta["imported"]
    assert imported["file"] == str(tmp_path / "irregular.csv") and imported["velocity"].startswith("estimated: Savitzky")
    assert "held" in imported["resampling"] and imported["copied"] == "q_des = q_ref"
    assert record.meta["name"] == "irregular"


def test_commands_are_held_row_by_row_on_a_jittery_20_hz_clock_and_mid_step_from_a_faster_log(tmp_path):
    steps = 60
    jitter = np.random.default_rng(1).uniform(-0.02, 0.02, steps)
    jitter[0] = 0.0
    t = DT * np.arange(steps) + jitter  # the XE75's logs: jitter well under dt/2
    command = 0.01 * np.arange(steps)[:, None] + 0.1 * np.arange(4)
    header, table = table_of(t, positions(t), q_ref=command, u=100 * command)
    record = read_table(write_csv(tmp_path / "jittery.csv", header, table))
    n = len(record)
    np.testing.assert_allclose(record.q_ref, command[:n], rtol=0, atol=1e-12)  # row k's, whatever the jitter (wrapped)
    np.testing.assert_array_equal(record.u, 100 * command[:n])

    fast = 0.01 * np.arange(301)  # commands at 100 Hz, a new value every row
    header, table = table_of(fast, positions(fast), q_ref=fast[:, None] + np.zeros(4))
    record = read_table(write_csv(tmp_path / "fast.csv", header, table))
    expected = np.minimum(0.01 * np.floor((record.t + DT / 2) / 0.01 + 1e-9), fast[-1])  # in force halfway through the step
    np.testing.assert_allclose(record.q_ref[:, 0], expected, rtol=0, atol=1e-12)


def test_empty_cells_leave_a_row_out_of_one_field_only(tmp_path):
    t = 0.01 * np.arange(201)
    header, table = table_of(t, positions(t), q_ref=np.tile(t[:, None], 4))
    table[np.arange(201) % 5 != 0, 5:9] = np.nan  # the reference logged at 20 Hz, the states at 100 Hz
    record = read_table(write_csv(tmp_path / "merged.csv", header, table))
    assert np.abs(wrap(record.q - positions(record.t))).max() < 1e-3
    np.testing.assert_allclose(record.q_ref[:, 0], record.t, rtol=0, atol=1e-12)  # the 20 Hz rows, held


def test_velocity_estimate_of_a_polynomial_is_exact_and_of_a_sine_within_its_stated_error():
    t = DT * np.arange(100)
    quadratic = 0.3 - 0.2 * t[:, None] + 0.05 * np.arange(1, 5) * t[:, None] ** 2
    np.testing.assert_allclose(estimate_velocity(quadratic), -0.2 + 0.1 * np.arange(1, 5) * t[:, None], atol=1e-10)
    # a 0.5 Hz sine: the 5-sample window's gain at ω·dt = 0.157 rad is (sin x + 2 sin 2x)/(5x) = 0.986 inside,
    # the end windows' quadratic fits reach 3.4 % of the peak speed
    w = 2 * math.pi * 0.5
    error = estimate_velocity(np.tile(np.sin(w * t)[:, None], 4)) - w * np.cos(w * t)[:, None]
    assert np.abs(error[2:-2]).max() < 0.015 * w and np.abs(error).max() < 0.035 * w
    assert estimate_velocity(np.array([[0.0] * 4, [0.1] * 4])) == pytest.approx(np.full((2, 4), 2.0))  # shorter than 5


def test_units_and_a_column_map(tmp_path):
    t = irregular_times(200, seed=2)
    q = positions(t)
    header = ["Stamp", "Boom", "Arm", "Bucket", "Swing", "Target1", "Target2", "Target3", "Target4", "BoomRate"]
    table = np.hstack([1.7e12 + 1000 * t[:, None], np.degrees(q), np.degrees(q + 0.02), np.degrees(velocities(t)[:, :1])])
    path = write_csv(tmp_path / "theirs.csv", header, table)
    columns = {"q": ["Boom", "Arm", "Bucket", "Swing"], "q_des": "Target1,Target2,Target3,Target4"}
    path.write_text("\ufeff" + path.read_text())  # a spreadsheet's byte-order mark before the first name
    record = read_table(path, columns, time_column="Stamp", time_unit="ms", angle_unit="deg")
    assert np.all(np.abs(wrap(record.q - positions(record.t))).max(axis=0) <= LINEAR_ERROR)
    imported = record.meta["imported"]
    assert imported["columns"]["q"] == ["Boom", "Arm", "Bucket", "Swing"] and imported["copied"] == "q_ref = q_des"
    assert imported["time_unit"] == "ms" and imported["angle_unit"] == "deg"
    with pytest.raises(EfficientTrackError, match=r"theirs.csv: no column\(s\) 'qd_arm' \(qd.arm\), 'qd_bucket'"):
        read_table(path, {**columns, "qd.boom": "BoomRate"}, time_column="Stamp", time_unit="ms", angle_unit="deg")
    with pytest.raises(EfficientTrackError, match=r"theirs.csv: column 'Boom' \(q.boom\) reaches .* degrees\?"):
        read_table(path, columns, time_column="Stamp", time_unit="ms")
    radians = write_csv(tmp_path / "rad.csv", header, np.hstack([table[:, :1], np.radians(table[:, 1:])]))
    with pytest.raises(EfficientTrackError, match=r"rad.csv: field 'q' .* stays within ±6.28 .* radians read as degrees\?"):
        read_table(radians, columns, time_column="Stamp", time_unit="ms", angle_unit="deg")


# --------------------------------------------------------------------------------------------- refusals


def one_line(info) -> str:
    message = str(info.value)
    assert "\n" not in message, message
    return message


def test_a_gap_beyond_max_gap_is_refused_naming_the_file_and_the_time(tmp_path):
    t = np.concatenate([DT * np.arange(21), 1.4 + DT * np.arange(20)])  # 0.4 s without a sample after 1.0 s
    header, table = table_of(t, positions(t), q_ref=positions(t))
    path = write_csv(tmp_path / "dropout.csv", header, table)
    with pytest.raises(EfficientTrackError) as info:
        read_table(path)
    assert re.fullmatch(
        rf"{re.escape(str(path))}: column 't' jumps by 0\.400 s at 1\.000 s into the log \(to 1\.400 s\), a gap longer than "
        r"--max-gap 0\.25 s; split the log there or allow a longer gap",
        one_line(info),
    ), one_line(info)
    assert len(read_table(path, max_gap=0.5)) == 48  # allowed: 0…2.35 s on the grid
    table[21:25, 1:5] = np.nan  # the positions alone missing 1.4…1.55 s: their own gap
    table[:, 0] = DT * np.arange(len(t))
    with pytest.raises(
        EfficientTrackError, match=r"dropout.csv: field 'q' \(columns q_boom, .*\) jumps by 0\.250 s at 1\.000 s"
    ):
        read_table(write_csv(path, header, table), max_gap=0.2)


def test_missing_columns_and_unknown_map_keys_are_named(tmp_path):
    t = DT * np.arange(10)
    header, table = table_of(t, positions(t), q_ref=positions(t))
    keep = [i for i, name in enumerate(header) if name != "q_swing"]
    path = write_csv(tmp_path / "partial.csv", [header[i] for i in keep], table[:, keep])
    with pytest.raises(EfficientTrackError) as info:
        read_table(path)
    assert one_line(info).startswith(f"{path}: no column(s) 'q_swing' (q.swing) (columns: t, q_boom, q_arm, q_bucket, q_ref_")
    with pytest.raises(EfficientTrackError, match=r"partial.csv: no time column 'time' \(columns: t, .*--time-column"):
        read_table(path, time_column="time")
    no_ref = write_csv(tmp_path / "noref.csv", header[:5], table[:, :5])
    with pytest.raises(EfficientTrackError, match=r"noref.csv: no reference: neither q_ref .* nor q_des"):
        read_table(no_ref)
    for columns, message in [
        ({"q.elbow": "X"}, r"--column 'q.elbow': unknown channel; expected FIELD.JOINT or FIELD"),
        ({"pos.boom": "X"}, r"--column 'pos.boom': unknown channel"),
        ({"t": "Time"}, r"--column 't': unknown channel; .* name the time column with --time-column"),
        ({"q": ["A", "B"]}, r"--column 'q': 2 column\(s\) given; expected 4, for boom, arm, bucket, swing"),
        (["q.boom"], r"--column 'q.boom': expected CHANNEL=COLUMN"),
        (["q.boom="], r"--column 'q.boom': empty column name"),
        (["q.boom=q_arm"], r"--column: column 'q_arm' is mapped to q.boom and q.arm; each joint of 'q' needs its own"),
        ({"q": ["A", "B", "A", "D"]}, r"--column: column 'A' is mapped to q.boom and q.bucket"),
    ]:
        with pytest.raises(EfficientTrackError, match=message):
            column_map(columns)
    with pytest.raises(EfficientTrackError, match=r"--column 'q.elbow': unknown channel"):
        read_table(path, {"q.elbow": "X"})
    names, given = column_map(["q.boom=Boom Angle", "u=U1,U2,U3,U4"])
    assert names["q"] == ("Boom Angle", "q_arm", "q_bucket", "q_swing") and names["u"] == ("U1", "U2", "U3", "U4")
    assert given == {"q", "u"}


def test_bad_cells_times_and_options_are_refused_in_one_line(tmp_path):
    t = DT * np.arange(10)
    header, table = table_of(t, positions(t), q_ref=positions(t))
    path = write_csv(tmp_path / "bad.csv", header, table)
    path.write_text(path.read_text().replace(repr(float(table[3, 2])), "oops", 1))
    with pytest.raises(EfficientTrackError, match=r"bad.csv: column 'q_arm' holds 'oops' at data row 4, not a number"):
        read_table(path)
    table[5, 0] = table[4, 0]
    with pytest.raises(EfficientTrackError, match=r"bad.csv: column 't' does not increase at data row 6 \(0.2, then 0.2\)"):
        read_table(write_csv(path, header, table))
    for options, message in [
        ({"time_unit": "min"}, r"--time-unit 'min': expected one of s, ms, us, ns"),
        ({"angle_unit": "grad"}, r"--angle-unit 'grad': expected one of rad, deg"),
        ({"max_gap": 0.01}, r"--max-gap 0.01: expected a number of seconds"),
        ({"max_gap": float("nan")}, r"--max-gap nan"),
    ]:
        with pytest.raises(EfficientTrackError, match=message):
            read_table(path, **options)


# ------------------------------------------------------------------------------------ our files, convert


def make_record(steps=40, seed=0, name="ours"):
    rng = np.random.default_rng(seed)
    q = np.cumsum(rng.normal(0, 0.01, (steps, 4)), axis=0)
    return EpisodeRecord(
        q=q,
        qd=rng.normal(0, 0.1, (steps, 4)),
        q_ref=q + rng.normal(0, 0.02, (steps, 4)),
        q_des=q + rng.normal(0, 0.02, (steps, 4)),
        u=rng.uniform(-1000, 1000, (steps, 4)),
        t=DT * np.arange(steps) + rng.uniform(0, 0.005, steps),
        meta={"name": name, "sigma": 0.0045},
    )


def test_our_own_csv_converts_exactly_as_before_and_round_trips_through_the_importer(tmp_path):
    path = save_csv(make_record(), tmp_path / "in" / "ours.csv")
    assert not needs_import(path)
    result = CliRunner().invoke(app, ["convert", str(tmp_path / "in"), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    before, after = load_record(path), load_record(tmp_path / "out" / "ours.npz")
    for name in ("q", "qd", "q_ref", "q_des", "u", "t"):
        np.testing.assert_array_equal(getattr(after, name), getattr(before, name), err_msg=name)
    assert after.meta == before.meta == {"name": "ours", "sigma": 0.0045}  # not resampled, not "imported"

    on_grid = make_record()
    on_grid.t = DT * np.arange(len(on_grid))
    imported = read_table(save_csv(on_grid, tmp_path / "grid.csv"))  # our names are the importer's defaults
    for name in ("q", "qd", "q_ref", "q_des", "u", "t"):
        np.testing.assert_allclose(getattr(imported, name), getattr(on_grid, name), rtol=0, atol=1e-12, err_msg=name)
    assert imported.meta["sigma"] == 0.0045 and imported.meta["imported"]["velocity"].startswith("logged")


def test_convert_imports_a_csv_without_velocities_and_names_the_method(tmp_path):
    t = irregular_times(100, seed=3)
    header, table = table_of(t, positions(t), q_ref=positions(t) + 0.01, u=np.zeros((len(t), 4)))
    path = write_csv(tmp_path / "novel.csv", header, table)
    assert needs_import(path)
    runner = CliRunner()
    result = runner.invoke(app, ["convert", str(path), "--out", str(tmp_path / "out"), "--format", "csv"])
    assert result.exit_code == 0, result.output
    [record] = load_records(tmp_path / "out")
    assert record.meta["imported"]["file"] == str(path) and record.meta["imported"]["velocity"].startswith("estimated")
    assert np.all(np.abs(wrap(record.q - positions(record.t))).max(axis=0) <= LINEAR_ERROR)
    # the options import every .csv, ours too, and are checked before any file is read
    ours = save_csv(make_record(), tmp_path / "ours.csv")
    result = runner.invoke(app, ["convert", str(ours), "--out", str(tmp_path / "o2"), "--time-column", "t"])
    assert result.exit_code == 0, result.output
    assert "imported" in load_record(tmp_path / "o2" / "ours.npz").meta
    result = runner.invoke(app, ["convert", str(ours), "--out", str(tmp_path / "o3"), "--column", "q.elbow=X"])
    assert isinstance(result.exception, EfficientTrackError) and "--column 'q.elbow'" in str(result.exception)
    assert not (tmp_path / "o3").exists()


# ----------------------------------------------------------------------------------------------- Parquet


def test_parquet_round_trip_and_a_timestamp_column(tmp_path):
    pa = pytest.importorskip("pyarrow", reason="pyarrow not installed (pip install 'efficienttrack[parquet]')")
    pq = pytest.importorskip("pyarrow.parquet")
    record = make_record(name="pq")
    record.t = DT * np.arange(len(record))
    columns = {"t": record.t, **{name: getattr(record, name.rsplit("_", 1)[0])[:, JOINT_NAMES.index(name.rsplit("_", 1)[1])]
                                   for name in OURS}}  # fmt: skip
    (tmp_path / "in").mkdir()
    pq.write_table(pa.table(columns), tmp_path / "in" / "pq.parquet")
    result = CliRunner().invoke(app, ["convert", str(tmp_path / "in"), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    back = load_record(tmp_path / "out" / "pq.npz")
    for name in ("q", "qd", "q_ref", "q_des", "u", "t"):
        np.testing.assert_allclose(getattr(back, name), getattr(record, name), rtol=0, atol=1e-12, err_msg=name)
    assert back.meta["imported"]["format"] == "parquet"

    t = irregular_times(120, seed=4)
    stamps = pa.array((1_700_000_000.0 + t) * 1e9, pa.float64()).cast(pa.int64()).cast(pa.timestamp("ns"))
    q = positions(t)
    table = pa.table({"when": stamps, **{f"pos{j}": q[:, j] for j in range(4)}, **{f"ref{j}": q[:, j] for j in range(4)}})
    pq.write_table(table, tmp_path / "stamped.parquet")
    imported = read_table(
        tmp_path / "stamped.parquet", ["q=pos0,pos1,pos2,pos3", "q_ref=ref0,ref1,ref2,ref3"], time_column="when"
    )
    assert np.all(np.abs(wrap(imported.q - positions(imported.t))).max(axis=0) <= LINEAR_ERROR)
    assert imported.meta["imported"]["time_unit"] == "from the Parquet type"


def test_parquet_without_pyarrow_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "x.parquet"
    path.write_bytes(b"PAR1")
    monkeypatch.setitem(sys.modules, "pyarrow", None)  # import pyarrow raises ImportError
    with pytest.raises(EfficientTrackError, match=r"x.parquet: install pyarrow .* pip install 'efficienttrack\[parquet\]'"):
        read_table(path)


# --------------------------------------------------------------------------------- the real XE75 logs


XE75_TOLERANCE = np.array([0.025, 0.025, 0.12, 0.015])
"""RMSE bounds of the estimated velocities against the sensor rates, rad/s (boom, arm, bucket, swing); measured over
all 40 pd_clean_train episodes: 0.0149, 0.0151, 0.0823, 0.0071 (docs/your-logs.md)."""


@pytest.mark.skipif(not PD_CLEAN.is_dir(), reason=f"the real XE75 logs not found at {PD_CLEAN}")
def test_velocities_estimated_from_the_xe75_positions_match_its_sensor_rates(tmp_path):
    squares, steps = np.zeros(4), 0
    for file in sorted(PD_CLEAN.glob("*.npz"))[:4]:
        log = load_record(file)
        header, table = table_of(log.t, log.q, q_ref=log.q_ref, u=log.u)  # the log without qd, at its own times
        imported = read_table(write_csv(tmp_path / file.name.replace(".npz", ".csv"), header, table))
        sensor = np.stack([np.interp(log.t[0] + imported.t, log.t, log.qd[:, j]) for j in range(4)], axis=1)
        squares += ((imported.qd - sensor) ** 2).sum(axis=0)
        steps += len(imported)
    rmse = np.sqrt(squares / steps)
    assert np.all(rmse < XE75_TOLERANCE), dict(zip(JOINT_NAMES, rmse.round(4), strict=True))
