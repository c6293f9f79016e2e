"""Fitting a run into minutes (efficienttrack.time_budget): the factor's arithmetic, and a run that trains fewer steps."""

import json
from dataclasses import replace

import pytest
from typer.testing import CliRunner

from efficienttrack import time_budget
from efficienttrack.cli import app
from efficienttrack.config import RunConfig
from efficienttrack.dynamics import ModelConfig
from efficienttrack.errors import EfficientTrackError
from efficienttrack.pipeline import run_pipeline
from efficienttrack.policy import PolicyConfig
from efficienttrack.time_budget import RESERVE, StepTimes, budget_scale, step_seconds
from efficienttrack.training import read_scalars
from toy_system import TOY, TOY_CFG, toy_split

CFG = RunConfig(model=ModelConfig(steps=100), policy=PolicyConfig(steps=50), rounds=3, warm_budget=0.5, time_budget=10)
TIMES = StepTimes(model=0.1, policy=0.2, windows=1000)


def test_the_factor_fits_every_rounds_training_into_what_is_left():
    # round 1: 100 × 0.1 + 50 × 0.2 = 20 s; rounds 2 and 3 half of it each: 40 s in all
    scale, training = budget_scale(CFG, TIMES, seconds_left=30, other_seconds=4)
    assert training == pytest.approx(40) and scale == pytest.approx((30 * (1 - RESERVE) - 4) / 40)
    assert budget_scale(CFG, TIMES, seconds_left=3600, other_seconds=4)[0] == 1.0  # never more steps than configured
    epochs = replace(CFG, model=ModelConfig(steps=None, epochs=2, batch_size=100))  # 2 passes over 1000 windows: 20 steps
    assert budget_scale(epochs, TIMES, seconds_left=3600, other_seconds=0)[1] == pytest.approx((20 * 0.1 + 50 * 0.2) * 2)


def test_a_budget_too_small_to_train_is_refused():
    with pytest.raises(EfficientTrackError, match=r"--time-budget 10 min: 0.0 min would be left for training"):
        budget_scale(CFG, TIMES, seconds_left=5, other_seconds=4)


def test_step_seconds_take_the_difference_of_two_short_trainings_after_a_warm_up():
    class Result:
        def __init__(self, seconds):
            self.seconds = seconds

    steps_seen = []

    def train(cfg):
        steps_seen.append(cfg.steps)
        return Result(3.0 + 0.25 * cfg.steps + (5.0 if len(steps_seen) == 1 else 0.0))  # setup, steps, a slow first call

    per_step, longer = step_seconds(train, ModelConfig(steps=None, epochs=5))
    assert per_step == pytest.approx(0.25) and steps_seen == list(time_budget.PROBE_STEPS)
    assert longer.seconds == 3.0 + 0.25 * time_budget.PROBE_STEPS[-1]


def test_a_run_with_a_budget_trains_the_scaled_steps_and_keeps_the_factor(tmp_path, monkeypatch):
    monkeypatch.setattr(time_budget, "measure_step_times", lambda cfg, records, device: StepTimes(0.05, 0.1, 500))
    cfg = replace(TOY_CFG, time_budget=0.5)  # 30 s; the configured training "takes" 300 × 0.05 + 300 × 0.1 = 45 s
    result = run_pipeline(TOY, *toy_split(), tmp_path, cfg)
    facts = json.loads((tmp_path / "stages" / "time_budget.json").read_text())
    assert 0.05 < facts["scale"] < 1 and facts["unscaled_training_seconds"] == pytest.approx(45)
    steps = round(TOY_CFG.model.steps * facts["scale"])
    assert len(read_scalars(tmp_path / "logs" / "model")["train/loss"][0]) == steps
    assert result.metrics["config"]["model"]["steps"] == steps
    assert json.loads((tmp_path / "config.json").read_text())["time_budget"] == 0.5

    def measured_again(*args):
        raise AssertionError("a rerun measured the step times again")

    monkeypatch.setattr(time_budget, "measure_step_times", measured_again)
    again = run_pipeline(TOY, *toy_split(), tmp_path, cfg)
    assert "time_budget" in again.skipped and again.metrics["config"]["model"]["steps"] == steps


def test_the_cli_option_sets_the_budget_and_refuses_a_bad_one(tmp_path):
    result = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "d"), "--time-budget", "0"])
    assert isinstance(result.exception, EfficientTrackError) and "time_budget must be a number > 0" in str(result.exception)
