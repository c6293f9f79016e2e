import json
import shutil
import subprocess

import pytest
import torch

from efficienttrack import __version__
from efficienttrack.core import provenance
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.provenance import PROVENANCE_KEYS, claim_folder, describe_device, git_commit


def test_provenance_has_every_key():
    facts = provenance.provenance("cpu", 12.3456)
    assert tuple(facts) == PROVENANCE_KEYS
    assert facts["version"] == __version__ and facts["torch"] == torch.__version__
    assert facts["device"] == "cpu" and facts["wall_seconds"] == 12.35
    assert facts["created"].endswith("+00:00") and facts["created"][:2] == "20"
    assert provenance.provenance()["device"] is None and provenance.provenance()["wall_seconds"] is None
    assert describe_device(torch.device("cpu")) == "cpu" and describe_device(None) is None


def test_git_commit_is_null_outside_a_checkout(tmp_path, monkeypatch):
    assert git_commit(tmp_path) is None
    assert git_commit(tmp_path / "missing") is None
    assert git_commit() is not None or not (provenance.PACKAGE_DIR.parents[1] / ".git").exists()
    monkeypatch.setattr(provenance, "PACKAGE_DIR", tmp_path)  # the package installed outside any checkout
    assert provenance.provenance()["git_commit"] is None
    monkeypatch.setenv("PATH", str(tmp_path))  # no git binary at all
    assert git_commit(tmp_path) is None


@pytest.mark.skipif(shutil.which("git") is None, reason="no git binary")
def test_git_commit_of_a_tracked_folder_only(tmp_path):
    def git(*args):
        return subprocess.run(["git", "-C", str(tmp_path), *args], capture_output=True, text=True, check=True).stdout.strip()

    git("init", "-q")
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "mod.py").write_text("x = 1\n")
    (tmp_path / "venv").mkdir()
    (tmp_path / "venv" / "installed.py").write_text("x = 1\n")
    git("add", "pkg")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "pkg")
    assert git_commit(tmp_path / "pkg") == git("rev-parse", "HEAD")
    assert git_commit(tmp_path / "venv") is None  # inside the checkout, but not part of it


@pytest.mark.skipif(shutil.which("git") is None, reason="no git binary")
def test_git_dirty_says_whether_the_tracked_sources_changed(tmp_path):
    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], capture_output=True, check=True)

    assert provenance.git_dirty(tmp_path) is None  # not a checkout
    git("init", "-q")
    (tmp_path / "mod.py").write_text("x = 1\n")
    git("add", "mod.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "mod")
    (tmp_path / "notes.txt").write_text("untracked files do not count\n")
    assert provenance.git_dirty(tmp_path) is False
    (tmp_path / "mod.py").write_text("x = 2\n")
    assert provenance.git_dirty(tmp_path) is True


def test_provenance_records_the_command_and_the_versions(monkeypatch):
    import platform
    import sys

    import numpy

    monkeypatch.setattr(sys, "argv", ["efficienttrack", "run", "--out", "runs/my run"])
    facts = provenance.provenance()
    assert facts["command"] == "efficienttrack run --out 'runs/my run'"
    assert facts["python"] == platform.python_version() and facts["numpy"] == numpy.__version__


def test_claim_folder_writes_identity_with_provenance_and_refuses_other_work(tmp_path):
    path = tmp_path / "run.json"
    claim_folder(path, {"seed": 1}, "other work")
    written = json.loads(path.read_text())
    assert written["seed"] == 1 and set(written["provenance"]) == set(PROVENANCE_KEYS)
    claim_folder(path, {"seed": 1}, "other work")  # the same work resumes: provenance is not compared
    with pytest.raises(EfficientTrackError, match=r"run.json: other work \(seed: 1 here, 2 now\)"):
        claim_folder(path, {"seed": 2}, "other work")
    nested = {"config": {"model": {"history": 5, "hidden": 128}}, "references": ["a", "b"]}
    claim_folder(tmp_path / "nested.json", nested, "other work")
    changed = {"config": {"model": {"history": 10, "hidden": 128}, "rounds": 2}, "references": ["a", "b"]}
    with pytest.raises(EfficientTrackError) as caught:
        claim_folder(tmp_path / "nested.json", changed, "other work")
    assert str(caught.value).endswith("(config.model.history: 5 here, 10 now; config.rounds: absent here, 2 now)")
    path.write_text("{not json")
    with pytest.raises(EfficientTrackError, match="unreadable"):
        claim_folder(path, {"seed": 1}, "other work")
