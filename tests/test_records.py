import json
import os
import re
import sys
import warnings
from pathlib import Path

import numpy as np
import numpy.lib.format as npy_format
import pytest
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.cli import main as cli_main
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.records import (
    EpisodeRecord,
    RecordWarning,
    load_csv,
    load_named_records,
    load_record,
    load_records,
    load_upstream_npy,
    save_csv,
    save_records,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
UPSTREAM = DATA / "upstream_format_samples"
FIELDS = ("q", "qd", "q_ref", "q_des", "u", "t")


def needs_data():
    if not UPSTREAM.is_dir():
        pytest.skip(f"shared XE75 data not found at {DATA}")


def make_record(steps=30, seed=0, with_u=True, name="ep"):
    rng = np.random.default_rng(seed)
    q = np.cumsum(rng.normal(0, 0.01, (steps, 4)), axis=0)
    return EpisodeRecord(
        q=q,
        qd=rng.normal(0, 0.1, (steps, 4)),
        q_ref=q + rng.normal(0, 0.02, (steps, 4)),
        q_des=q + rng.normal(0, 0.02, (steps, 4)),
        u=rng.uniform(-1000, 1000, (steps, 4)) if with_u else None,
        t=0.05 * np.arange(steps) + rng.uniform(0, 0.005, steps),
        meta={"name": name, "sigma": 0.0045, "note": "round trip"},
    )


def assert_same(a, b, atol=0.0):
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        if x is None or y is None:
            assert x is None and y is None, name
        elif atol == 0.0:
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            np.testing.assert_allclose(x, y, rtol=0, atol=atol, err_msg=name)


# ------------------------------------------------------------------------------------------- round trips


def test_npz_round_trip(tmp_path):
    record = make_record()
    loaded = EpisodeRecord.load(record.save(tmp_path / "a.npz"))
    assert_same(record, loaded)
    assert loaded.meta == record.meta
    assert not list(tmp_path.glob(".*tmp"))  # atomic write left no temporary file


@pytest.mark.parametrize("with_u", [True, False])
def test_csv_round_trip_is_exact(tmp_path, with_u):
    record = make_record(with_u=with_u)
    path = save_csv(record, tmp_path / "a.csv")
    header = path.read_text().splitlines()[1].split(",")
    assert header[:6] == ["t", "q_boom", "q_arm", "q_bucket", "q_swing", "qd_boom"]
    assert ("u_swing" in header) == with_u
    assert len(header) == 1 + 4 * (5 if with_u else 4)
    loaded = load_csv(path)
    assert_same(record, loaded)
    assert loaded.meta == record.meta


def test_save_and_load_records_folder(tmp_path):
    records = [make_record(seed=i, name=f"run_{i}") for i in (2, 0, 1)]
    paths = save_records(records, tmp_path / "out")
    assert [p.name for p in paths] == ["run_2.npz", "run_0.npz", "run_1.npz"]
    save_records(records[:1], tmp_path / "out" / "sub", fmt="csv")
    loaded = load_records(tmp_path / "out")  # the episodes directly in the folder, sorted
    assert [r.meta["name"] for r in loaded] == ["run_0", "run_1", "run_2"]
    loaded = load_records(tmp_path / "out", recursive=True)  # subfolders too, sorted by path
    assert [r.meta["name"] for r in loaded] == ["run_0", "run_1", "run_2", "run_2"]
    assert_same(loaded[3], records[0])
    with pytest.raises(EfficientTrackError, match="several records are named run_0"):
        save_records([records[1], records[1]], tmp_path / "dup")
    with pytest.raises(EfficientTrackError, match="--format 'hdf5'"):
        save_records(records, tmp_path / "x", fmt="hdf5")


def test_named_records_in_order_and_missing_ones_reported(tmp_path):
    save_records([make_record(seed=i, name=f"run_{i}") for i in (0, 1)], tmp_path)
    assert [r.meta["name"] for r in load_named_records(tmp_path, ["run_1", "run_0"])] == ["run_1", "run_0"]
    with pytest.raises(EfficientTrackError, match="run_2 missing"):
        load_named_records(tmp_path, ["run_0", "run_2"])


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04garbage", b"not a zip at all"])
def test_corrupt_npz_is_a_clear_error(tmp_path, content):
    path = tmp_path / "broken.npz"
    path.write_bytes(content)
    with pytest.raises(EfficientTrackError, match="broken.npz: not a readable .npz"):
        load_record(path)


def test_unnamed_records_get_numbered_names(tmp_path):
    record = make_record()
    record.meta = {}
    assert [p.name for p in save_records([record], tmp_path)] == ["episode_0000.npz"]


# -------------------------------------------------------------------------------- the upstream format


@pytest.mark.parametrize("stem", ["zc_interp_train1_2024_10_31_11_28_04", "zc_interp_train1_2024_10_31_14_49_55"])
def test_upstream_files_equal_the_converted_npz(stem):
    needs_data()
    reference = EpisodeRecord.load(DATA / "xe75" / "pd_noise_train" / f"{stem}.npz")
    from_npy = load_upstream_npy(UPSTREAM / f"{stem}.npy")
    assert_same(from_npy, reference)  # bit-exact
    from_csv = load_record(UPSTREAM / f"{stem}.csv")
    assert_same(from_csv, reference, atol=1e-7)  # 8 printed decimals
    assert len(from_npy) == 422 and from_npy.meta["name"] == stem


def test_upstream_folder_reads_npy_not_csv_duplicates(tmp_path):
    needs_data()
    records = load_records(UPSTREAM)
    assert [r.meta["name"] for r in records] == sorted(p.stem for p in UPSTREAM.glob("*.npy"))
    assert_same(records[0], load_upstream_npy(UPSTREAM / "zc_interp_train1_2024_10_31_11_28_04.npy"))  # the .npy, exact
    # the CSV alone is read when no .npy sits next to it, and differs from the .npy in the last digits
    csv_only = tmp_path / "only.csv"
    csv_only.write_text((UPSTREAM / "zc_interp_train1_2024_10_31_11_28_04.csv").read_text())
    (from_csv,) = load_records([csv_only])
    assert not np.array_equal(from_csv.q, records[0].q)
    np.testing.assert_allclose(from_csv.q, records[0].q, atol=1e-8, rtol=0)


def test_convert_command_upstream_to_csv_and_back(tmp_path):
    needs_data()
    runner = CliRunner()
    result = runner.invoke(app, ["convert", str(UPSTREAM), "--out", str(tmp_path / "csv"), "--format", "csv"])
    assert result.exit_code == 0, result.output
    assert "wrote 2 episode(s)" in result.output
    result = runner.invoke(app, ["convert", str(tmp_path / "csv"), "--out", str(tmp_path / "npz")])
    assert result.exit_code == 0, result.output
    for original, converted in zip(load_records(UPSTREAM), load_records(tmp_path / "npz"), strict=True):
        assert_same(original, converted)  # .npy → our CSV → .npz is lossless
        assert converted.meta == original.meta


# ------------------------------------------------------------------------------------------ validation


def write_npz(path, **changes):
    arrays = {name: getattr(make_record(steps=12), name) for name in FIELDS}
    arrays.update(changes)
    np.savez(path, **{k: v for k, v in arrays.items() if v is not None})
    return path


@pytest.mark.parametrize(
    ("changes", "field", "problem"),
    [
        ({"qd": None}, "qd", "missing"),
        ({"u": np.zeros((11, 4))}, "u", r"shape \(11, 4\), expected \(12, 4\)"),
        ({"q_ref": np.zeros((12, 3))}, "q_ref", "shape"),
        ({"t": np.arange(11.0)}, "t", "shape"),
        ({"q_des": np.where(np.arange(12)[:, None] == 5, np.nan, 0.1) * np.ones((12, 4))}, "q_des", "NaN/inf.*step 5"),
        ({"qd": np.full((12, 4), np.inf)}, "qd", "NaN/inf"),
        ({"t": np.where(np.arange(12) == 3, np.inf, np.arange(12.0))}, "t", "NaN/inf"),
        ({"q": np.full((12, 4), 45.0)}, "q", "degrees"),
        ({"q": np.zeros((1, 4))}, "q", "at least 2 steps"),
    ],
)
def test_validation_errors_name_file_and_field(tmp_path, changes, field, problem):
    write_npz(tmp_path / "bad_episode.npz", **changes)
    with pytest.raises(EfficientTrackError, match=problem) as info:
        load_records([tmp_path])
    message = str(info.value)
    assert "bad_episode.npz" in message
    assert f"field '{field}'" in message or f"field(s) '{field}'" in message


def test_csv_and_upstream_validation_errors(tmp_path):
    path = save_csv(make_record(steps=12), tmp_path / "ours.csv")
    lines = path.read_text().splitlines()
    header = lines[1].split(",")
    col = header.index("q_arm")
    body = [",".join(v for i, v in enumerate(line.split(",")) if i != col) for line in lines[1:]]
    path.write_text("\n".join([lines[0], *body]) + "\n")
    with pytest.raises(EfficientTrackError, match=r"ours.csv: field 'q' lacks column\(s\) q_arm"):
        load_csv(path)

    up = tmp_path / "up.csv"
    up.write_text("target,real_target,js,jv,time,action\n[1 2 3 4],[1 2 3 4],[1 2 3],[0 0 0 0],0.0,[0 0 0 0]\n")
    with pytest.raises(EfficientTrackError, match=r"up.csv: field 'js' does not hold 4 values"):
        load_csv(up)
    up.write_text("target,real_target,jv,time,action,extra\n")
    with pytest.raises(EfficientTrackError, match=r"up.csv: unknown CSV header"):
        load_csv(up)

    arr = np.empty((), dtype=object)
    arr[()] = {"js": [np.zeros(4)] * 3, "jv": [np.zeros(4)] * 3, "time": [0.0, 0.05, 0.1]}
    np.save(tmp_path / "partial.npy", arr, allow_pickle=True)
    with pytest.raises(EfficientTrackError, match=r"partial.npy: missing field\(s\) 'target', 'real_target', 'action'"):
        load_upstream_npy(tmp_path / "partial.npy")
    np.save(tmp_path / "ref.npy", np.zeros((10, 4)))
    with pytest.raises(EfficientTrackError, match=r"ref.npy: holds a float64 array of shape \(10, 4\)"):
        load_upstream_npy(tmp_path / "ref.npy")


def test_time_problems_only_warn(tmp_path):
    t = 0.05 * np.arange(12)
    write_npz(tmp_path / "backwards.npz", t=t[::-1].copy())
    with pytest.warns(RecordWarning, match="backwards.npz: timestamps are not increasing"):
        assert len(load_record(tmp_path / "backwards.npz")) == 12
    jitter = t.copy()
    jitter[6:] += 0.2  # a 0.25 s gap: dropped samples
    write_npz(tmp_path / "jitter.npz", t=jitter)
    with pytest.warns(RecordWarning, match="jitter.npz: jittery sampling, 1 step"):
        load_record(tmp_path / "jitter.npz")
    write_npz(tmp_path / "fine.npz", t=t + np.tile([0.0, 0.02], 6))  # 0.03/0.07 s steps are normal jitter
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_record(tmp_path / "fine.npz")


def test_the_subfolder_hint_counts_episodes_only(tmp_path):
    run = tmp_path / "run"
    (run / "refs" / "train").mkdir(parents=True)
    np.save(run / "refs" / "train" / "ref_00.npy", np.zeros((5, 4)))
    (run / "logs").mkdir()
    (run / "logs" / "scalars.csv").write_text("step,tag,value\n1,train/loss,0.5\n")
    with pytest.raises(EfficientTrackError, match="run: folder holds no episode files"):
        load_records(run)  # a reference and a log of scalars are not episodes
    save_records([make_record(name="a"), make_record(name="b")], run / "records" / "pass_000")
    save_records([make_record(name="c")], run / "records" / "pass_001", fmt="csv")
    with pytest.raises(EfficientTrackError, match=r"run: no episode files directly .* but 3 in 2 subfolder\(s\) \("):
        load_records(run)


def test_missing_and_empty_paths(tmp_path):
    with pytest.raises(EfficientTrackError, match="nowhere: no such file or folder"):
        load_records([tmp_path / "nowhere"])
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no episodes here")
    with pytest.raises(EfficientTrackError, match="empty: folder holds no episode files"):
        load_records(tmp_path / "empty")
    save_records([make_record(name="a")], tmp_path / "empty" / "pass_000")
    save_records([make_record(name="b")], tmp_path / "empty" / "pass_001")
    with pytest.raises(
        EfficientTrackError,
        match=r"empty: no episode files directly .* 2 in 2 subfolder\(s\) \(pass_000/, pass_001/\); .*--recursive",
    ):
        load_records(tmp_path / "empty")
    assert [r.meta["name"] for r in load_records(tmp_path / "empty", recursive=True)] == ["a", "b"]
    with pytest.raises(EfficientTrackError, match="notes.txt: unknown episode format"):
        load_records([tmp_path / "empty" / "notes.txt"])
    (tmp_path / "garbage.npz").write_bytes(b"not a zip")
    with pytest.raises(EfficientTrackError, match="garbage.npz: not a readable .npz"):
        load_records([tmp_path / "garbage.npz"])


# ------------------------------------------------------------------------------------- malicious pickle


class Exploit:
    """Unpickling this runs a shell command (what a hostile upstream file would do)."""

    def __init__(self, command):
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


def write_evil_npy(path, marker):
    """A valid .npy header (0-d object array) whose pickled dict carries the exploit."""
    arr = np.empty((), dtype=object)
    arr[()] = {"js": [np.zeros(4)], "time": [Exploit(f"touch {marker}")]}
    with path.open("wb") as f:
        npy_format.write_array(f, arr, allow_pickle=True)
    return path


def test_malicious_pickle_is_refused_and_never_executed(tmp_path):
    evil = write_evil_npy(tmp_path / "evil.npy", tmp_path / "pwned")
    with pytest.raises(EfficientTrackError, match=r"evil.npy: refused to unpickle global '(posix|os|nt)\.system'"):
        load_records([evil])
    with pytest.raises(EfficientTrackError, match="refused"):
        load_records([tmp_path])
    assert not (tmp_path / "pwned").exists()

    # the payload is live: a plain pickle load would have run it
    live = write_evil_npy(tmp_path / "live.npy", tmp_path / "live_marker")
    np.load(live, allow_pickle=True)
    assert (tmp_path / "live_marker").exists()


def run_main(monkeypatch, capsys, *args):
    """Run the ``efficienttrack`` entry point (``cli.main``) in this process, as the console script would.

    Returns:
        (exit code, stdout, stderr); an exception ``main`` lets through fails the test with its traceback.
    """
    monkeypatch.setattr(sys, "argv", ["efficienttrack", *args])
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)  # main() sets its one-line format
    code = 0
    try:
        cli_main()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_refuses_malicious_pickle_without_traceback(tmp_path, monkeypatch, capsys):
    evil = write_evil_npy(tmp_path / "evil.npy", tmp_path / "pwned")
    code, out, err = run_main(monkeypatch, capsys, "metrics", str(evil))
    assert code == 2
    assert "Traceback" not in err + out
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "evil.npy: refused to unpickle" in lines[0]
    assert not (tmp_path / "pwned").exists()


def test_restricted_unpickler_refuses_other_numpy_globals(tmp_path):
    # numpy itself is not trusted wholesale: only the array reconstruction globals are allowed
    payload = b"cnumpy\nload\n(S'x'\ntR."
    path = tmp_path / "np_load.npy"
    with path.open("wb") as f:
        npy_format.write_array_header_1_0(f, {"descr": "|O", "fortran_order": False, "shape": ()})
        f.write(payload)
    with pytest.raises(EfficientTrackError, match=r"np_load.npy: refused to unpickle global 'numpy\.load'"):
        load_upstream_npy(path)
    path.write_bytes(path.read_bytes()[:-6])
    with pytest.raises(EfficientTrackError, match="np_load.npy: "):
        load_upstream_npy(path)


def test_metrics_json_cli_line(tmp_path):
    needs_data()
    result = CliRunner().invoke(app, ["metrics", "--json", str(UPSTREAM)])
    assert result.exit_code == 0, result.output
    (line,) = result.output.strip().splitlines()
    figures = json.loads(line)
    assert figures["episodes"] == 2 and figures["steps"] == 844
    assert figures["mae_deg"] == pytest.approx(6.00, abs=0.005)


# ------------------------------------------------------------------- names, meta and dtypes from file contents


@pytest.mark.parametrize("name", ["../../x", "/abs/x", "sub/x", "..", "a\x00b", ""])
def test_convert_never_writes_outside_out(tmp_path, name):
    """A record's stored name becomes its file name: one leading outside --out is refused, nothing is written."""
    source, out, sibling = tmp_path / "in", tmp_path / "a" / "out", tmp_path / "a" / "sibling"
    save_records([make_record(name="victim")], sibling)
    before = (sibling / "victim.npz").read_bytes()
    source.mkdir()
    write_npz(source / "ep.npz", meta_json=np.array(json.dumps({"name": name})))
    result = CliRunner().invoke(app, ["convert", str(source), "--out", str(out)])
    assert isinstance(result.exception, EfficientTrackError), result.output
    assert f"ep.npz: field 'meta_json' key 'name' = {name!r} cannot be a file name" in str(result.exception)
    assert (sibling / "victim.npz").read_bytes() == before
    written = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file())
    assert written == ["a/sibling/victim.npz", "in/ep.npz"]


def test_cli_convert_traversal_is_one_line_exit_2(tmp_path, monkeypatch, capsys):
    (tmp_path / "in").mkdir()
    write_npz(tmp_path / "in" / "ep.npz", meta_json=np.array(json.dumps({"name": "../../x"})))
    monkeypatch.chdir(tmp_path)
    code, out, err = run_main(monkeypatch, capsys, "convert", "in", "--out", "out")
    assert code == 2 and out == "", err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "ep.npz: field 'meta_json' key 'name'" in lines[0]
    assert not (tmp_path.parent / "x.npz").exists() and not (tmp_path / "out").exists()


def test_save_records_refuses_names_leading_outside_the_folder(tmp_path):
    for name in ("../escape", "/tmp/abs", ".hidden", "a\x00b"):
        with pytest.raises(
            EfficientTrackError, match=re.escape(f"out: record 0 meta 'name' = {name!r} cannot be a file name")
        ):
            save_records([make_record(name=name)], tmp_path / "out")
    assert not (tmp_path / "escape.npz").exists() and not list((tmp_path / "out").glob("*"))
    path = save_csv(make_record(name="../x"), tmp_path / "ours.csv")
    with pytest.raises(EfficientTrackError, match=r"ours.csv: field 'meta' key 'name' = '../x' cannot be a file name"):
        load_csv(path)


@pytest.mark.parametrize(
    ("meta_json", "problem"),
    [
        (np.array("[1, 2]"), "field 'meta_json' holds a JSON list, expected an object"),
        (np.array("{bad"), "field 'meta_json' is not valid JSON"),
        (np.array("[" * 100_000), "field 'meta_json' is not valid JSON .RecursionError"),
        (np.array(b"\xff\xfe"), "field 'meta_json': has dtype |S2, expected a text string"),
        (np.array(["{}", "{}"]), r"field 'meta_json' has shape \(2,\), expected one string"),
        (np.array('{"name": 5}'), "field 'meta_json' key 'name' = 5 cannot be a file name: it is a int"),
    ],
)
def test_malformed_meta_json_is_a_clear_error(tmp_path, meta_json, problem):
    write_npz(tmp_path / "m.npz", meta_json=meta_json)
    with pytest.raises(EfficientTrackError, match=f"m.npz: {problem}"):
        load_record(tmp_path / "m.npz")


def test_bool_and_complex_arrays_are_refused(tmp_path):
    for dtype in (bool, complex, np.int64):
        write_npz(tmp_path / "x.npz", q=np.zeros((12, 4), dtype))
        with pytest.raises(
            EfficientTrackError, match=f"x.npz: field 'q': has dtype {np.dtype(dtype)}, expected real floating"
        ):
            load_record(tmp_path / "x.npz")
    record = make_record(steps=12)
    record.q = np.zeros((12, 4), complex)
    with pytest.raises(EfficientTrackError, match="mem: field 'q' has dtype complex128, expected real numbers"):
        record.validate("mem")
    arr = np.empty((), dtype=object)
    arr[()] = {key: [np.ones(4, bool)] * 3 for key in ("js", "jv", "target", "real_target", "action")} | {"time": [0.0] * 3}
    np.save(tmp_path / "up.npy", arr, allow_pickle=True)
    with pytest.raises(EfficientTrackError, match=r"up.npy: field 'js' \(q\) has dtype bool, expected real numbers"):
        load_upstream_npy(tmp_path / "up.npy")


def test_a_tiny_upstream_file_cannot_expand(tmp_path):
    """The probe's 562-byte upstream .npy that expanded to 690 MB: its array is refused before it is allocated."""
    reconstruct = np.ndarray.__reduce__(np.empty(0))[0]

    class Expanding:
        def __reduce__(self):
            return (reconstruct, (np.ndarray, (0,), b"b"), (1, (90_000_000,), np.dtype("f8"), False, b""))

    arr = np.empty((), dtype=object)
    arr[()] = {"js": Expanding()}
    np.save(tmp_path / "tiny.npy", arr, allow_pickle=True)
    assert (tmp_path / "tiny.npy").stat().st_size < 600
    with pytest.raises(EfficientTrackError, match=r"tiny.npy: declares a float64 array of shape \(90000000,\)"):
        load_records([tmp_path])


def test_damaged_npz_names_the_field_in_one_line(tmp_path):
    path = save_records([make_record(steps=400)], tmp_path)[0]
    raw = bytearray(path.read_bytes())
    start = raw.index(b"q.npy") + len("q.npy") + 200
    raw[start : start + 64] = bytes(64)  # np.savez stores: the damage shows as a CRC error
    path.write_bytes(bytes(raw))
    with pytest.raises(EfficientTrackError, match=r"ep.npz: field 'q': damaged \(Bad CRC-32") as info:
        load_record(path)
    assert "\n" not in str(info.value)


def test_a_hidden_file_stem_is_kept_as_the_name(tmp_path):
    """Only names stored inside a file are checked on load; a file's own stem is a file name already."""
    write_npz(tmp_path / ".hidden.npz")
    assert load_record(tmp_path / ".hidden.npz").meta["name"] == ".hidden"
