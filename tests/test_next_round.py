"""Rounds of continual learning: warm starts (library and --init-model/--init-policy) and the `round` command."""

import dataclasses
import json

import pytest
import torch
from typer.testing import CliRunner

from efficienttrack.cli import app
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.data.metrics import compute_metrics
from efficienttrack.data.records import save_records
from efficienttrack.deploy.runtime import track
from efficienttrack.learn.dynamics import load_model, model_error, save_model, train_model
from efficienttrack.learn.policy import load_policy, save_policy, train_policy
from efficienttrack.learn.settings import MODEL_PRESETS, POLICY_PRESETS
from efficienttrack.learn.training import read_scalars
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.workflow.collect import CollectConfig, collect
from efficienttrack.workflow.next_round import ROUND_JSON, continued_config, next_round
from test_dynamics import lag_records
from toy_system import make, sine_refs

STILL = 1e-9
"""A learning rate so small that a step leaves the weights where they were (to float precision)."""


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "200"})


@pytest.fixture(scope="module")
def records():
    return lag_records(n=4, T=60)


@pytest.fixture(scope="module")
def model(records):
    """Short training: it predicts some 20 times better than an untrained model, what a warm start is seen to keep."""
    return train_model(dataclasses.replace(MODEL_PRESETS["tiny"], steps=60), records, "cpu", progress=False).model


@pytest.fixture(scope="module")
def policy(model, records):
    """Barely trained: the tests look at its weights and settings, not at how well it tracks."""
    return train_policy(dataclasses.replace(POLICY_PRESETS["tiny"], steps=20), model, records, "cpu", progress=False).policy


def assert_same_state(a: torch.nn.Module, b: torch.nn.Module, atol: float) -> None:
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
        torch.testing.assert_close(x, y, rtol=0, atol=atol, msg=name)


def test_continued_config_keeps_the_sizes_and_takes_the_schedule():
    network = dataclasses.replace(MODEL_PRESETS["tiny"], history=3)
    cfg = continued_config(MODEL_PRESETS["cpu"], network)
    assert (cfg.hidden, cfg.layers, cfg.horizon, cfg.history) == (32, 2, 4, 3)
    assert (cfg.steps, cfg.batch_size, cfg.lr) == (MODEL_PRESETS["cpu"].steps, 256, MODEL_PRESETS["cpu"].lr)
    policy_cfg = continued_config(POLICY_PRESETS["cpu"], POLICY_PRESETS["tiny"])
    assert (policy_cfg.hidden, policy_cfg.horizon, policy_cfg.steps) == (32, 4, POLICY_PRESETS["cpu"].steps)
    with pytest.raises(EfficientTrackError, match="cannot continue"):
        continued_config(POLICY_PRESETS["cpu"], network)


def test_warm_start_begins_at_the_given_weights(model, policy, records):
    still_model = dataclasses.replace(MODEL_PRESETS["tiny"], steps=1, lr=STILL)
    warm = train_model(still_model, records, "cpu", seed=5, progress=False, init=model).model
    assert_same_state(warm, model, atol=1e-6)
    cold = train_model(still_model, records, "cpu", seed=5, progress=False).model
    assert model_error(cold, records, 10).mpe_deg > 5 * model_error(warm, records, 10).mpe_deg
    still_policy = dataclasses.replace(POLICY_PRESETS["tiny"], steps=1, lr=STILL)
    warm_policy = train_policy(still_policy, model, records, "cpu", seed=5, progress=False, init=policy).policy
    assert_same_state(warm_policy, policy, atol=1e-6)
    with pytest.raises(EfficientTrackError, match="sizes do not match"):
        train_model(dataclasses.replace(still_model, hidden=16), records, "cpu", progress=False, init=model)


def test_cli_init_model_and_init_policy(model, policy, records, tmp_path):
    data = tmp_path / "data"
    save_records(records, data)
    save_model(model, tmp_path / "m0.pt")
    save_policy(policy, tmp_path / "p0.pt")
    common = ("--data", data, "--device", "cpu", "--steps", "1")
    # a cpu-preset schedule continues the tiny network: its sizes, the preset's steps
    result = invoke("train-model", *common, "--out", tmp_path / "m1.pt", "--init-model", tmp_path / "m0.pt")
    assert result.exit_code == 0, result.output
    warm = load_model(tmp_path / "m1.pt")
    assert (warm.cfg.hidden, warm.cfg.steps, warm.cfg.batch_size) == (model.cfg.hidden, 1, MODEL_PRESETS["cpu"].batch_size)
    assert model_error(warm, records, 10).mpe_deg < 2 * model_error(model, records, 10).mpe_deg
    result = invoke(
        "train-policy",
        *common,
        "--model",
        tmp_path / "m0.pt",
        "--out",
        tmp_path / "p1.pt",
        "--init-policy",
        tmp_path / "p0.pt",
    )
    assert result.exit_code == 0, result.output
    assert load_policy(tmp_path / "p1.pt").cfg.hidden == policy.cfg.hidden
    # a checkpoint of the wrong kind or a missing one: the option is named
    wrong = invoke("train-model", *common, "--out", tmp_path / "m2.pt", "--init-model", tmp_path / "p0.pt")
    assert isinstance(wrong.exception, EfficientTrackError) and "--init-model" in str(wrong.exception)
    missing = invoke(
        "train-policy",
        *common,
        "--model",
        tmp_path / "m0.pt",
        "--out",
        tmp_path / "p2.pt",
        "--init-policy",
        tmp_path / "no.pt",
    )
    assert isinstance(missing.exception, EfficientTrackError) and "--init-policy" in str(missing.exception)


def test_next_round_library_reports_and_refuses_no_data(model, policy, records):
    schedule = dataclasses.replace(MODEL_PRESETS["tiny"], steps=60)
    result = next_round(model, policy, records[:2], records[2:], schedule, device="cpu", progress=False, held_out=records[2:])
    report = result.report
    assert (report.new_episodes, report.old_episodes, report.model_steps) == (2, 2, 60)
    assert report.model_mpe_after_deg < report.model_mpe_before_deg * 1.5
    assert report.held_out_mpe_after_deg is not None
    assert report.recorded_mae_deg == pytest.approx(compute_metrics(records[:2])["mae_deg"])
    with pytest.raises(EfficientTrackError, match="no new episodes"):
        next_round(model, policy, [], records, device="cpu", progress=False)


@pytest.mark.slow
def test_round_on_a_toy_system_lowers_its_tracking_error(tmp_path):
    system = BatchedSystem(make())
    train_refs, test_refs = sine_refs([100] * 6, seed=0), sine_refs([100] * 4, seed=1)
    pd_data = collect(system, train_refs, CollectConfig(passes=4, sigma_max=0.05, seed=0), progress=False).records
    model1 = train_model(dataclasses.replace(MODEL_PRESETS["tiny"], steps=150), pd_data, "cpu", progress=False).model
    # round 1's policy: barely trained, deployed and recorded
    policy1 = train_policy(
        dataclasses.replace(POLICY_PRESETS["tiny"], steps=15), model1, pd_data, "cpu", progress=False
    ).policy
    save_records(track(system, policy1, train_refs, progress=False), tmp_path / "round1_logs")
    save_model(model1, tmp_path / "model1.pt")
    save_policy(policy1, tmp_path / "policy1.pt")
    out = tmp_path / "round2"
    args = (
        "round",
        "--model",
        tmp_path / "model1.pt",
        "--policy",
        tmp_path / "policy1.pt",
        "--data",
        tmp_path / "round1_logs",
    )
    result = invoke(
        *args, "--out", out, "--preset", "tiny", "--steps-model", "100", "--steps-policy", "100", "--device", "cpu"
    )
    assert result.exit_code == 0, result.output
    assert "model 20-step MPE on the new episodes" in result.output
    report = json.loads((out / ROUND_JSON).read_text())
    assert report["new_episodes"] == 6 and report["old_episodes"] == 0 and report["policy_steps"] == 100
    assert report["predicted_after_deg"] < report["predicted_before_deg"]
    assert report["provenance"]["version"] and report["inputs"]["policy"] == str((tmp_path / "policy1.pt").resolve())

    def mae(policy):
        return compute_metrics(track(system, policy, test_refs, progress=False))["mae_deg"]

    before, after = mae(policy1), mae(load_policy(out / "policy.pt"))
    assert after < 0.7 * before, (before, after)
    # a finished round is refused without --force, and redone with it
    again = invoke(*args, "--out", out, "--preset", "tiny", "--steps-model", "100", "--steps-policy", "100", "--device", "cpu")
    assert isinstance(again.exception, EfficientTrackError) and "--force" in str(again.exception)
    forced = invoke(*args, "--out", out, "--preset", "tiny", "--steps-model", "2", "--steps-policy", "2", "--force")
    assert forced.exit_code == 0, forced.output
    assert json.loads((out / ROUND_JSON).read_text())["model_steps"] == 2


def test_interrupted_round_resumes(model, policy, records, tmp_path):
    out = tmp_path / "round"
    ramped = {"steps": 40, "warmup": 0.1}  # the command's: a later round's learning rates ramp up (round_warmup)
    schedules = dataclasses.replace(MODEL_PRESETS["tiny"], **ramped), dataclasses.replace(POLICY_PRESETS["tiny"], **ramped)
    next_round(model, policy, records, (), *schedules, device="cpu", progress=False, out_dir=out)
    finished = load_policy(out / "policy.pt")
    (out / ROUND_JSON).unlink()
    (out / "policy.pt").unlink()
    save_records(records, tmp_path / "data")
    save_model(model, tmp_path / "m.pt")
    save_policy(policy, tmp_path / "p.pt")
    result = invoke(
        "round", "--model", tmp_path / "m.pt", "--policy", tmp_path / "p.pt", "--data", tmp_path / "data", "--out", out,
        "--preset", "tiny", "--steps-model", "40", "--steps-policy", "40", "--device", "cpu",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert_same_state(load_policy(out / "policy.pt"), finished, atol=0)


def test_round_trains_the_warm_budget_of_the_preset_with_its_learning_rates_ramped_by_default(
    model, policy, records, tmp_path
):
    save_records(records, tmp_path / "data")
    save_model(model, tmp_path / "m.pt")
    save_policy(policy, tmp_path / "p.pt")
    args = ("round", "--model", tmp_path / "m.pt", "--policy", tmp_path / "p.pt", "--data", tmp_path / "data")
    result = invoke(*args, "--out", tmp_path / "r", "--preset", "tiny", "--warm-budget", "0.1", "--device", "cpu")
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "r" / ROUND_JSON).read_text())
    assert report["model_steps"] == round(0.1 * MODEL_PRESETS["tiny"].steps)
    assert report["policy_steps"] == round(0.1 * POLICY_PRESETS["tiny"].steps)
    for part, preset in (("model", MODEL_PRESETS["tiny"]), ("policy", POLICY_PRESETS["tiny"])):  # as `run`'s later rounds
        _, lr = read_scalars(tmp_path / "r" / f"{part}.logs")["train/lr"]
        ramp = 0.1 * report[f"{part}_steps"]  # round_warmup 0.1
        assert lr[0] == pytest.approx(preset.lr / ramp, rel=0.05) and max(lr) == pytest.approx(preset.lr, rel=0.05)
    flat = invoke(*args, "--out", tmp_path / "flat", "--preset", "tiny", "--warm-budget", "0.1", "--set", "round_warmup=0")
    assert flat.exit_code == 0, flat.output
    assert read_scalars(tmp_path / "flat" / "model.logs")["train/lr"][1][0] == pytest.approx(MODEL_PRESETS["tiny"].lr)
    refused = invoke(*args, "--out", tmp_path / "r0", "--warm-budget", "0")
    assert "--warm-budget 0.0: warm_budget must be a finite number > 0" in str(refused.exception)  # one line in main()
