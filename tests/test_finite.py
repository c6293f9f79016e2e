"""Nothing non-finite is trained, saved or reported: NaN losses stop training, JSON has no NaN, fallbacks are not results."""

import json
import warnings

import numpy as np
import pytest
import torch
from rich.console import Console

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import finite_json, write_json
from efficienttrack.data.records import EpisodeRecord, load_record
from efficienttrack.learn import checkpoints, training
from efficienttrack.learn.dynamics import ClosedLoopModel, load_model, save_model, train_model
from efficienttrack.learn.settings import MODEL_PRESETS, TrainingSchedule
from efficienttrack.systems.spec import SystemSpec
from efficienttrack.workflow import evaluation
from efficienttrack.workflow.stages import RunLog
from test_dynamics import lag_records
from test_records import make_record

TINY = MODEL_PRESETS["tiny"]

# ---------------------------------------------------------------------------------------------- training


def test_a_record_with_absurd_velocities_is_refused_on_load_naming_the_episode(tmp_path):
    record = make_record(name="wild")
    record.qd[5, 1] = 1e300
    path = record.save(tmp_path / "wild.npz")
    with pytest.raises(EfficientTrackError, match=r"wild.npz: field 'qd' reaches 1e\+300 rad/s at the arm"):
        load_record(path)


def test_a_nan_loss_stops_training_naming_the_step_and_what_to_check(tmp_path):
    records = lag_records(n=2, T=40)
    records[0] = EpisodeRecord(**{**vars(records[0]), "qd": records[0].qd * 1e300})  # in memory, past the loaders' check
    checkpoint = tmp_path / "m.state.pt"
    with pytest.raises(EfficientTrackError, match=r"model training stopped: the loss is nan at step 1 of 300 .*lower lr"):
        train_model(TINY, records, "cpu", progress=False, checkpoint=checkpoint)
    assert not checkpoint.exists()


class Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(3))


def test_a_nan_loss_keeps_the_last_good_training_state(tmp_path):
    cfg = TrainingSchedule(steps=10, save_every=5)
    net = Net()
    checkpoint = tmp_path / "state.pt"
    loop = training.TrainLoop("model", cfg, 10, net, torch.optim.SGD(net.parameters()), 0, checkpoint, False)
    with pytest.raises(EfficientTrackError, match=rf"at step 7 of 10 .* the training state in {checkpoint} is kept"):
        for step in loop:
            loss = 1.0 if step < 6 else float("nan")
            if step == 6:
                net.w.data.fill_(float("nan"))
            loop.record(step, loss)
    state = checkpoints.load_tensors(checkpoint)
    assert state["step"] == 5 and torch.equal(state["module"]["w"], torch.ones(3))


def test_nan_weights_are_never_saved_nor_loaded(tmp_path):
    model = ClosedLoopModel(TINY)
    save_model(model, tmp_path / "good.pt")
    with torch.no_grad():
        model.g_theta.body[0].weight[0, 0] = float("nan")
    with pytest.raises(EfficientTrackError, match=r"good.pt: closed_loop_model not saved: the weights hold NaN/inf .*body.0"):
        save_model(model, tmp_path / "good.pt")
    assert torch.isfinite(load_model(tmp_path / "good.pt").g_theta.body[0].weight).all()  # the good file is kept
    torch.save(model.state_dict(), tmp_path / "bad.pt")
    meta = json.loads((tmp_path / "good.json").read_text())
    (tmp_path / "bad.json").write_text(json.dumps({**meta, "weights_sha256": None}))
    with pytest.raises(EfficientTrackError, match="bad.pt: weights hold NaN/inf values"):
        load_model(tmp_path / "bad.pt")


# -------------------------------------------------------------------------------------------------- JSON


def test_json_files_hold_null_for_non_finite_figures_with_a_warning(tmp_path):
    with pytest.warns(UserWarning, match=r"m.json: not finite, written as null: mpe_deg, per_joint\[1\]"):
        path = write_json(tmp_path / "m.json", {"mpe_deg": float("nan"), "per_joint": [1.0, float("inf")], "ok": 2})
    assert json.loads(path.read_text(), parse_constant=lambda name: pytest.fail(name)) == {
        "mpe_deg": None,
        "per_joint": [1.0, None],
        "ok": 2,
    }
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert finite_json({"a": (1.0, np.float64(2.5))}, "x") == {"a": [1.0, 2.5]}


# -------------------------------------------------------------------------------------------- fallbacks


def _records(fallbacks):
    records = [make_record(seed=i, name=f"ep{i}") for i in range(2)]
    for record, count in zip(records, fallbacks, strict=True):
        record.meta["fallbacks"] = count
    return records


def test_fallback_share_warns_above_the_limit():
    assert evaluation.fallback_share(None) == (None, None)
    assert evaluation.fallback_share(_records([0, 3])) == (0.05, None)
    share, warning = evaluation.fallback_share(_records([30, 30]))
    assert share == 1.0 and "on 100% of the policy's steps" in warning and "not EfficientTrack's" in warning


def test_results_mostly_fallen_back_are_not_reported_as_efficienttrack(tmp_path):
    console = Console(record=True, width=200)
    refs = [type("Ref", (), {"name": f"ep{i}"})() for i in range(2)]
    pd, et = _records([0, 0]), _records([30, 25])
    metrics = evaluation.results(
        SystemSpec(), refs, pd, et, interaction_steps=None, train_seconds=None, model=None, policy_path="p.pt",
        config=None, device=None, wall_seconds=1.0,
    )  # fmt: skip
    assert metrics["fallback_share"] == pytest.approx(55 / 60, abs=1e-4) and "not EfficientTrack's" in metrics["warning"]
    evaluation.publish(tmp_path, RunLog(tmp_path, console), metrics, refs, pd, et, 0, "evaluation")
    shown = console.export_text()
    assert "guard fallback (not EfficientTrack)" in shown and "warning: the guard fell back" in shown
    assert "EfficientTrack " not in shown.replace("(not EfficientTrack)", "").replace("EfficientTrack's", "")
    assert json.loads((tmp_path / "metrics.json").read_text())["warning"] == metrics["warning"]
