"""Damaged files of resumable work (identity files, stage markers, training states) give errors naming the file and the fix."""

import pytest
import torch

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.provenance import claim_folder
from efficienttrack.learn import checkpoints, training
from efficienttrack.learn.settings import TrainingSchedule
from efficienttrack.workflow.ledger import Ledger

IDENTITY = {"config": {"passes": 2}, "references": ["a", "b"]}


@pytest.mark.parametrize("name", ["collect.json", "run.json"])
def test_a_truncated_identity_file_says_how_to_recover(tmp_path, name):
    path = tmp_path / name
    claim_folder(path, IDENTITY, "other work")
    path.write_text(path.read_text()[:25])
    with pytest.raises(EfficientTrackError, match=rf"{name}: unreadable, truncated or corrupted .*restore it, or start"):
        claim_folder(path, IDENTITY, "other work")
    path.write_text("[1, 2]")
    with pytest.raises(EfficientTrackError, match=rf"{name}: holds a list, not a mapping of facts"):
        claim_folder(path, IDENTITY, "other work")
    path.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(EfficientTrackError, match="unreadable"):
        claim_folder(path, IDENTITY, "other work")


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ('{"seconds": 3', "unreadable"),
        ("", "unreadable"),
        ("[3]", "not a mapping of facts"),
        ('{"seconds": 3}', "missing log"),
    ],
)
def test_a_damaged_stage_marker_names_the_file_and_how_to_recover(tmp_path, text, problem):
    ledger = Ledger(tmp_path, 0.0)
    ledger.once("model", lambda: {"seconds": 3.0, "log": "logs/model"})
    assert ledger.done("model", keys=("seconds", "log")) == {"seconds": 3.0, "log": "logs/model"}
    (tmp_path / "stages" / "model.json").write_text(text)
    with pytest.raises(EfficientTrackError, match=rf"model.json: the marker of finished stage 'model' is {problem}") as caught:
        Ledger(tmp_path, 0.0).done("model", keys=("seconds", "log"))
    assert "delete that file to redo the stage on the next run, or start afresh with --force" in str(caught.value)


# ------------------------------------------------------------------------------------------ training states


class Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(3))


CFG = TrainingSchedule(steps=10, save_every=5)


def loop(checkpoint):
    net = Net()
    return training.TrainLoop("model", CFG, 10, net, torch.optim.SGD(net.parameters(), lr=0.1), 0, checkpoint, False)


@pytest.fixture
def state_file(tmp_path):
    """A training state saved after 5 of 10 steps."""
    path = tmp_path / "m.state.pt"
    first = loop(path)
    for step in first:
        first.record(step, 1.0 / (step + 1))
        if step == 5:
            break
    assert checkpoints.load_tensors(path)["step"] == 5
    return path


def test_a_good_state_resumes(state_file):
    resumed = loop(state_file)
    assert resumed.start == 5 and resumed.losses()[:5].tolist() == [1.0, 1 / 2, 1 / 3, 1 / 4, 1 / 5]


@pytest.mark.parametrize(
    ("change", "problem"),
    [
        (lambda s: s.pop("losses"), "unreadable training state .*losses"),
        (lambda s: s.pop("generator"), "unreadable training state .*generator"),
        (lambda s: s.update(step=11), "training state at step 11, outside 0 … 10"),
        (lambda s: s.update(step=-1), "training state at step -1"),
        (lambda s: s.update(step="5"), "training state at step '5'"),
        (lambda s: s.update(losses=torch.zeros(3)), "lacks the losses of its 5 steps"),
        (lambda s: s.update(losses=torch.full((10,), float("nan"))), "lacks the losses of its 5 steps"),
        (lambda s: s["module"].update(w=torch.full((3,), float("nan"))), "weights hold NaN/inf"),
    ],
)
def test_a_damaged_training_state_is_refused_naming_the_file_and_the_fix(state_file, change, problem):
    state = checkpoints.load_tensors(state_file)
    change(state)
    torch.save(state, state_file)
    with pytest.raises(EfficientTrackError, match=rf"m.state.pt: .*{problem}") as caught:
        loop(state_file)
    assert "delete it (--force on the command line) to start this training afresh" in str(caught.value)
