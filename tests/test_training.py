"""The training log: scalars per optimizer step to CSV and TensorBoard, held-out figures at intervals, resume."""

import dataclasses

import numpy as np
import pytest

from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.settings import plain_form
from efficienttrack.learn import dynamics, policy, training
from efficienttrack.learn.settings import MODEL_PRESETS, POLICY_PRESETS, ModelConfig, PolicyConfig
from efficienttrack.learn.training import LOSS_TAG, LR_TAG, SCALARS_CSV, held_out_subset, read_scalars
from test_dynamics import lag_records

CFG = dataclasses.replace(MODEL_PRESETS["tiny"], steps=30, save_every=10, eval_every=10)


@pytest.fixture(scope="module")
def data():
    records = lag_records(n=3, T=40)
    return records[:2], records[2:]


def train(cfg, data, log_dir, checkpoint=None):
    train_records, held_out = data
    return dynamics.train_model(
        cfg, train_records, device="cpu", progress=False, checkpoint=checkpoint, log_dir=log_dir, held_out=held_out
    )


def test_every_step_logs_loss_and_lr_and_held_out_error_at_the_interval(data, tmp_path):
    result = train(CFG, data, tmp_path / "logs")
    scalars = read_scalars(tmp_path / "logs")
    assert set(scalars) == {LOSS_TAG, LR_TAG, dynamics.HELD_OUT_TAG}
    steps, losses = scalars[LOSS_TAG]
    np.testing.assert_array_equal(steps, np.arange(1, 31))
    np.testing.assert_allclose(losses, result.losses, rtol=1e-6)
    steps, lr = scalars[LR_TAG]
    np.testing.assert_array_equal(steps, np.arange(1, 31))
    assert lr[0] == pytest.approx(CFG.lr) and np.all(np.diff(lr) < 0)  # cosine decay
    steps, mpe = scalars[dynamics.HELD_OUT_TAG]
    np.testing.assert_array_equal(steps, [10, 20, 30])
    assert mpe[-1] == pytest.approx(dynamics.model_error(result.model, data[1]).mpe_deg, rel=1e-5)
    assert mpe[-1] < mpe[0]
    assert list((tmp_path / "logs").glob("events.out.tfevents.*"))


def test_a_warmup_ramps_the_learning_rate_up_over_its_share_of_the_steps_then_the_cosine_takes_over(data, tmp_path):
    train(dataclasses.replace(CFG, warmup=0.2), data, tmp_path / "logs")  # 30 steps: 6 of ramp
    _, lr = read_scalars(tmp_path / "logs")[LR_TAG]
    cosine = CFG.lr * 0.5 * (1 + np.cos(np.pi * np.arange(30) / 30))
    np.testing.assert_allclose(lr, cosine * np.minimum(1, np.arange(1, 31) / 6), rtol=1e-5)
    assert "warmup" not in plain_form(CFG)  # a config without one is written as before the field existed


def test_default_interval_is_a_tenth_of_the_run_and_always_ends_the_run(data, tmp_path):
    train(dataclasses.replace(CFG, steps=25, eval_every=None), data, tmp_path / "a")
    np.testing.assert_array_equal(read_scalars(tmp_path / "a")[dynamics.HELD_OUT_TAG][0], [3, 6, 9, 12, 15, 18, 21, 24, 25])
    train(dataclasses.replace(CFG, steps=5), (data[0], []), tmp_path / "b")
    assert set(read_scalars(tmp_path / "b")) == {LOSS_TAG, LR_TAG}  # no held-out episodes: no held-out figure


def test_tensorboard_events_hold_the_same_scalars(data, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    train(CFG, data, tmp_path / "logs")
    events = EventAccumulator(str(tmp_path / "logs")).Reload()
    assert set(events.Tags()["scalars"]) == {LOSS_TAG, LR_TAG, dynamics.HELD_OUT_TAG}
    steps, mpe = read_scalars(tmp_path / "logs")[dynamics.HELD_OUT_TAG]
    logged = events.Scalars(dynamics.HELD_OUT_TAG)
    assert [e.step for e in logged] == steps.tolist()
    np.testing.assert_allclose([e.value for e in logged], mpe, rtol=1e-6)


def test_resumed_run_writes_the_same_csv_as_an_uninterrupted_one(data, tmp_path, monkeypatch):
    train(CFG, data, tmp_path / "full")
    original = training.TrainLoop.record

    def crash_at_26(self, step, loss):
        original(self, step, loss)
        if step == 25:  # rows of steps 21 … 26 are written after the state saved at step 20
            raise KeyboardInterrupt

    monkeypatch.setattr(training.TrainLoop, "record", crash_at_26)
    with pytest.raises(KeyboardInterrupt):
        train(CFG, data, tmp_path / "resumed", tmp_path / "state.pt")
    assert max(read_scalars(tmp_path / "resumed")[LOSS_TAG][0]) == 26
    with (tmp_path / "resumed" / SCALARS_CSV).open("a") as f:
        f.write("27,train/lo")  # a line torn by the crash
    monkeypatch.setattr(training.TrainLoop, "record", original)
    train(CFG, data, tmp_path / "resumed", tmp_path / "state.pt")
    assert (tmp_path / "resumed" / SCALARS_CSV).read_text() == (tmp_path / "full" / SCALARS_CSV).read_text()
    # a finished run run again changes nothing
    train(CFG, data, tmp_path / "resumed", tmp_path / "state.pt")
    assert (tmp_path / "resumed" / SCALARS_CSV).read_text() == (tmp_path / "full" / SCALARS_CSV).read_text()


def test_policy_logs_its_held_out_tracking_error(data, tmp_path):
    model = train(dataclasses.replace(CFG, steps=10), data, None).model
    cfg = dataclasses.replace(POLICY_PRESETS["tiny"], steps=20, eval_every=10)
    result = policy.train_policy(cfg, model, data[0], device="cpu", progress=False, log_dir=tmp_path, held_out=data[1])
    scalars = read_scalars(tmp_path)
    np.testing.assert_array_equal(scalars[LOSS_TAG][0], np.arange(1, 21))
    steps, error = scalars[policy.HELD_OUT_TAG]
    np.testing.assert_array_equal(steps, [10, 20])
    expected = policy.predicted_tracking_error(model, data[1], result.policy, cfg.horizon).mae_deg
    assert error[-1] == pytest.approx(expected, rel=1e-5)


def test_held_out_subset_is_evenly_spaced_and_bounded():
    records = lag_records(n=10, T=30)
    for i, record in enumerate(records):
        record.meta["i"] = i
    assert [r.meta["i"] for r in held_out_subset(records, 10**6)] == list(range(10))
    assert [r.meta["i"] for r in held_out_subset(records, 95)] == [0, 4, 9]  # 3 × 30 steps ≤ 95
    assert [r.meta["i"] for r in held_out_subset(records, 1)] == [0] and held_out_subset([], 100) == []


def test_read_scalars_refuses_other_files(tmp_path):
    with pytest.raises(EfficientTrackError, match="no such scalar log"):
        read_scalars(tmp_path)
    (tmp_path / SCALARS_CSV).write_text("a,b\n")
    with pytest.raises(EfficientTrackError, match="not a scalar log"):
        read_scalars(tmp_path)
    (tmp_path / SCALARS_CSV).write_text("step,tag,value\n1,train/loss,x\n")
    with pytest.raises(EfficientTrackError, match="line 2"):
        read_scalars(tmp_path)


def test_config_checks_eval_every_and_old_configs_load():
    with pytest.raises(EfficientTrackError, match=r"eval_every must be an integer in \[1, 10000000\]"):
        ModelConfig(eval_every=0)
    with pytest.raises(EfficientTrackError, match=r"eval_every must be an integer in \[1, 10000000\]"):
        PolicyConfig(eval_every=0)
    old = {k: v for k, v in dataclasses.asdict(MODEL_PRESETS["tiny"]).items() if k != "eval_every"}
    assert ModelConfig.from_dict(old).eval_every is None


def test_a_schedule_scales_its_steps_or_epochs_and_keeps_the_rest():
    cfg = ModelConfig(steps=1000, lr=3e-4)
    assert cfg.scaled(0.5) == dataclasses.replace(cfg, steps=500)
    assert ModelConfig(steps=None, epochs=3).scaled(0.1).epochs == 1  # at least one
    with pytest.raises(EfficientTrackError, match="scaled by a share > 0"):
        cfg.scaled(0)


@pytest.mark.parametrize(
    "content",
    [
        b"",
        b"X\xe8\xb3\xfb",  # torch raised struct.error
        b"K\xfdh+\xac+\x10\xddr\x8b>",  # KeyError
        b"qJ\x9bR\x8bicc!\xa4a\xb5^\xf5[{\xea\xfd\x80\x9a\x9a\x9e\x92[y\xa64/\xa0\xfd\xb8\xb2\x94\xd9\x7f",  # IndexError
        np.random.default_rng(0).bytes(1000),
    ],
)
@pytest.mark.parametrize("load", [dynamics.load_model, policy.load_policy])
def test_random_bytes_as_a_checkpoint_are_one_clear_error(tmp_path, content, load):
    path = tmp_path / "random.pt"
    path.write_bytes(content)
    path.with_suffix(".json").write_text(
        '{"kind": "%s", "config": {}}' % ("closed_loop_model" if load is dynamics.load_model else "adjustment_policy")
    )
    with pytest.raises(EfficientTrackError, match=r"random.pt: (empty file|refused to load: not a plain tensor)") as info:
        load(path)
    assert "\n" not in str(info.value)
