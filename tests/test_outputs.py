"""Outputs are safe: checked before the work, locked against a second writer, and finished episodes kept on a failure."""

import errno
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from efficienttrack import cli
from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import check_output_file, check_output_folder, lock_path, output_lock
from efficienttrack.data.records import save_records
from efficienttrack.data.references import save_references
from test_dynamics import lag_records
from toy_system import LagSystem, sine_refs


def invoke(*args):
    """Run the app in-process; returns the click result (``exception`` holds an EfficientTrackError)."""
    return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "200"})


def refused(result, *messages):
    assert isinstance(result.exception, EfficientTrackError), result.output
    for message in messages:
        assert message in str(result.exception), str(result.exception)


# ----------------------------------------------------------------------------------- checked before the work


def test_check_output_file_and_folder(tmp_path):
    afile, adir = tmp_path / "afile", tmp_path / "adir"
    afile.write_text("mine")
    adir.mkdir()
    with pytest.raises(EfficientTrackError, match="is a folder, expected a file"):
        check_output_file(adir)
    with pytest.raises(EfficientTrackError, match=f"{afile} is a file, not a folder"):
        check_output_file(afile / "deeper" / "m.pt")
    with pytest.raises(EfficientTrackError, match="--plot .*: is a file, expected a folder"):
        check_output_folder(afile, "--plot")
    with pytest.raises(EfficientTrackError, match="is a file, not a folder"):
        check_output_folder(afile / "run")
    assert check_output_file(tmp_path / "new" / "deeper" / "m.pt") == tmp_path / "new" / "deeper" / "m.pt"
    check_output_folder(tmp_path / "new" / "run")
    check_output_folder(adir)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "afile"]  # no folder created, no probe left
    assert list(adir.iterdir()) == []


@pytest.mark.parametrize(
    ("fail", "code", "reason"),
    [("mkstemp", errno.EROFS, "Read-only file system"), ("fsync", errno.ENOSPC, "No space left on device")],
)
def test_a_read_only_or_full_disk_is_found_by_the_probe(tmp_path, monkeypatch, fail, code, reason):
    def refuse(*args, **kwargs):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(tempfile if fail == "mkstemp" else os, fail, refuse)
    with pytest.raises(EfficientTrackError, match=f"--out {tmp_path / 'eval'}: cannot write in {tmp_path} \\({reason}\\)"):
        check_output_folder(tmp_path / "eval")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_folder_without_write_permission_is_refused(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    with pytest.raises(EfficientTrackError, match="cannot write in .*Permission denied"):
        check_output_file(locked / "model.pt")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["collect", "--refs", "{missing}", "--out", "{afile}"], "--out {afile}: is a file, expected a folder"),
        (["evaluate", "--refs", "{missing}", "--out", "{afile}"], "--out {afile}: is a file, expected a folder"),
        (["run", "--train-refs", "{missing}", "--test-refs", "{missing}", "--out", "{afile}"], "--out {afile}: is a file"),
        (["demo", "--out", "{afile}/demo"], "--out {afile}/demo: {afile} is a file, not a folder"),
        (["train-model", "--data", "{missing}", "--out", "{afile}/m.pt"], "--out {afile}/m.pt: {afile} is a file"),
        (["train-model", "--data", "{missing}", "--out", "{adir}"], "--out {adir}: is a folder, expected a file"),
        (["train-policy", "--model", "{missing}", "--data", "{missing}", "--out", "{adir}"], "--out {adir}: is a folder"),
        (["round", "--model", "{missing}", "--policy", "{missing}", "--data", "{missing}", "--out", "{afile}"], "is a file"),
        (["convert", "{missing}", "--out", "{afile}"], "--out {afile}: is a file, expected a folder"),
        (["sim", "calibrate", "--logs", "{missing}", "--out", "{adir}"], "--out {adir}: is a folder, expected a file"),
        (["sim", "fidelity", "--logs", "{missing}", "--plot", "{afile}"], "--plot {afile}: is a file, expected a folder"),
        (["refs", "generate", "--out", "{afile}"], "--out {afile}: is a file, expected a folder"),
        (["refs", "plot", "{missing}", "--out", "{adir}"], "--out {adir}: is a folder, expected a file"),
        (["metrics", "{missing}", "--csv", "{adir}"], "--csv {adir}: is a folder, expected a file"),
    ],
)
def test_every_writing_command_checks_its_output_before_any_work(tmp_path, args, message):
    """The inputs do not exist: a command that read them before checking its output would name them instead."""
    paths = {"missing": tmp_path / "missing", "afile": tmp_path / "afile", "adir": tmp_path / "adir"}
    paths["afile"].write_text("mine")
    paths["adir"].mkdir()
    refused(invoke(*(arg.format(**paths) for arg in args)), message.format(**paths))
    assert paths["afile"].read_text() == "mine" and list(paths["adir"].iterdir()) == []


def test_evaluate_on_a_read_only_mount_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    save_references(sine_refs([20]), tmp_path / "refs")

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    argv = ["efficienttrack", "evaluate", "--system", "toy_system:make", "--refs", str(tmp_path / "refs")]
    monkeypatch.setattr(sys, "argv", [*argv, "--out", str(tmp_path / "eval")])
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Read-only file system" in err and not (tmp_path / "eval").exists()


# ------------------------------------------------------------------------------------ one writer at a time


def test_a_second_holder_of_a_folder_is_refused_until_the_first_lets_go(tmp_path):
    out = tmp_path / "run"
    with output_lock(out):
        assert out.is_dir() and list(tmp_path.iterdir()) == [out]  # the folder itself is locked: no lock file
        held = f"--out {tmp_path}/other/../run: another efficienttrack process is writing it; wait for it to finish"
        with pytest.raises(EfficientTrackError, match=held):
            with output_lock(tmp_path / "other" / ".." / "run"):  # another spelling of the same folder
                pass
    with output_lock(out):
        pass


def test_a_checkpoint_is_locked_through_a_file_beside_it_that_goes_with_the_lock(tmp_path):
    model = tmp_path / "model.pt"
    with output_lock(model, folder=False):
        assert lock_path(model) == tmp_path / ".model.pt.lock"
        assert lock_path(model).read_text() == f"{os.getpid()}\n"
        with pytest.raises(EfficientTrackError, match=f"another efficienttrack process \\(pid {os.getpid()}\\)"):
            with output_lock(model, "--model", folder=False):
                pass
    assert list(tmp_path.iterdir()) == []
    with output_lock(model, folder=False):
        pass


HOLD = """
import sys
from efficienttrack.core.fileio import output_lock
with output_lock(sys.argv[1], folder=sys.argv[2] == "folder"):
    print("locked", flush=True)
    sys.stdin.read()
"""


@pytest.mark.parametrize("kind", ["folder", "file"])
def test_the_lock_holds_between_processes_and_dies_with_its_holder(tmp_path, kind):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    out = tmp_path / "out"
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(out), kind], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        assert holder.stdout.readline() == "locked\n"
        with pytest.raises(EfficientTrackError, match="another efficienttrack process"):
            with output_lock(out, folder=kind == "folder"):
                pass
        holder.kill()  # however it ends, the kernel lets the lock go
        holder.wait(timeout=10)
    finally:
        holder.kill()
        holder.stdin.close()
        holder.stdout.close()
    with output_lock(out, folder=kind == "folder"):
        pass


def test_collect_and_train_model_refuse_a_folder_or_checkpoint_being_written(tmp_path):
    save_references(sine_refs([20, 20]), tmp_path / "refs")
    save_records(lag_records(n=2, T=40), tmp_path / "data")
    out, model = tmp_path / "collected", tmp_path / "model.pt"
    collect = ["collect", "--system", "toy_system:make", "--refs", tmp_path / "refs", "--out", out, "--passes", "1"]
    train = ["train-model", "--data", tmp_path / "data", "--out", model, "--preset", "tiny", "--steps", "2", "--device", "cpu"]
    with output_lock(out), output_lock(model, folder=False):
        refused(invoke(*collect), f"--out {out}: another efficienttrack process", "is writing it")
        refused(invoke(*train), f"--out {model}: another efficienttrack process")
        assert not model.exists() and not model.with_suffix(".state.pt").exists()
    for args in (collect, train):
        result = invoke(*args)
        assert result.exit_code == 0, result.output
    assert not lock_path(model).exists()  # released after the command
    with output_lock(out), output_lock(model, folder=False):
        pass


# ------------------------------------------------------------------------------ finished episodes are kept

FLAKY = {"fail_at_reset": None, "resets": 0}
"""The flaky system's switch: the reset (1-based) whose first step raises, and the resets counted."""


class FlakySystem(LagSystem):
    """A single-machine toy system whose valve sticks in episode ``FLAKY["fail_at_reset"]``."""

    def reset(self, q0):
        FLAKY["resets"] += 1
        return super().reset(q0)

    def step(self, q_ref):
        if FLAKY["resets"] == FLAKY["fail_at_reset"]:
            raise RuntimeError("valve 3 stuck")
        return super().step(q_ref)


def flaky() -> FlakySystem:
    """The ``module:callable`` entry point of the flaky system."""
    return FlakySystem(batched=False)


def test_evaluate_keeps_the_finished_episodes_of_a_failing_system_and_resumes(tmp_path, monkeypatch):
    save_references(sine_refs([20, 20, 20, 20], seed=3), tmp_path / "refs")
    args = ["evaluate", "--system", "test_outputs:flaky", "--refs", tmp_path / "refs", "--plots", "0"]
    monkeypatch.setitem(FLAKY, "resets", 0)
    monkeypatch.setitem(FLAKY, "fail_at_reset", 3)
    out = tmp_path / "eval"
    refused(
        invoke(*args, "--out", out),
        "evaluating pd: failed on episode(s) ref_02: RuntimeError: valve 3 stuck",
        f"2 of 4 episode(s) are recorded in {out / 'records' / '.pd.partial'}",
    )
    assert sorted(p.name for p in (out / "records" / ".pd.partial").iterdir()) == ["ref_00.npz", "ref_01.npz"]

    monkeypatch.setitem(FLAKY, "fail_at_reset", None)
    monkeypatch.setitem(FLAKY, "resets", 0)
    result = invoke(*args, "--out", out)  # the same command again goes on from ref_02
    assert result.exit_code == 0, result.output
    assert FLAKY["resets"] == 2
    assert sorted(p.name for p in (out / "records").iterdir()) == ["pd"]
    assert invoke(*args, "--out", tmp_path / "fresh").exit_code == 0
    resumed, fresh = (json.loads((tmp_path / name / "metrics.json").read_text()) for name in ("eval", "fresh"))
    assert resumed["pd"] == fresh["pd"] and resumed["pd"]["episodes"] == 4


def test_an_interrupted_evaluation_resumes_only_with_the_same_references(tmp_path, monkeypatch):
    refs = sine_refs([20, 20, 20], seed=3)
    save_references(refs, tmp_path / "refs3")
    save_references(refs[:2], tmp_path / "refs2")
    args = ["evaluate", "--system", "test_outputs:flaky", "--out", tmp_path / "eval", "--plots", "0"]
    monkeypatch.setitem(FLAKY, "resets", 0)
    monkeypatch.setitem(FLAKY, "fail_at_reset", 2)
    refused(invoke(*args, "--refs", tmp_path / "refs3"), "failed on episode(s) ref_01")
    monkeypatch.setitem(FLAKY, "fail_at_reset", None)
    refused(invoke(*args, "--refs", tmp_path / "refs2"), "evaluate.json: this folder holds an evaluation with another")
    result = invoke(*args, "--refs", tmp_path / "refs2", "--force")
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "eval" / "metrics.json").read_text())["pd"]["episodes"] == 2
    assert not Path(tmp_path / "eval" / "records" / ".pd.partial").exists()
