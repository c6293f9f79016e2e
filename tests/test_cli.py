"""The command line as a newcomer uses it: one metrics row per path, explicit recursion, --force, permissions, options."""

import csv
import functools
import json
import os
import stat

import pytest
import typer.main
from typer.testing import CliRunner

from efficienttrack import __version__
from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, current_umask
from efficienttrack.data.metrics import METRIC_KEYS, compute_metrics
from efficienttrack.data.records import load_records, save_records
from efficienttrack.data.references import save_references
from efficienttrack.workflow import pipeline
from efficienttrack.workflow.config import PRESETS, amend, load_config
from test_dynamics import lag_records
from test_records import make_record
from toy_system import sine_refs


def invoke(*args):
    """Run the app in-process; returns the click result (``exception`` holds an EfficientTrackError)."""
    return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "200"})


@functools.cache
def click_command():
    """The click command typer builds from ``app`` at every call (about 65 ms), built once for the tests that parse or
    run many command lines."""
    return typer.main.get_command(app)


def refused(result, message):
    assert isinstance(result.exception, EfficientTrackError), result.output
    assert message in str(result.exception), str(result.exception)


@pytest.fixture
def two_sets(tmp_path):
    """Two folders of episodes: a/ with 2, b/ with 3."""
    a = save_records([make_record(seed=i, name=f"a{i}") for i in range(2)], tmp_path / "a")
    b = save_records([make_record(seed=10 + i, name=f"b{i}") for i in range(3)], tmp_path / "b")
    return tmp_path / "a", tmp_path / "b", a + b


# ----------------------------------------------------------------------------------------------- metrics


def test_metrics_one_row_per_path(two_sets):
    a, b, _ = two_sets
    result = invoke("metrics", a, b, "--json")
    assert result.exit_code == 0, result.output
    rows = [json.loads(line) for line in result.output.strip().splitlines()]
    assert [row["path"] for row in rows] == [str(a), str(b)]
    assert [row["episodes"] for row in rows] == [2, 3]
    assert list(rows[0]) == ["path", *METRIC_KEYS]
    assert rows[1]["mae_deg"] == pytest.approx(compute_metrics(load_records(b))["mae_deg"], abs=1e-4)
    table = invoke("metrics", a, b)
    assert table.exit_code == 0 and str(a) in table.output and str(b) in table.output


def test_metrics_pool(two_sets):
    a, b, _ = two_sets
    result = invoke("metrics", a, b, "--json", "--pool")
    (line,) = result.output.strip().splitlines()
    row = json.loads(line)
    assert row["episodes"] == 5 and row["path"] == f"{a} + {b}"
    assert row["mae_deg"] == pytest.approx(compute_metrics(load_records([a, b]))["mae_deg"], abs=1e-4)
    refused(invoke("metrics", a, "--pool", "--per-episode"), "exclude each other")


def test_metrics_per_episode_csv(two_sets, tmp_path):
    a, b, files = two_sets
    out = tmp_path / "per_episode.csv"
    result = invoke("metrics", a, b, "--per-episode", "--csv", out, "--json")
    assert result.exit_code == 0, result.output
    rows = [json.loads(line) for line in result.output.strip().splitlines()]
    assert [row["path"] for row in rows] == [str(f) for f in sorted(files[:2]) + sorted(files[2:])]
    assert all(row["episodes"] == 1 for row in rows)
    with out.open() as f:
        table = list(csv.DictReader(f))
    assert [row["path"] for row in table] == [row["path"] for row in rows]
    assert float(table[3]["mae_deg"]) == pytest.approx(rows[3]["mae_deg"], abs=1e-4)
    assert float(table[3]["mae_deg_swing"]) == pytest.approx(rows[3]["per_joint_mae_deg"][3], abs=1e-4)


def test_folders_are_not_recursive_unless_asked(tmp_path):
    save_records([make_record(seed=1, name="x")], tmp_path / "records" / "pass_000")
    save_records([make_record(seed=2, name="y")], tmp_path / "records" / "pass_001")
    result = invoke("metrics", tmp_path / "records", "--json")
    refused(result, "no episode files directly in this folder, but 2 in 2 subfolder(s) (pass_000/, pass_001/)")
    assert "--recursive" in str(result.exception)
    result = invoke("metrics", tmp_path / "records", "--json", "-r")
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["episodes"] == 2
    refused(invoke("convert", tmp_path / "records", "--out", tmp_path / "c"), "--recursive")
    assert invoke("convert", tmp_path / "records", "--out", tmp_path / "c", "--recursive").exit_code == 0
    assert sorted(p.name for p in (tmp_path / "c").iterdir()) == ["x.npz", "y.npz"]


# ------------------------------------------------------------------------------------------------ --force


def test_refs_generate_refuses_a_full_folder_and_force_removes_stale_references(tmp_path):
    out = tmp_path / "refs"
    assert invoke("refs", "generate", "--out", out, "--n", "4").exit_code == 0
    (out / "notes.txt").write_text("mine")
    (out / "references.png").write_bytes(b"old plot")
    refused(invoke("refs", "generate", "--out", out, "--n", "2"), "folder is not empty")
    assert len(list(out.glob("*.npy"))) == 4
    result = invoke("refs", "generate", "--out", out, "--n", "2", "--force")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "ref_01.npy", "ref_02.npy"]


def test_convert_force(two_sets, tmp_path):
    a, b, _ = two_sets
    out = tmp_path / "converted"
    assert invoke("convert", b, "--out", out, "--format", "csv").exit_code == 0
    (out / "README").write_text("mine")
    refused(invoke("convert", a, "--out", out), "folder is not empty")
    assert invoke("convert", a, "--out", out, "--force").exit_code == 0
    assert sorted(p.name for p in out.iterdir()) == ["README", "a0.npz", "a1.npz"]
    refused(invoke("convert", out, "--out", out, "--force"), "holds the input")


def test_evaluate_force(tmp_path):
    refs = sine_refs([30, 30, 30], seed=1)
    save_references(refs, tmp_path / "refs3")
    save_references(refs[:2], tmp_path / "refs2")
    out = tmp_path / "eval"
    args = ["evaluate", "--system", "toy_system:make", "--out", out, "--plots", "0"]  # the plots are test_pipeline's
    assert invoke(*args, "--refs", tmp_path / "refs3").exit_code == 0
    (out / "notes.txt").write_text("mine")
    refused(invoke(*args, "--refs", tmp_path / "refs2"), "folder is not empty")
    result = invoke(*args, "--refs", tmp_path / "refs2", "--force")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (out / "records" / "pd").iterdir()) == ["ref_00.npz", "ref_01.npz"]
    assert (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "metrics.json").read_text())["pd"]["episodes"] == 2


def test_run_refuses_a_folder_of_other_files(tmp_path):
    save_references(sine_refs([30, 30], seed=1), tmp_path / "refs")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "thesis.tex").write_text("mine")
    args = ["run", "--system", "toy_system:make", "--train-refs", tmp_path / "refs", "--test-refs", tmp_path / "refs"]
    refused(invoke(*args, "--out", tmp_path / "out", "--preset", "tiny"), "thesis.tex")


def test_force_restarts_a_training_blocked_by_its_state(tmp_path):
    save_records(lag_records(n=2, T=40), tmp_path / "data")
    out = tmp_path / "model.pt"
    args = ["train-model", "--data", tmp_path / "data", "--out", out, "--preset", "tiny", "--device", "cpu"]
    assert invoke(*args, "--steps", "3").exit_code == 0
    refused(invoke(*args, "--steps", "4"), "training state of another run")
    result = invoke(*args, "--steps", "4", "--force")
    assert result.exit_code == 0, result.output
    assert "4 steps" in result.output and out.with_suffix(".state.pt").is_file()


# ------------------------------------------------------------------------------------ files and options


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_written_files_follow_the_umask(tmp_path, umask_022):
    assert current_umask() == 0o022
    path = atomic_write(tmp_path / "x.bin", lambda f: f.write(b"1"))
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert invoke("refs", "generate", "--out", tmp_path / "refs", "--n", "2").exit_code == 0
    assert {stat.S_IMODE(p.stat().st_mode) for p in (tmp_path / "refs").iterdir()} == {0o644}
    os.umask(0o077)
    assert stat.S_IMODE(atomic_write(tmp_path / "y.bin", lambda f: f.write(b"1")).stat().st_mode) == 0o600


def test_version():
    result = invoke("--version")
    assert result.exit_code == 0 and result.output.strip() == f"efficienttrack {__version__}"


def test_yaml_reads_exponents_as_numbers(tmp_path):
    path = tmp_path / "cfg.yaml"
    path.write_text("model:\n  lr: 1e-5\npolicy:\n  lr: 3E-4\n  steps: 7\n")
    cfg = load_config(path, PRESETS["tiny"])
    assert cfg.model.lr == 1e-05 and cfg.policy.lr == 3e-4 and cfg.policy.steps == 7


def test_demo_options_build_the_run_config(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(pipeline, "demo", lambda out, cfg, console, max_plots: calls.append((out, cfg)))
    (tmp_path / "tiny.yaml").write_text("model:\n  lr: 1e-5\n")
    out = tmp_path / "demo"
    result = invoke(
        "demo", "--out", out, "--preset", "tiny", "--config", tmp_path / "tiny.yaml", "--seed", "7", "--device", "cpu"
    )
    assert result.exit_code == 0, result.output
    expected = amend(load_config(tmp_path / "tiny.yaml", PRESETS["tiny"]), {"seed": 7, "device": "cpu"}, "test")
    assert calls == [(out, expected)]
    assert expected.model.lr == 1e-05 and expected.collect.seed == 7 and expected.policy == PRESETS["tiny"].policy
